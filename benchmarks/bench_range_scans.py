"""Benchmark on simulated multi-view range scans (issue 19): nkf, splines and Open3D's Poisson.

Each corpus mesh is scanned by :func:`benchmarks.range_scans.range_scan` (turntable views, occlusion,
grazing-angle noise, silhouette outliers, misregistered scans, no normals) and reconstructed by

- ``nkf`` and ``splines``: :func:`nkf_model.reconstruct` with its defaults (normals estimated);
- ``poisson``: Open3D's screened Poisson (depth 9) on normals estimated and oriented by Open3D
  (30 nearest neighbours, ``orient_normals_consistent_tangent_plane(15)``), as a user of Open3D would.

Scores, in units of the reference's bounding-box diagonal: Chamfer-L1, normal consistency and
F-score at 0.5 % between 100,000 area-weighted samples of the output and of the reference mesh;
the number of connected pieces and the share of the area in the largest; the share of the output's
area farther than 1 % of the diagonal from the reference ("off"); time in seconds; and the same
scores against only the part of the reference a scanner saw ("seen": reference samples within 0.5 %
of a scanned surface point; output samples nearest an unseen one left out), which separates what the
fit does with the data from how it closes what no scanner saw. "Seen-part F" is the F-score against
the whole reference of a surface that is exactly the seen part of the reference and nothing else
(precision 1; recall the share of the reference within 0.5 % of that part): what a method that
reconstructed every seen surface perfectly, and added nothing where no scanner looked, would score.
A mean F-score above it needs surface guessed right where no point is.

    python -m benchmarks.bench_range_scans --meshes quaternius__Sofa kenney__chairRounded
    python -m benchmarks.bench_range_scans --split val --every 4 --methods nkf splines poisson

Open3D: ``pip install -e '.[bench]'`` (on Debian also ``apt-get install libusb-1.0-0``).
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nkf_model.train import corpus, metrics

from .range_scans import RangeScan, range_scan

SAMPLES = 100_000
FSCORE = 0.005  # of the diagonal
OFF = 0.01  # of the diagonal
DEFAULT_SCANS = {"views": 10, "pixels": 200, "noise": 0.0005, "misregistration": 0.001, "elevations": (15.0, 40.0)}


def open3d_poisson(points: np.ndarray, depth: int = 9):
    """Open3D normals (estimated, oriented by tangent planes) then screened Poisson."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
    pcd.orient_normals_consistent_tangent_plane(15)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def run_method(method: str, points: np.ndarray, resolution: int, **settings):
    """Vertices, faces and seconds of one reconstruction."""
    t0 = time.perf_counter()
    if method == "poisson":
        v, f = open3d_poisson(points)
    else:
        import nkf_model

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = nkf_model.reconstruct(points, method=method, resolution=resolution, **settings)
        v, f = m.vertices.astype(np.float64), m.faces.astype(np.int64)
    return v, f, time.perf_counter() - t0


def pieces(v: np.ndarray, f: np.ndarray) -> tuple[int, float]:
    """Connected pieces and the largest piece's share of the area."""
    from nkf_model.surface.trim import face_areas, piece_labels

    if len(f) == 0:
        return 0, 0.0
    _, face_label = piece_labels(len(v), f)
    area = face_areas(v, f)
    per = np.bincount(face_label, weights=area)
    return int((per > 0).sum()), float(per.max() / per.sum())


def score(v, f, ref_v, ref_f, diagonal: float, seed: int = 0, points: np.ndarray | None = None,
          surface_points: np.ndarray | None = None) -> dict:
    """Chamfer-L1, normal consistency, F-score, pieces, largest share, off-surface share."""
    rng = np.random.default_rng(seed)
    if len(f) == 0:
        return {"chamfer": float("nan"), "nc": 0.0, "fscore": 0.0, "pieces": 0, "largest": 0.0, "off": 1.0}
    rp, rn = metrics.sample_surface(ref_v, ref_f, SAMPLES, rng)
    pp, pn = metrics.sample_surface(v, f, SAMPLES, rng)
    s = metrics.surface_metrics(pp / diagonal, pn, rp / diagonal, rn, tau=FSCORE)
    d_off, _ = cKDTree(rp).query(pp, workers=-1)
    n_pieces, largest = pieces(v, f)
    out = {"chamfer": s["chamfer_l1"], "nc": s["normal_consistency"], "fscore": s["fscore"],
           "pieces": n_pieces, "largest": largest, "off": float((d_off > OFF * diagonal).mean())}
    if points is not None:
        d_in, _ = cKDTree(points).query(pp, workers=-1)
        out["near_input"] = float((d_in < 0.0025 * diagonal).mean())
    if surface_points is not None:
        out.update(seen_metrics(pp / diagonal, pn, rp / diagonal, rn, surface_points / diagonal))
    return out


