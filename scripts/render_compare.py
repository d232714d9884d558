"""Render a point cloud and several meshes of it side by side (same camera), as one PNG.

    python scripts/render_compare.py SCAN OUT.png MESH1.ply:label MESH2.npz:label ... [--y-up]

Meshes are PLY files or ``.npz`` files with arrays ``v`` (V, 3) and ``f`` (F, 3). Each panel gets its
label written under it by PIL. Uses the rasteriser of ``scripts/render_scan.py`` (no GPU, no Blender).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_scan import Camera, render_mesh, render_points  # noqa: E402

from nkf_model.io.files import read_point_cloud  # noqa: E402


def _load_mesh(path: str):
    if path.endswith(".npz"):
        d = np.load(path)
        return d["v"].astype(float), d["f"].astype(np.int64)
    from plyfile import PlyData

    ply = PlyData.read(path)
    v = ply["vertex"]
    return (np.stack([v["x"], v["y"], v["z"]], axis=1).astype(float),
            np.stack(ply["face"]["vertex_indices"]).astype(np.int64))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scan")
    ap.add_argument("out")
    ap.add_argument("meshes", nargs="+", help="PATH:LABEL")
    ap.add_argument("--y-up", action="store_true", help="the data's up axis is +y (Stanford scans)")
    ap.add_argument("--size", type=int, nargs=2, default=(480, 420))
    ap.add_argument("--view", type=float, nargs=3, default=(0.2, -1.25, 0.5), help="eye direction from the centre")
    a = ap.parse_args(argv)
    cloud = read_point_cloud(a.scan)
    up = (lambda p: np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)) if a.y_up else (lambda p: p)  # noqa: E731
    pts = up(np.asarray(cloud.points, float))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    target = 0.5 * (lo + hi)
    cam = Camera(target + np.asarray(a.view) * float((hi - lo).max()), target, *a.size)
    panels = [(render_points(cam, pts, None, radius=1.0), f"input: {len(pts):,} points")]
    for spec in a.meshes:
        path, _, label = spec.partition(":")
        v, f = _load_mesh(path)
        panels.append((render_mesh(cam, up(v), f), label or Path(path).stem))
    gap = np.full((a.size[1], 6, 3), 255.0)
    row = []
    for img, label in panels:
        im = Image.fromarray(np.clip(img, 0, 255).astype(np.uint8))
        ImageDraw.Draw(im).text((8, a.size[1] - 18), label, fill=(0, 0, 0))
        row += [np.asarray(im, float), gap]
    Image.fromarray(np.concatenate(row[:-1], axis=1).astype(np.uint8)).save(a.out)
    print(f"{a.out}: {len(panels)} panels")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
