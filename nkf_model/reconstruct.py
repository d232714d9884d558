"""The whole pipeline: oriented points in, triangle mesh out.

normalise -> augment -> solve -> evaluate -> mesh, each stage in its own module. This module only
checks settings, wires the stages together and records what each one did.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from .augment import augment, default_eps
from .engines import select_engine
from .errors import InvalidParameterError, NoSurfaceError
from .evaluate import MAX_RESOLUTION, MIN_RESOLUTION, evaluate_sparse
from .inputs import clean_points
from .kernel import homogeneous
from .mesh import Mesh, triangulate, vertex_normals
from .normalise import Normalisation
from .progress import Tracker
from .sampling import farthest_point_sample
from .solve import KernelFunction, solve_dense, solve_falkon
from .weights import has_default_weights, load_weights

METHODS = ("splines", "nkf")
# The learned kernel is the default when the package ships its weights; "splines" needs none.
DEFAULT_METHOD = "nkf" if has_default_weights() else "splines"
DEFAULT_LAM = 1e-10
DEFAULT_RESOLUTION = 128
# Up to this many constraints (2 per point) the solve is exact; beyond it, Falkon with this many
# Nystrom centres. See docs/benchmarks.md for the trade-off of this number against IoU and time.
DEFAULT_CENTRES = 6000
# Relative residual at which Falkon's conjugate gradient stops: 1e-6 gave the same IoU and Chamfer as
# 1e-9 on 12 validation meshes at 10,000 points, in 17 iterations instead of 25.
FALKON_TOL = 1e-6
# Threads for dense linear algebra (OpenBLAS). One: on a busy 2-core machine (Blender's UI, another
# job) two OpenBLAS threads ran a 2,000 x 2,000 Cholesky 8x slower than one, and a 6,000 one 2x slower.
BLAS_THREADS = 1


class InputWarning(UserWarning):
    """Some input rows were dropped (NaN, infinite, zero-length normals, duplicates)."""


def check_settings(method, lam, resolution, device, eps, max_centres) -> None:
    """Raise :class:`InvalidParameterError` for a setting out of range."""
    if method not in METHODS:
        raise InvalidParameterError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
        raise InvalidParameterError(f"resolution must be an integer, got {resolution!r}")
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise InvalidParameterError(
            f"resolution must be between {MIN_RESOLUTION} and {MAX_RESOLUTION}, got {resolution}"
        )
    try:
        lam_f = float(lam)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"lambda must be a number, got {lam!r}") from None
    if not math.isfinite(lam_f) or lam_f < 0:
        raise InvalidParameterError(f"lambda must be a finite number >= 0, got {lam!r}")
    if device not in ("auto", "cpu", "cuda"):
        raise InvalidParameterError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    if eps is not None and not (isinstance(eps, (int, float)) and 0 < eps <= 0.1):
        raise InvalidParameterError(f"eps must be in (0, 0.1] of the bounding box, got {eps!r}")
    if isinstance(max_centres, bool) or not isinstance(max_centres, (int, np.integer)) or max_centres < 100:
        raise InvalidParameterError(f"max_centres must be an integer >= 100, got {max_centres!r}")


def reconstruct(
    points,
    normals,
    *,
    method: str = DEFAULT_METHOD,
    lam: float = DEFAULT_LAM,
    resolution: int = DEFAULT_RESOLUTION,
    device: str = "auto",
    progress: Callable[[float, str], None] | None = None,
    cancel=None,
    eps: float | None = None,
    max_centres: int = DEFAULT_CENTRES,
    seed: int = 0,
    weights=None,
) -> Mesh:
    """Reconstruct a watertight surface from oriented points.

    Parameters
    ----------
    points : array_like, (N, 3)
        Positions in any units and any coordinate frame (float32 or float64).
    normals : array_like, (N, 3)
        Outward normals, one per point; any positive length.
    method : {"splines", "nkf"}
        ``"splines"``: the data-free Neural Splines kernel, no weights needed.
        ``"nkf"``: the learned Neural Kernel Field kernel (needs weights; the default when the
        package ships them, see :func:`nkf_model.weights.has_default_weights`).
    lam : float
        Regularisation per constraint, >= 0 (the paper's lambda; the solve uses
        ``(G + 2N lam I) alpha = y``). Larger values smooth the surface; 1e-12 to 1e-8 fit the points.
    resolution : int
        Cells per side of the marching-cubes grid, 16 to 1024. The grid spans the input's
        bounding box plus 5 % on each side.
    device : {"auto", "cpu", "cuda"}
        ``"auto"`` uses a CUDA GPU when PyTorch sees one, else the CPU.
    progress : callable, optional
        ``progress(fraction, stage)``: ``fraction`` in [0, 1], ``stage`` one of ``"normalise"``,
        ``"augment"``, ``"features"`` (nkf only), ``"solve"``, ``"evaluate"``, ``"mesh"``, then ``"done"``.
    cancel : threading.Event, optional
        When set, the work stops within 0.5 s by raising :class:`~nkf_model.errors.Cancelled`.
    eps : float, optional
        Offset of the constraints along the normals, as a fraction of the bounding box's longest
        side. Default: 0.01 up to 3,000 points, then shrinking with the point spacing.
    max_centres : int
        Largest exact solve (in constraints, 2 per point); larger inputs use this many Nystrom
        centres.
    seed : int
        Seed for the choice of Nystrom centres.
    weights : str or os.PathLike, optional
        Weights file (safetensors) for ``method="nkf"``; default: the weights shipped in the
        package. Ignored by ``method="splines"``.

    Returns
    -------
    Mesh
        ``vertices`` (V, 3) float32 in the input's frame, ``faces`` (F, 3) int32 facing out,
        ``normals`` (V, 3) float32, and ``stats`` (counts, warnings, time per stage in seconds).

    Raises
    ------
    nkf_model.errors.NKFInputError
        A ``ValueError`` subclass for every bad input or setting (see :mod:`nkf_model.errors`);
        :class:`~nkf_model.errors.WeightsError` for a missing, corrupt or mismatched weights file.
    nkf_model.errors.Cancelled
        ``cancel`` was set.
    """
    check_settings(method, lam, resolution, device, eps, max_centres)
    model = load_weights(weights) if method == "nkf" else None
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        return _reconstruct(
            points, normals, method, lam, resolution, device, progress, cancel, eps, max_centres, seed, model
        )


def _reconstruct(points, normals, method, lam, resolution, device, progress, cancel, eps, max_centres, seed, model):
    t_start = time.perf_counter()
    engine = select_engine(device)
    stages = ("normalise", "augment") + (("features",) if model is not None else ()) + ("solve", "evaluate", "mesh")
    track = Tracker(progress, cancel, stages=stages)
    track.begin("normalise")
    clean = clean_points(points, normals)
    for line in clean.warnings():
        warnings.warn(line, InputWarning, stacklevel=3)
    norm = Normalisation.fit(clean.points)
    x = norm.to_unit(clean.points)
    n = len(x)

    track.begin("augment")
    eps_used = float(eps) if eps is not None else default_eps(n)
    xa, y = augment(x, clean.normals, eps_used)
    phi = None
    if model is None:
        a = homogeneous(xa)
    else:
        track.begin("features")
        prep = model.prepare(xa, y)
        a, y, phi = prep.a, prep.y, prep.phi

    track.begin("solve")
    if len(a) <= max_centres:
        alpha, info = solve_dense(a, y, float(lam), engine, check=track.check)
        centres = a
    else:
        half = farthest_point_sample(x, max_centres // 2, seed=seed)
        idx = np.concatenate([half, half + n])
        alpha, info = solve_falkon(a, y, idx, float(lam), engine, tol=FALKON_TOL, check=track.check, step=track.step)
        centres = a[idx]
    fn = KernelFunction(centres, alpha, engine, features=phi)

    track.begin("evaluate")
    field_ = evaluate_sparse(
        lambda p: fn(p, check=track.check), resolution, check=track.check, step=track.step, seeds=x
    )

    track.begin("mesh")
    unit_v, faces = triangulate(field_, check=track.check, step=track.step)
    if len(faces) == 0:
        raise NoSurfaceError(
            "the fitted function has no zero crossing inside the grid; check that the normals "
            "point out of the surface, or lower lambda"
        )
    normals_v = vertex_normals(unit_v, faces)
    local = unit_v * norm.scale
    track.finish()
    stats = {
        "method": method,
        "weights": str(model.meta.get("path", "")) if model is not None else None,
        "points_in": int(np.asarray(points).shape[0]),
        "points_used": n,
        "dropped": dict(clean.dropped),
        "warnings": clean.warnings(),
        "eps": eps_used,
        "lam": float(lam),
        "solver": info.method,
        "centres": info.centres,
        "cg_iterations": info.iterations,
        "kernel_evaluations_grid": int(field_.evaluations) * len(centres),
        "grid_points_evaluated": int(field_.evaluations),
        "level_evaluations": field_.level_evaluations,
        "engine": f"{engine.name}:{engine.device}",
        "vertices": int(len(unit_v)),
        "triangles": int(len(faces)),
        "timings": dict(track.timings),
        "seconds": time.perf_counter() - t_start,
    }
    return Mesh(
        vertices=(local + norm.center).astype(np.float32),
        faces=faces.astype(np.int32),
        normals=normals_v.astype(np.float32),
        center=norm.center.copy(),
        scale=norm.scale,
        local_vertices=local.astype(np.float32),
        stats=stats,
    )