def seen_metrics(pp, pn, rp, rn, surface_points, tau: float = FSCORE) -> dict:
    """The same scores against only the part of the reference a scanner saw.

    A reference sample is *seen* when a scan's surface point (outliers excluded) lies within ``tau``
    of it. Output samples whose nearest reference sample is unseen are left out (they close what no
    scanner saw, right or wrong); the rest and the seen reference samples are scored as in
    :func:`nkf_model.train.metrics.surface_metrics`. ``seen_part_f``: the F-score, against the whole
    reference, of the seen reference samples taken as the output (precision 1; it depends on the scan
    only). All inputs in units of the diagonal: ``pp, pn`` (N, 3) output samples and normals, ``rp, rn``
    (M, 3) reference ones, ``surface_points`` (K, 3)."""
    d_seen, _ = cKDTree(surface_points).query(rp, workers=-1)
    seen = d_seen < tau
    d_pr, i_pr = cKDTree(rp).query(pp, workers=-1)
    keep = seen[i_pr]
    d_rp, i_rp = cKDTree(pp).query(rp[seen], workers=-1)
    if not seen.any():
        return {"seen_share": 0.0, "seen_chamfer": float("nan"), "seen_nc": 0.0, "seen_fscore": 0.0,
                "seen_part_f": 0.0}
    # The seen part of the reference as a surface of its own, scored against the whole reference.
    d_part, _ = cKDTree(rp[seen]).query(rp, workers=-1)
    part_recall = float((d_part < tau).mean())
    part_f = 2 * part_recall / (1 + part_recall)
    if not keep.any():
        return {"seen_share": float(seen.mean()), "seen_chamfer": float("nan"), "seen_nc": 0.0, "seen_fscore": 0.0,
                "seen_part_f": part_f}
    nc_pr = np.abs(np.sum(pn[keep] * rn[i_pr[keep]], axis=1)).mean()
    nc_rp = np.abs(np.sum(rn[seen] * pn[i_rp], axis=1)).mean()
    precision = float((d_pr[keep] < tau).mean())
    recall = float((d_rp < tau).mean())
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"seen_share": float(seen.mean()), "seen_chamfer": 0.5 * float(d_pr[keep].mean() + d_rp.mean()),
            "seen_nc": 0.5 * float(nc_pr + nc_rp), "seen_fscore": f, "seen_part_f": part_f}


def scan_of(entry, scans: dict, seed: int) -> tuple[RangeScan, np.ndarray, np.ndarray]:
    v, f = corpus.load(entry)
    return range_scan(v, f, seed=corpus.stable_seed(entry.name, seed), **scans), v, f


def run(entries, methods, resolution: int, scans: dict, seed: int = 0, log=print, settings=None) -> list[dict]:
    rows = []
    for e in entries:
        sc, rv, rf = scan_of(e, scans, seed)
        for method in methods:
            try:
                v, f, dt = run_method(method, sc.points, resolution, **(settings or {}))
                r = score(v, f, rv, rf, sc.diagonal, seed=seed, surface_points=sc.points[~sc.outlier])
                err = None
            except Exception as exc:  # a failure is a result
                r, dt, err = {}, float("nan"), f"{type(exc).__name__}: {exc}"
            row = {"mesh": e.name, "method": method, "points": len(sc.points), "seconds": dt, "error": err, **r}
            rows.append(row)
            log(_fmt_row(row))
    return rows


