"""Benchmark on a real multi-view range scan without a reference mesh (issue 19): the dragon of
``../shared/data/scans`` by default.

Each method reconstructs the raw points (no normals) and is judged by what needs no reference:

- pieces, and the largest piece's share of the area;
- where the surface lies: the share of 200,000 area samples of the output within 0.5 mm of an input
  point, 0.5 to 1.5 mm, and beyond 1.5 mm (what closes holes no scanner saw, or a second sheet
  beside the first);
- how close the input is to the surface: the median, 90th and 99th percentile distance from the
  input points to the output mesh;
- time in seconds.

Methods: ``nkf`` and ``splines`` (:func:`nkf_model.reconstruct` with its defaults), ``poisson``
(Open3D's screened Poisson, depth 9, on Open3D's own normals, as in :mod:`benchmarks.bench_range_scans`).

    python -m benchmarks.bench_real_scan --methods splines poisson --render docs/dragon_real_scan.png

``--units-per-mm`` converts the file's units (the dragon is in metres: 1000). Open3D: ``pip install
-e '.[bench]'``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nkf_model.io.files import read_point_cloud
from nkf_model.train import corpus, metrics

from .bench_range_scans import pieces, run_method

DRAGON = corpus.corpus_dir().parent / "scans" / "dragon_stand_scans.ply"  # beside the mesh corpus
SAMPLES = 200_000
NEAR_MM, FAR_MM = 0.5, 1.5


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from each point ``p`` (N, 3) to its triangle ``a, b, c`` (N, 3 each): the closest point
    on the triangle by its Voronoi regions (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        q = a + v_in[:, None] * ab + w_in[:, None] * ac  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [
        (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    points = [a, b, c, a + t_ab[:, None] * ab, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b)]
    taken = np.zeros(len(p), bool)
    for region, point in zip(regions, points):
        use = region & ~taken
        q[use] = point[use]
        taken |= use
    return np.linalg.norm(p - q, axis=1)


def point_mesh_distance(points: np.ndarray, v: np.ndarray, f: np.ndarray, samples: np.ndarray,
                        sample_faces: np.ndarray, k: int = 8) -> np.ndarray:
    """Distance from each of ``points`` (N, 3) to the mesh ``v, f``: the nearest of the triangles under
    its ``k`` nearest area samples (``samples`` (S, 3) on faces ``sample_faces`` (S,)); exact wherever
    the nearest triangle carries one of those samples, and never more than the nearest sample's
    distance."""
    _, idx = cKDTree(samples).query(points, k=k, workers=-1)
    best = np.full(len(points), np.inf)
    for j in range(k):
        tri = f[sample_faces[idx[:, j]]]
        best = np.minimum(best, point_triangle_distance(points, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]))
    return best


def judge(v: np.ndarray, f: np.ndarray, points: np.ndarray, mm: float, seed: int = 0) -> dict:
    """Reference-free scores of a mesh (``v`` (V, 3), ``f`` (F, 3)) of ``points`` (N, 3); ``mm``: one
    millimetre in the points' units."""
    if len(f) == 0:
        return {"pieces": 0, "largest": 0.0, "near": 0.0, "mid": 0.0, "far": 1.0,
                "in_p50": float("nan"), "in_p90": float("nan"), "in_p99": float("nan")}
    samples, _, sample_faces = metrics.sample_surface(v, f, SAMPLES, np.random.default_rng(seed), return_faces=True)
    d_out, _ = cKDTree(points).query(samples, workers=-1)
    d_in = point_mesh_distance(points, v, f, samples, sample_faces)
    n_pieces, largest = pieces(v, f)
    near = float((d_out < NEAR_MM * mm).mean())
    far = float((d_out > FAR_MM * mm).mean())
    return {"pieces": n_pieces, "largest": largest, "near": near, "mid": 1.0 - near - far, "far": far,
            "in_p50": float(np.median(d_in) / mm), "in_p90": float(np.percentile(d_in, 90) / mm),
            "in_p99": float(np.percentile(d_in, 99) / mm)}


def table(rows) -> str:
    lines = ["| method | points | pieces | largest piece | surface within 0.5 mm of a point | 0.5 to 1.5 mm | "
             "beyond 1.5 mm | input to surface, median / 90 % / 99 % (mm) | time (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    for r in rows:
        if r.get("error"):
            lines.append(f"| {r['method']} | {r['points']:,} | failed: {r['error']} | | | | | | |")
            continue
        lines.append(f"| {r['method']} | {r['points']:,} | {r['pieces']} | {r['largest']:.4f} | "
                     f"{100 * r['near']:.1f} % | {100 * r['mid']:.1f} % | {100 * r['far']:.1f} % | "
                     f"{r['in_p50']:.3f} / {r['in_p90']:.3f} / "
                     f"{r['in_p99']:.3f} | {r['seconds']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scan", type=Path, default=DRAGON, help="point cloud file (default: the dragon)")
    ap.add_argument("--units-per-mm", type=float, default=1000.0, help="the file's units in a millimetre")
    ap.add_argument("--methods", nargs="+", default=["splines", "nkf", "poisson"])
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--meshes", type=Path, help="also save each mesh here as METHOD.npz (v, f)")
    ap.add_argument("--render", type=Path, help="render the input and the meshes side by side into this PNG")
    ap.add_argument("--y-up", action=argparse.BooleanOptionalAction, default=True,
                    help="the data's up axis is +y (Stanford scans; default)")
    ap.add_argument("--out", type=Path, help="append the table to this Markdown file")
    a = ap.parse_args(argv)
    cloud = read_point_cloud(a.scan)
    points = np.asarray(cloud.points, np.float64)
    mm = 1.0 / a.units_per_mm
    rows, meshes = [], []
    for method in a.methods:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                v, f, dt = run_method(method, points, a.resolution)
            row = {"method": method, "points": len(points), "seconds": dt, **judge(v, f, points, mm)}
            meshes.append((method, v, f))
        except Exception as exc:  # a failure is a result
            row = {"method": method, "points": len(points), "error": f"{type(exc).__name__}: {exc}"}
        rows.append(row)
        print(table([row]).splitlines()[-1], flush=True)
    text = (f"{a.scan.name}: {len(points):,} points, resolution {a.resolution} (nkf, splines); "
            f"distances in mm\n\n" + table(rows))
    print(text)
    if a.out:
        with open(a.out, "a") as fh:
            fh.write(text + "\n\n")
    if a.meshes:
        a.meshes.mkdir(parents=True, exist_ok=True)
        for method, v, f in meshes:
            np.savez_compressed(a.meshes / f"{method}.npz", v=v, f=f)
    if a.render and meshes:
        import subprocess
        import sys
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            specs = []
            for method, v, f in meshes:
                path = Path(tmp) / f"{method}.npz"
                np.savez(path, v=v, f=f)
                specs.append(f"{path}:{method}")
            script = Path(__file__).resolve().parents[1] / "scripts" / "render_compare.py"
            subprocess.run([sys.executable, str(script), str(a.scan), str(a.render), *specs]
                           + (["--y-up"] if a.y_up else []), check=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
