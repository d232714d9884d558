"""Render a coloured point cloud and the mesh reconstructed from it side by side, as a PNG.

    python scripts/render_scan.py SCAN.ply MESH.ply OUT.png [--eye X Y Z] [--target X Y Z]

A small z-buffer rasteriser (numba): the mesh with its vertex colours (grey without) and Lambert
shading from a light at the camera, the points as 2-pixel splats with their colours. No GPU, no
Blender; the README's picture of a reconstructed scan is made with it.
"""

from __future__ import annotations

import argparse
import math

import numba as nb
import numpy as np
from PIL import Image

from nkf_model.io.files import read_point_cloud, write_point_cloud  # noqa: F401  (documented reader)


@nb.njit(cache=True)
def _raster(tri_xy, tri_z, tri_rgb, width, height, img, zbuf):
    for t in range(tri_xy.shape[0]):
        x0, y0 = tri_xy[t, 0]
        x1, y1 = tri_xy[t, 1]
        x2, y2 = tri_xy[t, 2]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        i0 = max(0, int(math.floor(min(x0, x1, x2))))
        i1 = min(width - 1, int(math.ceil(max(x0, x1, x2))))
        j0 = max(0, int(math.floor(min(y0, y1, y2))))
        j1 = min(height - 1, int(math.ceil(max(y0, y1, y2))))
        for j in range(j0, j1 + 1):
            py = j + 0.5
            for i in range(i0, i1 + 1):
                px = i + 0.5
                l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                l2 = 1.0 - l0 - l1
                if l0 < 0 or l1 < 0 or l2 < 0:
                    continue
                z = l0 * tri_z[t, 0] + l1 * tri_z[t, 1] + l2 * tri_z[t, 2]
                if z < zbuf[j, i]:
                    zbuf[j, i] = z
                    for c in range(3):
                        img[j, i, c] = l0 * tri_rgb[t, 0, c] + l1 * tri_rgb[t, 1, c] + l2 * tri_rgb[t, 2, c]


@nb.njit(cache=True)
def _splat(xy, z, rgb, radius, width, height, img, zbuf):
    for k in range(xy.shape[0]):
        cx, cy = xy[k]
        for j in range(max(0, int(cy - radius)), min(height, int(cy + radius) + 1)):
            for i in range(max(0, int(cx - radius)), min(width, int(cx + radius) + 1)):
                if (i + 0.5 - cx) ** 2 + (j + 0.5 - cy) ** 2 <= radius * radius and z[k] < zbuf[j, i]:
                    zbuf[j, i] = z[k]
                    for c in range(3):
                        img[j, i, c] = rgb[k, c]


class Camera:
    def __init__(self, eye, target, width, height, fov_deg=50.0):
        self.eye = np.asarray(eye, float)
        f = np.asarray(target, float) - self.eye
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        self.axes = np.stack([r, u, f])
        self.width, self.height = width, height
        self.focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)

    def project(self, p):
        c = (np.asarray(p, float) - self.eye) @ self.axes.T
        z = c[:, 2]
        x = self.width / 2 + self.focal * c[:, 0] / z
        y = self.height / 2 - self.focal * c[:, 1] / z
        return np.stack([x, y], axis=1), z


def render_mesh(cam, vertices, faces, colors=None):
    img = np.full((cam.height, cam.width, 3), 255.0)
    zbuf = np.full((cam.height, cam.width), np.inf)
    xy, z = cam.project(vertices)
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    view = cam.eye - tri.mean(axis=1)
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    shade = 0.25 + 0.75 * np.abs(np.sum(n * view, axis=1))
    base = np.full((len(vertices), 3), 200.0) if colors is None else colors.astype(float)
    rgb = base[faces] * shade[:, None, None]
    keep = (z[faces] > 1e-3).all(axis=1)
    _raster(np.ascontiguousarray(xy[faces][keep]), np.ascontiguousarray(z[faces][keep]),
            np.ascontiguousarray(rgb[keep]), cam.width, cam.height, img, zbuf)
    return img


def render_points(cam, points, colors, radius=1.2):
    img = np.full((cam.height, cam.width, 3), 255.0)
    zbuf = np.full((cam.height, cam.width), np.inf)
    xy, z = cam.project(points)
    keep = z > 1e-3
    rgb = np.full((len(points), 3), 80.0) if colors is None else colors.astype(float)
    _splat(np.ascontiguousarray(xy[keep]), np.ascontiguousarray(z[keep]), np.ascontiguousarray(rgb[keep]),
           radius, cam.width, cam.height, img, zbuf)
    return img


def main(argv=None):
    from plyfile import PlyData

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scan")
    ap.add_argument("mesh")
    ap.add_argument("out")
    ap.add_argument("--eye", type=float, nargs=3, default=None)
    ap.add_argument("--target", type=float, nargs=3, default=None)
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480))
    args = ap.parse_args(argv)
    cloud = read_point_cloud(args.scan)
    ply = PlyData.read(args.mesh)
    v = ply["vertex"]
    verts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(float)
    names = {p.name for p in v.properties}
    cols = np.stack([v["red"], v["green"], v["blue"]], axis=1) if {"red", "green", "blue"} <= names else None
    faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
    lo, hi = cloud.points.min(axis=0), cloud.points.max(axis=0)
    target = np.asarray(args.target) if args.target else 0.5 * (lo + hi)
    eye = np.asarray(args.eye) if args.eye else target + np.array([0.2, -1.25, 0.9]) * float((hi - lo).max())
    cam = Camera(eye, target, *args.size)
    left = render_points(cam, cloud.points, cloud.colors)
    right = render_mesh(cam, verts, faces, cols)
    gap = np.full((args.size[1], 8, 3), 255.0)
    Image.fromarray(np.clip(np.concatenate([left, gap, right], axis=1), 0, 255).astype(np.uint8)).save(args.out)
    print(f"{args.out}: {args.size[0] * 2 + 8} x {args.size[1]}")


if __name__ == "__main__":
    main()
