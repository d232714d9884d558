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
from .evaluate import MAX_RESOLUTION, MIN_RESOLUTION
from .fileio import check_output_path, read_point_cloud, write_mesh
from .reconstruct import DEFAULT_LAM, DEFAULT_METHOD, DEFAULT_RESOLUTION, METHODS, check_settings

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
        help="reconstruct a mesh from a PLY point cloud with normals",
        description="Reconstruct a watertight mesh from a PLY point cloud with x y z nx ny nz.",
    )
    r.add_argument("input", help="PLY point cloud (ASCII or binary) with x y z nx ny nz")
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


def cmd_reconstruct(args) -> int:
    from .reconstruct import reconstruct

    check_settings(args.method, args.lam, args.resolution, args.device, None, 6000)
    if args.max_points is not None and args.max_points < 10:
        raise NKFInputError(f"--max-points must be at least 10, got {args.max_points}")
    out = check_output_path(args.output)
    if args.method == "nkf":
        from .weights import load_weights

        load_weights(args.weights)  # a bad weights file fails before the input is read
    t0 = time.perf_counter()
    cloud = read_point_cloud(args.input)
    if cloud.normals is None:
        raise MissingNormalsError(
            f"{args.input}: the points have no normals (nx ny nz); normals are required"
        )
    points, normals = cloud.points, cloud.normals
    if len(points) == 0:
        raise NKFInputError(f"{args.input}: the file holds no points")
    t_read = time.perf_counter() - t0
    if args.max_points is not None and len(points) > args.max_points:
        keep = np.sort(np.random.default_rng(args.seed).choice(len(points), args.max_points, replace=False))
        _say(f"using a random {args.max_points:,} of {len(points):,} points (--max-points)")
        points, normals = points[keep], normals[keep]

    progress, close = _progress_bar(args.quiet)
    cancel = threading.Event()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mesh = reconstruct(points, normals, method=args.method, lam=args.lam, resolution=args.resolution,
                               device=args.device, progress=progress, cancel=cancel, seed=args.seed,
                               weights=args.weights)
    finally:
        close()
    for w in caught:
        _say(f"warning: {w.message}")
    t1 = time.perf_counter()
    write_mesh(out, mesh.vertices, mesh.faces, mesh.normals)
    t_write = time.perf_counter() - t1
    if not args.quiet:
        st = mesh.stats
        stages = dict(read=t_read, **st["timings"], write=t_write)
        times = ", ".join(f"{k} {v:.2f}s" for k, v in stages.items())
        print(
            f"{out}: {st['points_used']:,} points -> {st['triangles']:,} triangles "
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
            from .training import main as train_main

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