def _fmt_row(r) -> str:
    if r.get("error"):
        return f"{r['mesh']:<34} {r['method']:<8} ERROR {r['error']}"
    return (f"{r['mesh']:<34} {r['method']:<8} n={r['points']:>7,} CD={r['chamfer']:.5f} NC={r['nc']:.4f} "
            f"F={r['fscore']:.4f} pieces={r['pieces']:>4} largest={r['largest']:.4f} off={r['off']:.4f} "
            f"t={r['seconds']:.1f}s seen={r['seen_share']:.3f} seenCD={r['seen_chamfer']:.5f} "
            f"seenNC={r['seen_nc']:.4f} seenF={r['seen_fscore']:.4f} seenPartF={r['seen_part_f']:.4f}")


def table(rows, methods) -> str:
    lines = ["| method | meshes | mean Chamfer-L1 | mean normal consistency | mean F-score (0.5 %) | mean pieces | "
             "min largest piece | mean off (> 1 %) | mean time (s) | seen share | seen Chamfer-L1 | seen NC | seen F | "
             "seen-part F |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for m in methods:
        rs = [r for r in rows if r["method"] == m and not r.get("error")]
        fails = sum(1 for r in rows if r["method"] == m and r.get("error"))
        if not rs:
            lines.append(f"| {m} | 0 ({fails} failed) | | | | | | | | | | | | |")
            continue
        mean = lambda k, rs=rs: float(np.mean([r[k] for r in rs]))  # noqa: E731
        lines.append(
            f"| {m} | {len(rs)}{f' ({fails} failed)' if fails else ''} | {mean('chamfer'):.5f} | {mean('nc'):.4f} | "
            f"{mean('fscore'):.4f} | {mean('pieces'):.1f} | {min(r['largest'] for r in rs):.4f} | {mean('off'):.4f} | "
            f"{mean('seconds'):.1f} | {mean('seen_share'):.3f} | {mean('seen_chamfer'):.5f} | {mean('seen_nc'):.4f} | "
            f"{mean('seen_fscore'):.4f} | {mean('seen_part_f'):.4f} |"
        )
    return "\n".join(lines)


def select_entries(meshes, split: str, every: int, start: int = 0) -> list:
    """Corpus entries by name (``meshes``), or every ``every``-th of ``split`` from ``start``."""
    rows_all = corpus.manifest()
    if meshes:
        by = {e.name: e for e in rows_all}
        return [by[m] for m in meshes]
    return [e for e in rows_all if e.split == split][start::every]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="*", help="corpus mesh names (default: --split with --every)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--every", type=int, default=4, help="every k-th mesh of the split")
    ap.add_argument("--methods", nargs="+", default=["nkf", "splines", "poisson"])
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--views", type=int, default=DEFAULT_SCANS["views"])
    ap.add_argument("--pixels", type=int, default=DEFAULT_SCANS["pixels"])
    ap.add_argument("--noise", type=float, default=DEFAULT_SCANS["noise"])
    ap.add_argument("--misregistration", type=float, default=DEFAULT_SCANS["misregistration"])
    ap.add_argument("--elevations", type=float, nargs="+", default=list(DEFAULT_SCANS["elevations"]),
                    help="scanner elevations in degrees, cycled over the views; a negative one looks from "
                         "below (the object turned over and scanned again)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="append the table to this Markdown file")
    a = ap.parse_args(argv)
    entries = select_entries(a.meshes, a.split, a.every)
    scans = {"views": a.views, "pixels": a.pixels, "noise": a.noise, "misregistration": a.misregistration,
             "elevations": tuple(a.elevations)}
    rows = run(entries, a.methods, a.resolution, scans, seed=a.seed)
    elevations = ", ".join(f"{e:g}" for e in a.elevations)
    text = (f"Simulated range scans: {a.views} views, {a.pixels} px, noise {a.noise} and misregistration up to "
            f"{a.misregistration} of the diagonal, elevations {elevations} degrees, resolution {a.resolution}, "
            f"{len(entries)} meshes\n\n"
            + table(rows, a.methods))
    print(text)
    if a.out:
        with open(a.out, "a") as fh:
            fh.write(text + "\n\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
