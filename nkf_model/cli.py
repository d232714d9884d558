"""The ``nkf`` command line (also ``python -m nkf_model``).

``nkf reconstruct INPUT OUTPUT.{ply,obj}`` reads points (PLY, LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD),
reconstructs a surface and writes it in the input's coordinate frame (map coordinates included).
Problems with the input or the settings end with one
line on stderr and exit status 1 (2 for unknown options); nothing is written unless the whole run
succeeds.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import warnings

from . import __version__
from .errors import Cancelled, MissingNormalsError, NKFInputError
from .options import SCAN_MIN_PIECE, SCAN_TRIM, SETTING, Options

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
        help="reconstruct a mesh from a point cloud (PLY, LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD)",
        description="Reconstruct a mesh from a point cloud with x y z (normals and colours when present; "
                    "normals are estimated when absent). Formats by extension: .ply .las .laz .e57 .xyz "
                    ".pts .txt .csv .pcd.",
    )
    r.add_argument("input", help="point cloud: .ply (nx/normal_x, red green blue), .las/.laz, .e57 (every scan, "
                                 "with its scanner position), .xyz/.pts/.txt/.csv (columns detected), .pcd")
    r.add_argument("output", help="mesh to write: .ply (binary) or .obj")
    method, lam, res = SETTING["method"], SETTING["lam"], SETTING["resolution"]
    r.add_argument("--method", choices=method.values, default=method.default,
                   help=f"kernel: 'splines' (data-free Neural Splines) or 'nkf' (learned); default {method.default}")
    r.add_argument("--lam", type=float, default=lam.default,
                   help=f"regularisation lambda per constraint, >= 0 (default {lam.default:g}); larger is smoother")
    r.add_argument("--resolution", type=int, default=res.default,
                   help=f"grid cells per side, {res.low}-{res.high} (default {res.default})")
    r.add_argument("--device", choices=SETTING["device"].values, default=SETTING["device"].default,
                   help="where the kernel runs; 'auto' uses a CUDA GPU when present (default auto)")
    r.add_argument("--max-points", type=int, default=None, metavar="N",
                   help="use a random subset of at most N points (said on stderr when it applies)")
    r.add_argument("--seed", type=int, default=SETTING["seed"].default,
                   help="seed for --max-points and solver centres (default 0)")
    s = r.add_argument_group("scans (unoriented, large, open or coloured point clouds)")
    s.add_argument("--normals", choices=SETTING["normals_mode"].values, default=SETTING["normals_mode"].default,
                   help="'given': use the file's nx ny nz (required); 'estimate': estimate them (PCA and "
                        "orientation); 'auto': given if the file has them, else estimate (default)")
    s.add_argument("--orient", choices=SETTING["orientation"].values, default=None,
                   help="orientation of estimated normals: 'outward' (closed objects, default), 'up' "
                        "(terrain, aerial scans), 'viewpoint' (towards --viewpoint; default when one is given)")
    s.add_argument("--viewpoint", type=float, nargs=3, action="append", metavar=("X", "Y", "Z"),
                   help="scanner or camera position in the input's frame (repeat for several); default: "
                        "the scanner positions of an E57 file")
    s.add_argument("--classes", default=None, metavar="C,C,...",
                   help="keep only points of these classification codes (LAS/LAZ; e.g. 2,6 for ground "
                        "and buildings)")
    s.add_argument("--columns", default=None, metavar="NAMES",
                   help="what the columns of a text file (.xyz .pts .txt .csv) are, e.g. 'x y z i r g b' "
                        "(nx ny nz, r g b, i, classification; _ skips one); default: a header line or a guess")
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
    s.add_argument("--keep-outliers", action="store_true",
                   help="keep points far sparser than the surface around them (removed by default from "
                        "10,000 points up: scanner mixed pixels, stray returns)")
    s.add_argument("--no-balloon-check", action="store_true",
                   help="--method nkf: keep the learned surface even where it bulges far beyond sparse points "
                        "(checked by default up to 3,000 points, falling back to the data-free kernel)")
    reduce_to = SETTING["reduce_to"].default
    s.add_argument("--reduce-to", type=int, default=reduce_to, metavar="N",
                   help=f"reduce larger inputs to at most N points by voxel-grid averaging "
                        f"(default {reduce_to:,}; 0: never)")
    s.add_argument("--solver", choices=SETTING["solver"].values, default=SETTING["solver"].default,
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
    t.add_argument("--commit-every", type=float, default=None, metavar="MIN",
                   help="git-commit the run folder (only it) at the first checkpoint MIN minutes after the last "
                        "commit, and at the end, so the run survives the machine")
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


def options_from_args(args) -> Options:
    """The :class:`~nkf_model.options.Options` of ``nkf reconstruct``'s command line (validated)."""
    if args.memory_budget is not None and not args.memory_budget > 0:
        raise NKFInputError(f"--memory-budget must be a positive number of gigabytes, got {args.memory_budget}")
    return Options(
        method=args.method, lam=args.lam, resolution=args.resolution, device=args.device,
        max_points=args.max_points, seed=args.seed, normals_mode=args.normals, orientation=args.orient,
        trim=args.trim if args.trim is not None else (SCAN_TRIM if args.scan else None),
        min_piece=args.min_piece if args.min_piece is not None else (SCAN_MIN_PIECE if args.scan else 0.0),
        close=args.close, outliers=not args.keep_outliers, balloon_check=not args.no_balloon_check,
        reduce_to=None if args.reduce_to == 0 else args.reduce_to, solver=args.solver,
        memory_budget=None if args.memory_budget is None else args.memory_budget * 2**30, weights=args.weights,
    )


