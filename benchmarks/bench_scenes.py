"""Benchmarks for scans: synthetic room scans, and large object inputs.

``python -m benchmarks.bench_scenes`` prints Markdown tables:

1. Scenes (:mod:`benchmarks.scenes`: rooms with corpus meshes of the ``val`` split, scanned from
   three positions, 100,000 points with range noise): ``splines`` with normals estimated from the
   points (oriented towards the scanner positions) and with the true normals, trimmed as a scan
   (``trim=SCAN_TRIM``, ``min_piece=SCAN_MIN_PIECE``), against Open3D's screened Poisson (depth 8,
   then density trimming: vertices below the 5 % quantile of the Poisson density removed) on the
   same points and normals; ``nkf`` too when ``method="nkf"`` works in this installation. Metrics
   against dense noiseless samples of the visible surfaces, all in the scene's unit box (longest
   side 1): Chamfer-L1, normal consistency, F-score at 1 % and 0.5 %, wall time and peak memory of
   the call.
2. ``--large``: ``val`` objects sampled at 100,000 and 1,000,000 points (noise 0.002 of the box)
   at resolution 256: time, peak memory, what reduction applied, and IoU / Chamfer-L1, with and
   without the voxel-grid reduction (its accuracy effect).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from nkf_model.options import SCAN_MIN_PIECE, SCAN_TRIM
from nkf_model.pipeline.reconstruct import DEFAULT_REDUCE_TO, reconstruct
from nkf_model.train import corpus, metrics

from . import scenes
from .bench import PeakRSS, machine, reference, report, score, warm_up

POISSON_DENSITY_QUANTILE = 0.05


def _measure(fn):
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        try:
            out = fn()
            err = None
        except Exception as exc:  # a failure is a result of the benchmark
            out, err = None, f"{type(exc).__name__}: {exc}"
        dt = time.perf_counter() - t0
    return out, dt, mem.peak, err


def poisson_trimmed(points, normals, depth=8, quantile=POISSON_DENSITY_QUANTILE):
    """Open3D screened Poisson, then vertices below the ``quantile`` of the density removed."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    dens = np.asarray(dens)
    mesh.remove_vertices_by_mask(dens < np.quantile(dens, quantile))
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def nkf_available() -> tuple[bool, str]:
    """Whether ``method="nkf"`` runs here, and why not."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    try:
        reconstruct(p, p, method="nkf", resolution=16, device="cpu")
        return True, ""
    except Exception as exc:
        return False, str(exc)


def scene_metrics(v, f, scan_: scenes.Scan, scale, seed):
    if f is None or len(f) == 0:
        return {"chamfer_l1": float("nan"), "normal_consistency": 0.0, "fscore": 0.0, "fscore_half": 0.0}
    rng = np.random.default_rng(seed)
    pp, pn = metrics.sample_surface(np.asarray(v, np.float64) / scale, f, 100_000, rng)
    ref_p = scan_.reference_points / scale
    out = metrics.surface_metrics(pp, pn, ref_p, scan_.reference_normals)
    out["fscore_half"] = metrics.surface_metrics(pp, pn, ref_p, scan_.reference_normals, tau=0.005)["fscore"]
    return out


def run_scenes(seeds, n_points, resolution, noise, methods, log=print):
    rows = []
    for seed in seeds:
        scene = scenes.make_scene(seed=seed)
        scan_ = scenes.scan(scene, n_points, noise=noise, seed=seed)
        scale = float((scan_.points.max(axis=0) - scan_.points.min(axis=0)).max())
        log(f"scene {seed}: {', '.join(scene.objects)}; {len(scan_.points):,} points")
        from nkf_model.normals.estimate import estimate_normals

        (est, _), t_est, _, _ = _measure(
            lambda scan_=scan_, scene=scene: estimate_normals(scan_.points, viewpoints=scene.viewpoints)
        )
        agree = float((np.sum(est * scan_.normals, axis=1) > 0).mean())
        for method in methods:
            for normals_kind in ("estimated", "true"):
                nrm = est if normals_kind == "estimated" else scan_.normals
                if method in ("splines", "nkf"):
                    def fn(nrm=nrm, method=method, scan_=scan_):
                        m = reconstruct(scan_.points, nrm, method=method, resolution=resolution, device="cpu",
                                        trim=SCAN_TRIM, min_piece=SCAN_MIN_PIECE)
                        return m.vertices, m.faces
                else:
                    def fn(nrm=nrm, scan_=scan_):
                        return poisson_trimmed(scan_.points, nrm)
                out, dt, mem, err = _measure(fn)
                v, f = out if out is not None else (None, None)
                s = scene_metrics(v, f, scan_, scale, seed)
                if normals_kind == "estimated":
                    dt += t_est  # the normals are part of that pipeline's cost
                s.update(scene=seed, method=method, normals=normals_kind, time=dt, mem=mem, err=err, agree=agree)
                rows.append(s)
                log(f"  {method:8s} {normals_kind:9s} CD {s['chamfer_l1']:.5f} NC {s['normal_consistency']:.4f} "
                    f"F {s['fscore']:.4f} t {dt:6.1f}s mem {mem / 2**20:6.0f} MiB" + (f" FAILED {err}" if err else ""))
    return rows


def format_scenes(rows, n_points, resolution, noise, note="") -> str:
    lines = [
        "| method | normals | Chamfer-L1 | normal consistency | F-score (1 %) | F-score (0.5 %) | mean time (s) "
        "| peak memory (MiB) | failures |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    keys = []
    for r in rows:
        if (r["method"], r["normals"]) not in keys:
            keys.append((r["method"], r["normals"]))
    for method, kind in keys:
        sel = [r for r in rows if r["method"] == method and r["normals"] == kind]
        ok = [r for r in sel if not r["err"]]
        label = {"splines": f"splines, trim {SCAN_TRIM:g}", "poisson": "Poisson depth 8 + density trim"}.get(
            method, method)

        def m(key, rs=ok):
            vals = [r[key] for r in rs if np.isfinite(r[key])]
            return statistics.mean(vals) if vals else float("nan")

        lines.append(
            f"| {label} | {kind} | {m('chamfer_l1'):.5f} | {m('normal_consistency'):.4f} | {m('fscore'):.4f} "
            f"| {m('fscore_half'):.4f} | {m('time', sel):.1f} | {max(r['mem'] for r in sel) / 2**20:.0f} "
            f"| {len(sel) - len(ok)} |"
        )
    agree = statistics.mean(r["agree"] for r in rows)
    scenes_n = len({r["scene"] for r in rows})
    lines += ["", f"{scenes_n} scenes, {n_points:,} points each, range noise {noise} m, splines at resolution "
              f"{resolution}. Estimated normals (oriented towards the 3 scanner positions) agree in sign with "
              f"the true ones for {100 * agree:.1f} % of the points; their time is included."]
    if note:
        lines += ["", note]
    return "\n".join(lines)


def run_large(entries, sizes, resolution, cache, methods=("splines",), log=print):
    rows = []
    for e in entries:
        ref = reference(e, cache)
        v0, f0 = corpus.load(e)
        for n in sizes:
            pts, nrm = corpus.sample_input(v0, f0, n, 0.002, corpus.stable_seed("large", e.name, n))
            variants = [(method, "default", DEFAULT_REDUCE_TO) for method in methods]
            if n > DEFAULT_REDUCE_TO:
                variants += [(method, "all points", None) for method in methods]
            for method, label, reduce_to in variants:
                def fn(reduce_to=reduce_to, pts=pts, nrm=nrm, method=method):
                    return reconstruct(pts, nrm, method=method, resolution=resolution, device="cpu",
                                       reduce_to=reduce_to)

                m, dt, mem, err = _measure(fn)
                if m is None:
                    s = {"iou": 0.0, "chamfer_l1": float("nan"), "fscore": 0.0, "normal_consistency": 0.0}
                    red, solver = "", "failed"
                else:
                    s = score(m.vertices.astype(np.float64), m.faces, ref, corpus.stable_seed("score", e.name, n))
                    r = m.stats.get("reduction")
                    red = f"voxel grid to {r['to']:,}" if r else "none"
                    solver = m.stats["solver"]
                s.update(mesh=e.name, n=n, variant=label, method=method, time=dt, mem=mem, err=err, reduction=red,
                         solver=solver)
                rows.append(s)
                log(f"  {e.name:36s} n={n:>9,} {method:8s} {label:10s} {red:24s} IoU {s['iou']:.4f} "
                    f"CD {s['chamfer_l1']:.5f} t {dt:6.1f}s mem {mem / 2**20:6.0f} MiB"
                    + (f" FAILED {err}" if err else ""))
    return rows


def format_large(rows, resolution) -> str:
    lines = [
        "| points | method | variant | reduction | solver | mean IoU | mean Chamfer-L1 | mean F-score "
        "| mean time (s) | max time (s) | peak memory (MiB) |",
        "|---:|---|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    keys = []
    for r in rows:
        if (r["n"], r["method"], r["variant"]) not in keys:
            keys.append((r["n"], r["method"], r["variant"]))
    for n, method, variant in keys:
        sel = [r for r in rows if r["n"] == n and r["method"] == method and r["variant"] == variant]
        reds = sorted({r["reduction"] for r in sel})
        cds = [r["chamfer_l1"] for r in sel if np.isfinite(r["chamfer_l1"])]
        lines.append(
            f"| {n:,} | {method} | {variant} | {'; '.join(reds)} | {sel[0]['solver']} "
            f"| {statistics.mean(r['iou'] for r in sel):.4f} "
            f"| {statistics.mean(cds) if cds else float('nan'):.5f} | {statistics.mean(r['fscore'] for r in sel):.4f} "
            f"| {statistics.mean(r['time'] for r in sel):.1f} | {max(r['time'] for r in sel):.1f} "
            f"| {max(r['mem'] for r in sel) / 2**20:.0f} |"
        )
    meshes = sorted({r["mesh"] for r in rows})
    lines += ["", f"Resolution {resolution}, position noise 0.002 of the box, meshes: {', '.join(meshes)}."]
    return "\n".join(lines)


def run_estimates(methods=("splines",), log=print):
    """Predicted against measured time and peak memory over a spread of inputs and settings."""
    from nkf_model.pipeline.budget import estimate

    entries = {e.name: e for e in corpus.manifest()}
    cases = [
        ("quaternius__Donut", 1_000, 128, False), ("quaternius__Donut", 10_000, 256, False),
        ("quaternius__Donut", 30_000, 256, False), ("kenney__chairRounded", 100_000, 128, False),
        ("kenney__chairRounded", 100_000, 256, False), ("kenney__chairRounded", 100_000, 256, True),
        ("quaternius__Donut", 300_000, 256, False), ("quaternius__Donut", 1_000_000, 256, False),
        ("quaternius__Donut", 1_000_000, 256, True), ("quaternius__Donut", 100_000, 512, False),
    ]
    rows = []
    for (name, n, res, est_normals), method in [(c, m) for c in cases for m in methods]:
        v0, f0 = corpus.load(entries[name])
        pts, nrm = corpus.sample_input(v0, f0, n, 0.002, corpus.stable_seed("estimate", name, n))
        pred = estimate(n, resolution=res, estimate_normals=est_normals, method=method)

        def fn(pts=pts, nrm=nrm, res=res, est_normals=est_normals, method=method):
            return reconstruct(pts, None if est_normals else nrm, method=method, resolution=res, device="cpu")

        m, dt, mem, err = _measure(fn)
        stages = "" if m is None else ", ".join(f"{k} {v:.1f}" for k, v in m.stats["timings"].items())
        grid = 0 if m is None else m.stats["grid_points_evaluated"]
        rows.append((name, n, res, est_normals, method, pred, dt, mem, grid, stages, err))
        log(f"  {name} n={n:,} {method} R={res} normals={'est' if est_normals else 'given'}: predicted "
            f"{pred.seconds:.1f}s {pred.peak_bytes / 2**20:.0f} MiB, measured {dt:.1f}s {mem / 2**20:.0f} MiB "
            f"grid {grid:,} [{stages}]" + (f" FAILED {err}" if err else ""))
    lines = [
        "| input | points | resolution | normals | method | solver | predicted time (s) | measured time (s) "
        "| predicted memory (MiB) | measured peak (MiB) |",
        "|---|---:|---:|---|---|---|---:|---:|---:|---:|",
    ]
    for name, n, res, est_normals, method, pred, dt, mem, _, _, _ in rows:
        lines.append(
            f"| {name} | {n:,} | {res} | {'estimated' if est_normals else 'given'} | {method} | {pred.solver} "
            f"| {pred.seconds:.1f} | {dt:.1f} | {pred.peak_bytes / 2**20:.0f} | {mem / 2**20:.0f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_scenes", description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, nargs="*", default=[0, 1, 2], help="scene seeds")
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--noise", type=float, default=0.003, help="range noise, metres")
    ap.add_argument("--methods", nargs="+", default=["splines", "nkf", "poisson"])
    ap.add_argument("--large", action="store_true", help="also the 100k / 1M object table")
    ap.add_argument("--large-meshes", nargs="*", default=None, help="meshes for --large (default: 3 val meshes)")
    ap.add_argument("--large-sizes", type=int, nargs="*", default=[100_000, 1_000_000])
    ap.add_argument("--skip-scenes", action="store_true")
    ap.add_argument("--estimates", action="store_true", help="also predicted against measured time and memory")
    ap.add_argument("--cache", type=Path, default=Path(".bench-cache"))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    warm_up()
    parts = [f"Machine: {machine()}", ""]
    methods = list(args.methods)
    note = ""
    if "nkf" in methods:
        ok, why = nkf_available()
        if not ok:
            methods.remove("nkf")
            note = f"`nkf` skipped: method='nkf' is not available in this installation ({why})."
            log(note)
    kernels = [m for m in methods if m in ("splines", "nkf")]
    if not args.skip_scenes:
        rows = run_scenes(args.scenes, args.points, args.resolution, args.noise, methods, log)
        parts += ["Scenes:", "", format_scenes(rows, args.points, args.resolution, args.noise, note), ""]
    if args.large:
        entries = [e for e in corpus.manifest() if e.split == "val"]
        if args.large_meshes:
            entries = [e for e in entries if e.name in set(args.large_meshes)]
        else:
            entries = [e for e in entries if e.name in ("quaternius__Donut", "kenney__chairRounded", "abc__abc6")]
        rows = run_large(entries, args.large_sizes, args.resolution, args.cache, kernels, log)
        parts += ["Large inputs:", "", format_large(rows, args.resolution), ""]
    if args.estimates:
        parts += ["Estimates (nkf_model.estimate) against measurements:", "", run_estimates(kernels, log), ""]
    text = "\n".join(parts)
    return report(text, args.out)


if __name__ == "__main__":
    sys.exit(main())
