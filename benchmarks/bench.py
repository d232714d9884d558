"""Benchmark: ``nkf`` and ``splines`` against screened Poisson on the corpus's validation meshes.

Run ``python -m benchmarks.bench`` (Poisson needs the ``bench`` extra: Open3D, which on Debian also
needs ``libusb-1.0-0``). It prints Markdown tables:

1. quality and cost per (points, noise, method): IoU, Chamfer-L1, normal consistency, F-score
   (ConvONet protocol, see :mod:`nkf_model.train.metrics`), wall time of the reconstruction call, and
   its peak memory (resident-set growth over the call, sampled every 5 ms);
2. ``--tradeoff``: Falkon's size (Nystrom centres) against IoU and time at 10,000 points, beside the default
   partition-of-unity solver;
3. ``--growth``: grid points and kernel evaluations from resolution 64 to 512;
4. ``--overhead N``: the extra wall time of ``nkf`` over ``splines`` at 1,000 points, resolution 128.

``--rows FILE.json`` saves the main table's per-mesh results; ``--merge A.json B.json ...`` prints (and
plots) one table from runs made separately, for example one process per point count.

``--methods nkf splines poisson`` adds the learned kernel (``--weights PATH``, default the shipped
weights), ``--half 3000`` adds half-surface inputs (points from one side of a random plane through the
centre of each mesh's box), and ``--plot FILE.png`` draws mean IoU against the number of input points.

Reference samples and occupancies of each validation mesh are cached in ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from nkf_model.pipeline.reconstruct import reconstruct
from nkf_model.train import corpus, metrics

N_EVAL = 100_000
DEFAULT_RES = {300: 128, 1000: 128, 3000: 128, 10000: 256}


class PeakRSS:
    """Peak resident-set growth of this process during a ``with`` block, in bytes.

    Linux keeps the high-water mark of the resident set (``VmHWM``); writing 5 to
    ``/proc/self/clear_refs`` resets it to the current size, so the peak of the block is exact, however
    short. Where that is not allowed, a thread samples the resident set every ``interval`` seconds.
    """

    def __init__(self, interval=0.005):
        self.interval = interval
        self.peak = 0

    @staticmethod
    def _status(key):
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
        raise OSError(key)

    @staticmethod
    def _rss():
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss() - self.base)
            time.sleep(self.interval)

    def __enter__(self):
        self.base = self._rss()
        self._t = None
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")
            self._hwm = True
        except OSError:
            self._hwm = False
            self._stop = threading.Event()
            self._t = threading.Thread(target=self._run, daemon=True)
            self._t.start()
        return self

    def __exit__(self, *exc):
        if self._hwm:
            self.peak = max(0, self._status("VmHWM") - self.base)
        else:
            self._stop.set()
            self._t.join()
            self.peak = max(self.peak, self._rss() - self.base)


def reference(entry, cache: Path):
    """Cached reference samples of a corpus mesh: surface points/normals, volume points, their
    winding numbers and occupancy (``w > 0.5``)."""
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"{entry.name}.npz"
    if path.exists():
        d = np.load(path)
        d = {k: d[k] for k in d.files}
        if "vol_w" not in d:  # caches written before the winding numbers were kept
            v, f = corpus.load(entry)
            d["vol_w"] = metrics.winding_number(v, f, d["vol_pts"]).astype(np.float32)
            np.savez_compressed(path, **d)
        return d
    v, f = corpus.load(entry)
    rng = np.random.default_rng(corpus.stable_seed("reference", entry.name))
    sp, sn = metrics.sample_surface(v, f, N_EVAL, rng)
    vol = metrics.volume_points(N_EVAL, rng)
    w = metrics.winding_number(v, f, vol)
    d = {"surf_pts": sp, "surf_nrm": sn, "vol_pts": vol, "vol_occ": w > 0.5, "vol_w": w.astype(np.float32)}
    np.savez_compressed(path, **d)
    return d


def _mesh_occupancy(v, f, q):
    try:
        import open3d as o3d
    except ImportError:
        return metrics.occupancy(v, f, q)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
    occ = scene.compute_occupancy(o3d.core.Tensor(np.asarray(q, np.float32)), nsamples=3)
    return occ.numpy() > 0.5


def score(v, f, ref, seed):
    """All metrics of a predicted mesh (in the reference's unit box) against cached reference data."""
    if len(f) == 0:
        return {"iou": 0.0, "chamfer_l1": float("nan"), "normal_consistency": 0.0, "fscore": 0.0}
    rng = np.random.default_rng(seed)
    pp, pn = metrics.sample_surface(v, f, N_EVAL, rng)
    out = metrics.surface_metrics(pp, pn, ref["surf_pts"], ref["surf_nrm"])
    out["iou"] = metrics.iou(_mesh_occupancy(v, f, ref["vol_pts"]), ref["vol_occ"])
    return out


def run_splines(pts, nrm, resolution, **kw):
    m = reconstruct(pts, nrm, method="splines", resolution=resolution, device="cpu", **kw)
    return m.vertices.astype(np.float64), m.faces, m.stats


def run_nkf(pts, nrm, resolution, weights=None, **kw):
    m = reconstruct(pts, nrm, method="nkf", resolution=resolution, device="cpu", weights=weights, **kw)
    return m.vertices.astype(np.float64), m.faces, m.stats


def half_input(vertices, faces, n_points: int, noise: float, seed: int):
    """Oriented input points from one side of a random plane through the centre of the mesh's box.

    ``n_points`` uniform surface samples with ``(p - c) . d > 0`` for a direction ``d`` drawn from
    ``seed`` and the box centre ``c`` (the origin of the corpus's unit box), then Gaussian position
    noise of standard deviation ``noise``; normals of the true surface.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    v = np.asarray(vertices, np.float64)
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    pts, nrm = np.zeros((0, 3)), np.zeros((0, 3))
    draw = 2 * n_points
    for _ in range(20):
        p, q = metrics.sample_surface(vertices, faces, draw, rng)
        keep = (p - c) @ d > 0
        pts, nrm = np.concatenate([pts, p[keep]]), np.concatenate([nrm, q[keep]])
        if len(pts) >= n_points:
            break
        draw *= 2
    pts, nrm = pts[:n_points], nrm[:n_points]
    if noise > 0:
        pts = pts + rng.normal(scale=noise, size=pts.shape)
    return pts, nrm


def run_poisson(pts, nrm, depth=8):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(nrm)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles), {}


def measure(fn, *args, **kw):
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        try:
            v, f, stats = fn(*args, **kw)
            err = None
        except Exception as exc:  # a failure is a result of the benchmark, not a crash
            v, f, stats, err = np.zeros((0, 3)), np.zeros((0, 3), np.int64), {}, str(exc)
        dt = time.perf_counter() - t0
    return v, f, stats, dt, mem.peak, err


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba
    import scipy

    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}, numba {numba.__version__}"
    )


def warm_up(weights=None):
    """Compile (or load from numba's cache) every kernel before timing anything."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(400, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    reconstruct(p, p, method="splines", resolution=32, device="cpu")
    reconstruct(p, p, method="splines", resolution=32, device="cpu", max_centres=300)
    if weights is not False:
        try:
            reconstruct(p, p, method="nkf", resolution=32, device="cpu", weights=weights)
            reconstruct(p, p, method="nkf", resolution=32, device="cpu", max_centres=300, weights=weights)
        except ValueError:
            pass  # no weights: the nkf rows report the error


def main_table(entries, points, noises, methods, cache, res_override=None, log=print, weights=None, half=()):
    """Rows ``(label, resolution, noise, method, results)`` for every (points, noise, method), then the
    half-surface inputs (``half``: point counts, noise-free), each over all ``entries``."""
    rows = []
    modes = [(n, noise, False) for n in points for noise in noises] + [(n, 0.0, True) for n in half]
    for n, noise, is_half in modes:
        res = res_override or DEFAULT_RES.get(n, 128)
        label = f"{n} half" if is_half else str(n)
        for method in methods:
            results = []
            for e in entries:
                ref = reference(e, cache)
                v0, f0 = corpus.load(e)
                if is_half:
                    pts, nrm = half_input(v0, f0, n, noise, corpus.stable_seed("half-input", e.name, n, noise))
                else:
                    pts, nrm = corpus.sample_input(v0, f0, n, noise, corpus.stable_seed("input", e.name, n, noise))
                if method == "splines":
                    v, f, stats, dt, mem, err = measure(run_splines, pts, nrm, res)
                elif method == "nkf":
                    v, f, stats, dt, mem, err = measure(run_nkf, pts, nrm, res, weights)
                else:
                    v, f, stats, dt, mem, err = measure(run_poisson, pts, nrm)
                s = score(v, f, ref, corpus.stable_seed("score", e.name, n, noise, method, *(["half"] * is_half)))
                s.update(time=dt, mem=mem, err=err, mesh=e.name)
                results.append(s)
                log(
                    f"  {method:8s} n={label:>10s} noise={noise:<6} {e.name:40s} IoU {s['iou']:.3f} "
                    f"CD {s['chamfer_l1']:.4f} t {dt:6.2f}s mem {mem / 2**20:7.0f} MiB"
                    + (f"  FAILED: {err}" if err else "")
                )
            rows.append((label, res, noise, method, results))
    return rows


def plot_iou(rows, path: Path, title: str = "") -> Path:
    """PNG of mean IoU against the number of input points, one line per method, one panel per noise
    level (half-surface rows as separate markers), like the figure of the NKF paper."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    noises = sorted({noise for _, _, noise, _, _ in rows})
    fig, axes = plt.subplots(1, len(noises), figsize=(5.2 * len(noises), 4), squeeze=False)
    colours = {"nkf": "C3", "splines": "C0", "poisson": "C2"}
    for ax, noise in zip(axes[0], noises):
        for method in dict.fromkeys(m for _, _, _, m, _ in rows):
            pts = sorted(
                (int(label), statistics.mean(r["iou"] for r in res))
                for label, _, nz, m, res in rows
                if m == method and nz == noise and label.isdigit()
            )
            if pts:
                x, y = zip(*pts)
                ax.plot(x, y, "o-", color=colours.get(method), label=method)
            half = [(int(label.split()[0]), statistics.mean(r["iou"] for r in res))
                    for label, _, nz, m, res in rows if m == method and nz == noise and not label.isdigit()]
            for x, y in half:
                ax.plot([x], [y], "^", ms=9, color=colours.get(method), mfc="none",
                        label=f"{method}, half surface")
        ax.set_xscale("log")
        ticks = sorted({int(label.split()[0]) for label, _, _, _, _ in rows})
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t:,}" for t in ticks])
        ax.minorticks_off()
        ax.set_xlabel("input points")
        ax.set_ylabel("mean IoU")
        ax.set_title(f"noise {noise:g}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def format_main(rows) -> str:
    out = [
        "| points | resolution | noise | method | IoU | Chamfer-L1 | normal consistency | F-score (1%) "
        "| mean time (s) | max time (s) | peak memory (MiB) | failures |",
        "|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n, res, noise, method, results in rows:
        ok = [r for r in results if not r["err"]]
        cds = [r["chamfer_l1"] for r in ok]
        res_s = "depth 8" if method == "poisson" else str(res)
        out.append(
            f"| {n} | {res_s} | {noise} | {method} | {statistics.mean(r['iou'] for r in results):.4f} "
            f"| {statistics.mean(cds) if cds else float('nan'):.5f} "
            f"| {statistics.mean(r['normal_consistency'] for r in results):.4f} "
            f"| {statistics.mean(r['fscore'] for r in results):.4f} "
            f"| {statistics.mean(r['time'] for r in results):.3f} | {max(r['time'] for r in results):.3f} "
            f"| {max(r['mem'] for r in results) / 2**20:.0f} | {len(results) - len(ok)} |"
        )
    return "\n".join(out)


def tradeoff(entries, cache, centres_list, n=10000, res=256, log=print) -> str:
    lines = [
        "| Nystrom centres | solver | mean IoU | mean Chamfer-L1 | mean time (s) | mean solve (s) |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    # Falkon with each number of centres, then the default solver (partition of unity) for comparison.
    for c in list(centres_list) + [None]:
        kw = {"max_centres": c, "solver": "falkon"} if c is not None else {}
        ious, cds, ts, ss = [], [], [], []
        solver = ""
        for e in entries:
            ref = reference(e, cache)
            v0, f0 = corpus.load(e)
            pts, nrm = corpus.sample_input(v0, f0, n, 0.0, corpus.stable_seed("input", e.name, n, 0.0))
            v, f, stats, dt, mem, err = measure(run_splines, pts, nrm, res, **kw)
            s = score(v, f, ref, corpus.stable_seed("score", e.name, n, 0.0, "splines"))
            ious.append(s["iou"])
            cds.append(s["chamfer_l1"])
            ts.append(dt)
            ss.append(stats.get("timings", {}).get("solve", float("nan")))
            solver = stats.get("solver", "failed")
            log(f"  centres={c or '-'!s:>6} {e.name:40s} IoU {s['iou']:.3f} t {dt:.2f}s")
        lines.append(
            f"| {c if c is not None else '-'} | {solver} | {statistics.mean(ious):.4f} | {statistics.mean(cds):.5f} "
            f"| {statistics.mean(ts):.2f} | {statistics.mean(ss):.2f} |"
        )
    return "\n".join(lines)


def overhead(entries, weights=None, n=1000, res=128, repeats=3, log=print) -> str:
    """Wall time of ``nkf`` against ``splines`` on the same inputs (the median of ``repeats`` calls
    each, alternating), and the learned kernel's extra cost per input: a table."""
    return format_overhead(overhead_times(entries, weights, n, res, repeats, log))


def overhead_times(entries, weights=None, n=1000, res=128, repeats=3, log=print) -> list[tuple[float, float]]:
    """``(splines seconds, nkf seconds)`` per input, each the median of ``repeats`` alternating calls."""
    rows = []
    for e in entries:
        v0, f0 = corpus.load(e)
        pts, nrm = corpus.sample_input(v0, f0, n, 0.0, corpus.stable_seed("input", e.name, n, 0.0))
        ts = {"splines": [], "nkf": []}
        for _ in range(repeats):
            for method in ts:
                t0 = time.perf_counter()
                reconstruct(pts, nrm, method=method, resolution=res, device="cpu", weights=weights)
                ts[method].append(time.perf_counter() - t0)
        t_s, t_n = statistics.median(ts["splines"]), statistics.median(ts["nkf"])
        rows.append((t_s, t_n))
        log(f"  overhead {e.name:40s} splines {t_s:.3f}s nkf {t_n:.3f}s (+{t_n - t_s:.3f}s)")
    return rows


def format_overhead(rows) -> str:
    extra = [t_n - t_s for t_s, t_n in rows]
    return "\n".join([
        "| inputs | splines, mean (s) | nkf, mean (s) | extra, mean (s) | extra, max (s) |",
        "|---:|---:|---:|---:|---:|",
        f"| {len(rows)} | {statistics.mean(r[0] for r in rows):.3f} | {statistics.mean(r[1] for r in rows):.3f} "
        f"| {statistics.mean(extra):.3f} | {max(extra):.3f} |",
    ])


def growth(entry, n=1000, resolutions=(64, 128, 256, 512), log=print) -> str:
    v0, f0 = corpus.load(entry)
    pts, nrm = corpus.sample_input(v0, f0, n, 0.0, corpus.stable_seed("input", entry.name, n, 0.0))
    lines = [
        "| resolution | grid points evaluated | dense grid (R+1)^3 | kernel evaluations | ratio to previous "
        "| time (s) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    prev = None
    for r in resolutions:
        t0 = time.perf_counter()
        m = reconstruct(pts, nrm, method="splines", resolution=r, device="cpu")
        dt = time.perf_counter() - t0
        k = m.stats["kernel_evaluations_grid"]
        ratio = f"{k / prev:.2f}" if prev else ""
        prev = k
        lines.append(
            f"| {r} | {m.stats['grid_points_evaluated']:,} | {(r + 1) ** 3:,} | {k:,} | {ratio} | {dt:.2f} |"
        )
        log(f"  growth R={r} evals={k:,} t={dt:.2f}s")
    return "\n".join(lines)


def report(text: str, out: Path | None = None) -> int:
    """Print a benchmark's Markdown ``text`` and, with ``out``, also write it there; exit status 0."""
    print(text)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    return 0


def save_rows(rows, path: Path, meshes, split: str) -> Path:
    """Write the rows of :func:`main_table` (with the machine and the meshes) to a JSON file."""
    doc = {"machine": machine(), "split": split, "meshes": list(meshes),
           "rows": [{"label": label, "resolution": res, "noise": noise, "method": method, "results": results}
                    for label, res, noise, method, results in rows]}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, default=float))
    return path


def merge(paths, plot: Path | None = None, out: Path | None = None) -> int:
    """Print one main table (and plot) from JSON files of :func:`save_rows` over the same meshes."""
    docs = [json.loads(Path(p).read_text()) for p in paths]
    meshes = docs[0]["meshes"]
    for p, d in zip(paths, docs):
        if d["meshes"] != meshes:
            raise SystemExit(f"{p}: other meshes than {paths[0]}; merge runs over the same meshes only")
    order = {"nkf": 0, "splines": 1, "poisson": 2}
    rows = [(r["label"], r["resolution"], r["noise"], r["method"], r["results"]) for d in docs for r in d["rows"]]
    rows.sort(key=lambda r: ("half" in r[0], int(r[0].split()[0]), r[2], order.get(r[3], 9)))
    machines = sorted({d["machine"] for d in docs})
    text = "\n".join([f"Machine: {'; '.join(machines)}", "",
                      f"Meshes: {len(meshes)} ({docs[0]['split']} split), merged from {len(docs)} runs", "",
                      format_main(rows), ""])
    if plot:
        plot_iou(rows, plot, title=f"{len(meshes)} {docs[0]['split']} meshes of the corpus")
    return report(text, out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench", description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.005])
    ap.add_argument("--methods", nargs="+", default=["splines", "poisson"], choices=["nkf", "splines", "poisson"])
    ap.add_argument("--weights", default=None, help="weights file for nkf (default: the shipped weights)")
    ap.add_argument("--half", type=int, nargs="*", default=[], metavar="POINTS",
                    help="also run half-surface inputs (one side of a plane through the centre) of these sizes")
    ap.add_argument("--plot", type=Path, default=None, help="write a PNG of mean IoU against input points")
    ap.add_argument("--resolution", type=int, default=None, help="override the per-size resolution")
    ap.add_argument("--limit", type=int, default=None, help="use only the first N validation meshes")
    ap.add_argument("--split", default="val")
    ap.add_argument("--tradeoff", type=int, nargs="*", default=None, metavar="CENTRES",
                    help="also print solver size vs IoU/time at 10,000 points for these centre counts")
    ap.add_argument("--tradeoff-limit", type=int, default=12, help="meshes used for the trade-off table")
    ap.add_argument("--growth", action="store_true", help="also print kernel evaluations vs resolution")
    ap.add_argument("--overhead", type=int, default=0, metavar="MESHES",
                    help="also time nkf against splines at 1,000 points, resolution 128, on this many meshes")
    ap.add_argument("--skip-main", action="store_true")
    ap.add_argument("--cache", type=Path, default=Path(".bench-cache"))
    ap.add_argument("--out", type=Path, default=None, help="also write the tables to this Markdown file")
    ap.add_argument("--rows", type=Path, default=None,
                    help="also write the main table's per-mesh results to this JSON file (for --merge)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, metavar="JSON",
                    help="run nothing: print (and --plot) the main table of runs saved with --rows, "
                         "e.g. point counts run in parallel processes")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.plot, args.out)
    warnings.filterwarnings("ignore", message=".*TBB.*")
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))

    entries = [e for e in corpus.manifest() if e.split == args.split]
    if args.limit:
        entries = entries[: args.limit]
    warm_up(args.weights if ("nkf" in args.methods or args.overhead) else False)
    parts = [f"Machine: {machine()}", ""]
    if not args.skip_main:
        rows = main_table(entries, args.points, args.noise, args.methods, args.cache, args.resolution, log,
                          weights=args.weights, half=args.half)
        parts += [f"Meshes: {len(entries)} ({args.split} split)", "", format_main(rows), ""]
        if args.rows:
            save_rows(rows, args.rows, meshes=[e.name for e in entries], split=args.split)
        if args.plot:
            plot_iou(rows, args.plot, title=f"{len(entries)} {args.split} meshes of the corpus")
    if args.tradeoff is not None:
        cl = args.tradeoff or [2000, 4000, 6000, 8000]
        sub = entries[: args.tradeoff_limit]
        parts += [f"Solver size at 10,000 points, resolution 256, {len(sub)} meshes:", "",
                  tradeoff(sub, args.cache, cl, log=log), ""]
    if args.overhead:
        parts += [f"Extra time of nkf over splines (1,000 points, resolution 128, median of 3 calls each, "
                  f"{args.overhead} meshes):", "", overhead(entries[: args.overhead], args.weights, log=log), ""]
    if args.growth:
        parts += [f"Kernel evaluations against resolution (1,000 points, {entries[0].name}):", "",
                  growth(entries[0], log=log), ""]
    text = "\n".join(parts)
    return report(text, args.out)


if __name__ == "__main__":
    sys.exit(main())