def _classes(text):
    """``--classes 2,6`` as a tuple of ints (None when not given)."""
    if text is None:
        return None
    try:
        codes = tuple(int(c) for c in text.replace(" ", "").split(",") if c)
    except ValueError:
        codes = ()
    if not codes or any(not 0 <= c <= 255 for c in codes):
        raise NKFInputError(f"--classes takes classification codes 0-255 separated by commas, got '{text}'")
    return codes


def _load_solver(program: bool):
    """Import the solver. As the program (see :func:`_end_of_process`), without the cyclic garbage
    collector's futile work: importing NumPy, SciPy and numba makes about a million objects, almost
    none of them garbage, and sets off some 250 collections that free nothing (0.1 s); the collector
    is paused meanwhile and what the imports made is then frozen (:func:`gc.freeze`), so that it is
    not traversed later either. An in-process caller's collector is left alone."""
    import gc

    frozen = program and gc.isenabled()
    if frozen:
        gc.disable()
    try:
        from .pipeline.reconstruct import reconstruct
    finally:
        if frozen:
            gc.freeze()
            gc.enable()
    return reconstruct


def cmd_reconstruct(args, program: bool = False) -> int:
    reconstruct = _load_solver(program)
    import numpy as np

    from .io.files import check_output_path, read_point_cloud, write_mesh
    from .pipeline import budget

    opts = options_from_args(args)
    out = check_output_path(args.output)
    if opts.method == "nkf":
        from .kernel.weights import load_weights

        load_weights(opts.weights)  # a bad weights file fails before the input is read
    t0 = time.perf_counter()
    cloud = read_point_cloud(args.input, classes=_classes(args.classes), columns=args.columns)
    if opts.normals_mode == "given" and cloud.normals is None:
        raise MissingNormalsError(
            f"{args.input}: the points have no normals (nx ny nz); normals are required with "
            f"--normals given (use --normals auto or estimate to estimate them)"
        )
    estimate_n = opts.normals_mode == "estimate" or cloud.normals is None
    opts = opts.replace(normals_mode="estimate" if estimate_n else "given")
    points, normals = cloud.points, (None if estimate_n else cloud.normals)
    colors = None if args.no_colors else cloud.colors
    if len(points) == 0:
        raise NKFInputError(f"{args.input}: the file holds no points")
    if cloud.skipped:
        _say(f"warning: dropped {cloud.skipped:,} points with NaN or infinite coordinates")
    # Viewpoints in the points' frame: the user's (file coordinates) less the offset, else the file's own.
    viewpoints = None
    if args.viewpoint:
        viewpoints = [list(map(float, np.asarray(v, np.float64) - cloud.offset)) for v in args.viewpoint]
    elif cloud.viewpoints is not None and estimate_n:
        viewpoints = cloud.viewpoints
        k = len(viewpoints)
        _say(f"{args.input}: orienting estimated normals towards its {k} scanner position{'s' if k != 1 else ''}")
    t_read = time.perf_counter() - t0
    n_used = len(points)
    if opts.max_points is not None and len(points) > opts.max_points:
        n_used = opts.max_points
        _say(f"using a random {opts.max_points:,} of {len(points):,} points (--max-points)")
    est = budget.plan_for(len(points), opts, estimate_normals=estimate_n, colors=colors is not None)
    if args.dry_run:
        print(f"{args.input}: {n_used:,} points; estimate: {est.summary()}")
        budget.enforce(est, opts.memory_budget)
        return 0
    if estimate_n and args.normals == "auto":
        _say(f"{args.input} has no normals: estimating them (--normals auto)")
    if est.reduced:
        _say(f"{n_used:,} points: reducing to at most {opts.reduce_to:,} by voxel-grid averaging (--reduce-to)")

    progress, close = _progress_bar(args.quiet)
    cancel = threading.Event()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mesh = reconstruct(points, normals, options=opts, progress=progress, cancel=cancel,
                               viewpoints=viewpoints, colors=colors)
    finally:
        close()
    for w in caught:
        _say(f"warning: {w.message}")
    t1 = time.perf_counter()
    if np.any(cloud.offset):  # back to the file's (map) coordinates, in float64
        local = np.asarray(mesh.center, np.float64) + np.asarray(mesh.local_vertices, np.float64)
        write_mesh(out, local, mesh.faces, mesh.normals, mesh.colors, offset=cloud.offset)
    else:
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
        if st.get("denoise"):
            extra.append(f"noisy: points moved a median {st['denoise']['moved']:.3g} to the middle of their sheet")
        if st.get("trim"):
            extra.append(f"{st['trim']['trimmed_faces'] + st['trim']['small_piece_faces']:,} triangles trimmed")
        if mesh.colors is not None:
            extra.append("colours")
        note = f" ({'; '.join(extra)})" if extra else ""
        print(
            f"{out}: {st['points_used']:,} points{note} -> {st['triangles']:,} triangles "
            f"({st['vertices']:,} vertices) in {time.perf_counter() - t0:.2f}s [{times}]; "
            f"read {args.input}: {cloud.describe()}"
        )
    return 0


def _end_of_process() -> None:
    """The command is done and the process ends next: leave the cyclic garbage collector out of it.

    Python's shutdown runs a full collection over every object still alive, and after a
    reconstruction these are mostly the hundreds of thousands that numba, llvmlite and SciPy made
    while loading (0.26 s of a 1,000-point ``nkf reconstruct``, ``docs/blender-user.md``).
    :func:`gc.freeze` moves them out of the collector's reach, so the shutdown frees what reference
    counting frees and skips that sweep. Only for the program itself (``main()`` with no
    ``argv``): everything the command writes is closed by then, and an in-process caller (tests,
    scripts calling ``main([...])``) keeps its collector as it was."""
    import gc

    gc.disable()
    gc.freeze()


def main(argv=None) -> int:
    """``nkf`` with ``argv`` (default: this process's command line, and then it runs as the program:
    :func:`_load_solver`, :func:`_end_of_process`)."""
    program = argv is None
    rc = _main(argv, program)
    if program:
        _end_of_process()
    return rc


def _main(argv, program: bool) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    try:
        if args.command == "reconstruct":
            return cmd_reconstruct(args, program)
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
