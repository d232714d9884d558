"""The ``nkf`` command line (also ``python -m nkf_model``).

``nkf reconstruct INPUT.ply OUTPUT.{ply,obj}`` reads oriented points, reconstructs a surface and
writes it in the input's coordinate frame. Problems with the input or the settings end with one
line on stderr and exit status 1 (2 for unknown options); nothing is written unless the whole run
succeeds.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import warnings

import numpy as np

from . import __version__
from .errors import Cancelled, MissingNormalsError, NKFInputError
from .io.files import check_output_path, read_point_cloud, write_mesh
from .normals.estimate import ORIENTATIONS
from .pipeline.reconstruct import (
    DEFAULT_CENTRES,
    DEFAULT_LAM,
    DEFAULT_METHOD,
    DEFAULT_REDUCE_TO,
    DEFAULT_RESOLUTION,
    METHODS,
    NORMALS_MODES,
    SOLVERS,
    check_scan_settings,
    check_settings,
)
from .surface.evaluate import MAX_RESOLUTION, MIN_RESOLUTION
from .surface.trim import SCAN_MIN_PIECE, SCAN_TRIM

EXIT_INPUT = 1
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="nkf",
        description="Surface reconstruction from oriented point clouds (Neural Kernel Fields / Neural Splines).",
    )
    ap.add_argument("--version", action="version", version=f"nkf {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser(
        "reconstruct",
        help="reconstruct a mesh from a PLY point cloud",
        description="Reconstruct a mesh from a PLY point cloud with x y z (nx ny nz and red green blue "
                    "when present; normals are estimated when absent).",
    )
    r.add_argument("input", help="PLY point cloud (ASCII or binary) with x y z, optionally nx ny nz and red green blue")
    r.add_argument("output", help="mesh to write: .ply (binary) or .obj")
    r.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD,
                   help=f"kernel: 'splines' (data-free Neural Splines) or 'nkf' (learned); default {DEFAULT_METHOD}")
    r.add_argument("--lam", type=float, default=DEFAULT_LAM,
                   help=f"regularisation lambda per constraint, >= 0 (default {DEFAULT_LAM:g}); larger is smoother")
    r.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION,
                   help=f"grid cells per side, {MIN_RESOLUTION}-{MAX_RESOLUTION} (default {DEFAULT_RESOLUTION})")
    r.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where the kernel runs; 'auto' uses a CUDA GPU when present (default auto)")
    r.add_argument("--max-points", type=int, default=None, metavar="N",
                   help="use a random subset of at most N points (said on stderr when it applies)")
    r.add_argument("--seed", type=int, default=0, help="seed for --max-points and solver centres (default 0)")
    s = r.add_argument_group("scans (unoriented, large, open or coloured point clouds)")
    s.add_argument("--normals", choices=NORMALS_MODES, default="auto",
                   help="'given': use the file's nx ny nz (required); 'estimate': estimate them (PCA and "
                        "orientation); 'auto': given if the file has them, else estimate (default)")
    s.add_argument("--orient", choices=ORIENTATIONS, default=None,
                   help="orientation of estimated normals: 'outward' (closed objects, default), 'up' "
                        "(terrain, aerial scans), 'viewpoint' (towards --viewpoint; default when one is given)")
    s.add_argument("--viewpoint", type=float, nargs=3, action="append", metavar=("X", "Y", "Z"),
                   help="scanner or camera position in the input's frame (repeat for several)")
    s.add_argument("--scan", action="store_true",
                   help=f"the input is an open scan: trim the surface far from the points and drop small "
                        f"pieces (same as --trim {SCAN_TRIM:g} --min-piece {SCAN_MIN_PIECE:g})")
    s.add_argument("--trim", type=float, default=None, metavar="K",
                   help="cut away the surface farther than K point spacings from every point (default: off)")
    s.add_argument("--min-piece", type=float, default=None, metavar="F",
                   help="drop connected pieces with less than fraction F of the total area (default 0)")
    s.add_argument("--close", action="store_true",
                   help="cap the surface where it meets the grid's bounds, for a watertight mesh")
    s.add_argument("--no-colors", action="store_true",
                   help="do not carry the points' red green blue onto the mesh (carried when present)")
    s.add_argument("--reduce-to", type=int, default=DEFAULT_REDUCE_TO, metavar="N",
                   help=f"reduce larger inputs to at most N points by voxel-grid averaging "
                        f"(default {DEFAULT_REDUCE_TO:,}; 0: never)")
    s.add_argument("--solver", choices=SOLVERS, default="auto",
                   help="'auto' (default): exact up to 3,000 points, else partition of unity; "
                        "'falkon': Nystrom centres")
    s.add_argument("--memory-budget", type=float, default=None, metavar="GB",
                   help="refuse to start if the estimated memory exceeds GB gigabytes "
                        "(default: 60%% of this machine's memory, at most 16)")
    s.add_argument("--dry-run", action="store_true",
                   help="print the time and memory estimate and what would be done, then stop")
    r.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    r.add_argument("--weights", default=None, metavar="PATH",
                   help="weights file (safetensors) for --method nkf; default: the weights shipped in the package")
    r.add_argument("--debug", action="store_true", help="show the full traceback on errors")
    t = sub.add_parser(
        "train",
        help="train the learned kernel (method nkf) on the mesh corpus",
        description="Train the feature network of the learned kernel on the train split of the mesh corpus.",
    )
    t.add_argument("--config", default="configs/nkf.toml", help="TOML training config (default configs/nkf.toml)")
    t.add_argument("--out", default=None, metavar="DIR", help="run folder (default runs/CONFIG-NAME)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    t.add_argument("--max-steps", type=int, default=None, metavar="N", help="stop after N more steps")
    t.add_argument("--stop-after", type=float, default=None, metavar="MIN",
                   help="stop this session after MIN minutes of training (checkpointed; --resume continues)")
    t.add_argument("--quiet", action="store_true", help="no progress bar; log lines on stderr instead")
    t.add_argument("--debug", action="store_true", help="show the full traceback on errors")
    return ap


def _say(msg: str) -> None:
    print(f"nkf: {msg}", file=sys.stderr, flush=True)


def _progress_bar(quiet: bool):
    if quiet:
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=1000, file=sys.stderr, bar_format="{desc:<10} {percentage:3.0f}%|{bar}| {elapsed}",
               leave=False, dynamic_ncols=True)

    def progress(fraction, stage):
        bar.set_description_str(stage, refresh=False)
        bar.n = int(round(1000 * fraction))
        bar.refresh()

    return progress, bar.close


def _scan_settings(args):
    """trim, min_piece, reduce_to and memory budget (bytes) from the command line."""
    trim = args.trim if args.trim is not None else (SCAN_TRIM if args.scan else None)
    min_piece = args.min_piece if args.min_piece is not None else (SCAN_MIN_PIECE if args.scan else 0.0)
    reduce_to = None if args.reduce_to == 0 else args.reduce_to
    budget = None if args.memory_budget is None else args.memory_budget * 2**30
    if args.memory_budget is not None and not args.memory_budget > 0:
        raise NKFInputError(f"--memory-budget must be a positive number of gigabytes, got {args.memory_budget}")
    return trim, min_piece, reduce_to, budget


def cmd_reconstruct(args) -> int:
    from .pipeline import budget as budget_mod
    from .pipeline.reconstruct import reconstruct

    check_settings(args.method, args.lam, args.resolution, args.device, None, DEFAULT_CENTRES)
    trim, min_piece, reduce_to, memory_budget = _scan_settings(args)
    check_scan_settings("auto", None, args.solver, reduce_to, trim, min_piece)
    if args.max_points is not None and args.max_points < 10:
        raise NKFInputError(f"--max-points must be at least 10, got {args.max_points}")
    out = check_output_path(args.output)
    if args.method == "nkf":
        from .kernel.weights import load_weights

        load_weights(args.weights)  # a bad weights file fails before the input is read
    t0 = time.perf_counter()
    cloud = read_point_cloud(args.input)
    if args.normals == "given" and cloud.normals is None:
        raise MissingNormalsError(
            f"{args.input}: the points have no normals (nx ny nz); normals are required with "
            f"--normals given (use --normals auto or estimate to estimate them)"
        )
    estimate_n = args.normals == "estimate" or cloud.normals is None
    points, normals = cloud.points, (None if estimate_n else cloud.normals)
    colors = None if args.no_colors else cloud.colors
    if len(points) == 0:
        raise NKFInputError(f"{args.input}: the file holds no points")
    t_read = time.perf_counter() - t0
    if args.max_points is not None and len(points) > args.max_points:
        keep = np.sort(np.random.default_rng(args.seed).choice(len(points), args.max_points, replace=False))
        _say(f"using a random {args.max_points:,} of {len(points):,} points (--max-points)")
        points = points[keep]
        normals = None if normals is None else normals[keep]
        colors = None if colors is None else colors[keep]
    est = budget_mod.plan(len(points), resolution=args.resolution, estimate_normals=estimate_n, solver=args.solver,
                          max_centres=DEFAULT_CENTRES, reduce_to=reduce_to, colors=colors is not None,
                          trim=trim is not None, method=args.method)
    if args.dry_run:
        print(f"{args.input}: {len(points):,} points; estimate: {est.summary()}")
        budget_mod.check(est, memory_budget)
        return 0
    if estimate_n and args.normals == "auto":
        _say(f"{args.input} has no normals: estimating them (--normals auto)")
    if est.reduced:
        _say(f"{len(points):,} points: reducing to at most {reduce_to:,} by voxel-grid averaging (--reduce-to)")

    progress, close = _progress_bar(args.quiet)
    cancel = threading.Event()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mesh = reconstruct(points, normals, method=args.method, lam=args.lam, resolution=args.resolution,
                               device=args.device, progress=progress, cancel=cancel, seed=args.seed,
                               normals_mode="estimate" if estimate_n else "given", orientation=args.orient,
                               viewpoints=args.viewpoint, colors=colors, trim=trim, min_piece=min_piece,
                               reduce_to=reduce_to, solver=args.solver, memory_budget=memory_budget,
                               weights=args.weights, close=args.close)
    finally:
        close()
    for w in caught:
        _say(f"warning: {w.message}")
    t1 = time.perf_counter()
    write_mesh(out, mesh.vertices, mesh.faces, mesh.normals, mesh.colors)
    t_write = time.perf_counter() - t1
    if not args.quiet:
        st = mesh.stats
        stages = dict(read=t_read, **st["timings"], write=t_write)
        times = ", ".join(f"{k} {v:.2f}s" for k, v in stages.items())
        extra = []
        if st.get("reduction"):
            extra.append(f"reduced from {st['reduction']['from']:,}")
        if st.get("normals") == "estimated":
            extra.append("normals estimated")
        if st.get("trim"):
            extra.append(f"{st['trim']['trimmed_faces'] + st['trim']['small_piece_faces']:,} triangles trimmed")
        if mesh.colors is not None:
            extra.append("colours")
        note = f" ({'; '.join(extra)})" if extra else ""
        print(
            f"{out}: {st['points_used']:,} points{note} -> {st['triangles']:,} triangles "
            f"({st['vertices']:,} vertices) in {time.perf_counter() - t0:.2f}s [{times}]"
        )
    return 0


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    try:
        if args.command == "reconstruct":
            return cmd_reconstruct(args)
        if args.command == "train":
            from .train.kernel_training import main as train_main

            return train_main(args)
        ap.error(f"unknown command {args.command}")  # pragma: no cover - argparse guards this
    except NKFInputError as exc:
        if args.debug:
            raise
        _say(f"error: {exc}")
        return EXIT_INPUT
    except (KeyboardInterrupt, Cancelled):
        _say("interrupted; nothing was written")
        return EXIT_INTERRUPTED
    except MemoryError:
        if args.debug:
            raise
        _say("error: out of memory; lower --resolution or --max-points")
        return EXIT_INTERNAL
    except Exception as exc:  # an unexpected failure: say it in one line unless --debug
        if args.debug:
            raise
        _say(f"internal error: {type(exc).__name__}: {exc} (run with --debug for the traceback)")
        return EXIT_INTERNAL
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
