"""Benchmark: dense noisy points, estimated normals against the mesh's own (issue 19, item 3).

``python -m benchmarks.bench_dense_normals [--points 300000] [--every 8 --start 1 | --meshes A B ...]``
samples each mesh by area, adds Gaussian noise of ``--spacing-noise`` (default 0.5) times the median
nearest-neighbour spacing of the samples, and reconstructs with ``splines`` at ``--resolution``
(default 256) twice: with the mesh's normals and with ``reconstruct``'s own estimation (orientation
"outward"). It prints one Markdown row per mesh and normals (Chamfer-L1, normal consistency, F-score
at 0.5 %, pieces, largest piece, seconds; units of the reference's diagonal, scored as
:func:`benchmarks.bench_range_scans.score`) and the mean Chamfer-L1 of both. The issue's criterion:
Chamfer-L1 within 5 % of the mesh normals' and one piece.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import numpy as np
from scipy.spatial import cKDTree

from nkf_model.pipeline.reconstruct import reconstruct
from nkf_model.train import corpus, metrics

from .bench_range_scans import score, select_entries


def noisy_samples(entry, n: int, spacing_noise: float):
    """``n`` area samples (n, 3), their true normals, the reference mesh and its diagonal."""
    v, f = corpus.load(entry)
    rng = np.random.default_rng(corpus.stable_seed(entry.name, n))
    p, nrm = metrics.sample_surface(v, f, n, rng)
    d, _ = cKDTree(p).query(p, k=2, workers=-1)
    p = p + rng.normal(scale=spacing_noise * float(np.median(d[:, 1])), size=p.shape)
    return p, nrm, v, f, float(np.linalg.norm(v.max(0) - v.min(0)))


def run(entries, n: int, spacing_noise: float, resolution: int, log=print) -> list[dict]:
    rows = []
    for e in entries:
        p, nrm, v, f, diag = noisy_samples(e, n, spacing_noise)
        for tag, normals in (("true", nrm), ("estimated", None)):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = reconstruct(p, normals, method="splines", resolution=resolution)
            dt = time.perf_counter() - t0
            r = score(m.vertices, m.faces, v, f, diag)
            row = {"mesh": e.name, "normals": tag, "seconds": dt, **r}
            rows.append(row)
            log(f"| {e.name} | {tag} | {r['chamfer']:.5f} | {r['nc']:.4f} | {r['fscore']:.4f} | {r['pieces']} "
                f"| {r['largest']:.4f} | {dt:.1f} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="*", help="corpus mesh names (default: --split, every --every from --start)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--every", type=int, default=8)
    ap.add_argument("--start", type=int, default=1)
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--spacing-noise", type=float, default=0.5, help="noise, times the median point spacing")
    ap.add_argument("--resolution", type=int, default=256)
    a = ap.parse_args(argv)
    entries = select_entries(a.meshes, a.split, a.every, a.start)
    print(f"{a.points:,} points, noise {a.spacing_noise} of the spacing, splines, resolution {a.resolution}\n")
    print("| mesh | normals | Chamfer-L1 | normal consistency | F-score 0.5 % | pieces | largest piece | time (s) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    rows = run(entries, a.points, a.spacing_noise, a.resolution)
    mean = {t: statistics.mean(r["chamfer"] for r in rows if r["normals"] == t) for t in ("true", "estimated")}
    print(f"\nMean Chamfer-L1: true {mean['true']:.5f}, estimated {mean['estimated']:.5f} "
          f"({100 * (mean['estimated'] / mean['true'] - 1):+.1f} %)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
