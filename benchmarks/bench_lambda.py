"""What lambda does (issue 19): roughness and distance to the data against lambda, 1,000 to 1,000,000 points.

For each corpus mesh and point count, points are sampled by area with Gaussian position noise (a
fraction of the bounding-box diagonal, default 0.001) and true normals, and reconstructed with
``splines`` at each lambda. Reported per lambda (means over the meshes):

- **roughness**: the mean angle, in degrees, between the normals of triangles that share an edge
  (a smoother surface has a smaller one; at a fixed resolution it compares lambdas fairly);
- **to data**: the mean distance from the input points to the surface, in units of the diagonal;
- **Chamfer-L1** to the reference mesh, in units of the diagonal;
- the regularisation the local fits actually used (``stats["pou"]["patch_lam"]``, above 3,000 points).

    python -m benchmarks.bench_lambda --points 1000 10000 100000 --lams 1e-10 1e-8 1e-6 1e-4 1e-3
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.spatial import cKDTree

import nkf_model
from nkf_model.train import corpus, metrics

DEFAULT_MESHES = ("quaternius__Donut", "geocentral__cat_head", "kenney__chairRounded")


def roughness(v: np.ndarray, f: np.ndarray) -> float:
    """Mean angle (degrees) between the normals of triangles sharing an edge."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = (key[1:] == key[:-1]).all(axis=1)
    a, b = owner[:-1][same], owner[1:][same]
    cos = np.clip(np.einsum("ij,ij->i", n[a], n[b]), -1, 1)
    return float(np.degrees(np.arccos(cos)).mean())


def run(names, points, lams, noise: float, resolution: int, log=print) -> list[dict]:
    rows = []
    entries = {e.name: e for e in corpus.manifest()}
    for name in names:
        rv, rf = corpus.load(entries[name])
        diag = float(np.linalg.norm(rv.max(0) - rv.min(0)))
        ref, _ = metrics.sample_surface(rv, rf, 100_000, np.random.default_rng(1))
        for n in points:
            rng = np.random.default_rng(corpus.stable_seed(name, n))
            p, nrm = metrics.sample_surface(rv, rf, n, rng)
            p = p + rng.normal(scale=noise * diag, size=p.shape)
            for lam in lams:
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    m = nkf_model.reconstruct(p, nrm, method="splines", lam=lam, resolution=resolution)
                dt = time.perf_counter() - t0
                v, f = m.vertices.astype(float), m.faces.astype(np.int64)
                s, _ = metrics.sample_surface(v, f, 200_000, rng)
                to_data = float(cKDTree(s).query(p)[0].mean()) / diag
                row = {"mesh": name, "points": n, "lam": lam, "roughness": roughness(v, f), "to_data": to_data,
                       "chamfer": metrics.chamfer_l1(s, ref) / diag, "seconds": dt,
                       "patch_lam": (m.stats.get("pou") or {}).get("patch_lam")}
                rows.append(row)
                log(f"{name:<28} n={n:>9,} lam={lam:.0e} roughness={row['roughness']:.2f} deg "
                    f"to_data={to_data:.5f} chamfer={row['chamfer']:.5f} t={dt:.1f}s")
    return rows


def table(rows) -> str:
    out = ["| points | lambda | local lambda used | roughness (degrees) | mean distance to data | Chamfer-L1 "
           "| time (s) |", "|---:|---:|---|---:|---:|---:|---:|"]
    for n in sorted({r["points"] for r in rows}):
        for lam in sorted({r["lam"] for r in rows}):
            rs = [r for r in rows if r["points"] == n and r["lam"] == lam]
            used = sorted({f"{r['patch_lam']:.1e}" for r in rs if r["patch_lam"] is not None})
            out.append(f"| {n:,} | {lam:.0e} | {', '.join(used) or 'exact solve'} | "
                       f"{np.mean([r['roughness'] for r in rs]):.2f} | {np.mean([r['to_data'] for r in rs]):.5f} | "
                       f"{np.mean([r['chamfer'] for r in rs]):.5f} | {np.mean([r['seconds'] for r in rs]):.1f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="+", default=list(DEFAULT_MESHES))
    ap.add_argument("--points", type=int, nargs="+", default=[1000, 10_000, 100_000])
    ap.add_argument("--lams", type=float, nargs="+", default=[1e-10, 1e-8, 1e-6, 1e-4, 1e-3])
    ap.add_argument("--noise", type=float, default=0.001, help="position noise, fraction of the diagonal")
    ap.add_argument("--resolution", type=int, default=128)
    a = ap.parse_args(argv)
    rows = run(a.meshes, a.points, a.lams, a.noise, a.resolution)
    print(f"\nsplines, noise {a.noise} of the diagonal, resolution {a.resolution}, meshes: {', '.join(a.meshes)}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
