"""The whole pipeline: oriented points in, triangle mesh out.

normalise -> augment -> solve -> evaluate -> mesh, each stage in its own module. This module only
takes the settings (:class:`~nkf_model.options.Options`), wires the stages together and records what each one did.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputWarning, MissingNormalsError
from ..fit.augment import augment, default_eps
from ..kernel.engines import cpu_engine, select_engine
from ..kernel.neural_spline import homogeneous
from ..kernel.weights import load_weights
from ..normals.estimate import DEFAULT_K as NORMAL_K
from ..normals.estimate import check_orientation, check_viewpoints, estimate_normals, median_spacing
from ..options import SETTING, Options
from ..points.clean import clean_points
from ..points.denoise import DENOISE_MIN_POINTS, along_normal_moves, apply_moves, is_noisy
from ..points.noise import estimate_noise, noise_lam
from ..points.normalise import GRID_HALF, Normalisation
from ..points.outliers import OUTLIER_MIN_POINTS, sparse_outliers
from ..points.subset import random_subset
from ..points.voxel_reduce import voxel_for_count, voxel_reduce
from ..surface.colors import as_rgb8
from ..surface.mesh import Mesh
from . import budget
from .blas_threads import blas_threads
from .fitted import BLAS_THREADS, FALKON_TOL, FAR_END, FAR_START, Fit, Prepared, _Shared, mesh_stages
from .progress import Tracker

METHODS = SETTING["method"].values
DEFAULT_METHOD = SETTING["method"].default
DEFAULT_LAM = SETTING["lam"].default
DEFAULT_RESOLUTION = SETTING["resolution"].default
# Up to max_centres constraints (2 per point, so 3,000 points) the solve is exact; beyond it, a partition
# of unity of small exact solves (nkf_model.fit.partition_of_unity). On 12 validation meshes PoU matched
# the exact solve at 2,500 and 4,000 points (IoU within 0.005) in less time, and beat Falkon with this
# many Nystrom centres at 10,000 points (0.901 against 0.893 IoU, 3.5x faster); see docs/benchmarks.md.
# Falkon stays available as solver="falkon", with max_centres centres.
DEFAULT_CENTRES = SETTING["max_centres"].default
# Larger inputs are reduced by voxel-grid averaging to at most this many points (docs/scans.md).
DEFAULT_REDUCE_TO = SETTING["reduce_to"].default
NORMALS_MODES = SETTING["normals_mode"].values
SOLVERS = SETTING["solver"].values
# FALKON_TOL (Falkon's stopping residual) and BLAS_THREADS (one OpenBLAS thread) live with the solve in
# nkf_model.pipeline.fitted, and so do FAR_START and FAR_END:
# Global fits (dense, Falkon) follow the point cloud's winding number away from the data: the blend
# starts FAR_START and ends FAR_END patch spacings (pou.patch_spacing, about 0.1 of the box at 1,000
# points) from the nearest point (nkf_model.points.winding.BlendedField). Chosen on 14 training-split meshes
# with a first version that took the winding number's sign everywhere past the blend: half-surface
# inputs of 3,000 points, learned kernel, IoU 0.4242 without, 0.5084 / 0.5142 / 0.5112 with (1, 2) /
# (1.5, 3) / (2, 4); whole inputs of 1,000 and 3,000 points (splines) unchanged. The rule kept keeps
# the fit wherever its sign agrees with the winding number (docs/benchmarks.md has the 52-mesh runs).
__all__ = ["reconstruct", "fit", "Fit", "BLAS_THREADS", "FALKON_TOL", "FAR_START", "FAR_END"]
# The learned kernel's local fits (above 3,000 points: denser than it was trained on) take the same
# noise-aware regularisation, in proportion to its magnitude: lam = NKF_NOISE_LAM_FACTOR * r * (the
# data-free kernel's noise floor, nkf_model.points.noise.noise_lam; 6 s^2 when this was chosen),
# with r the ratio of the mean Gram diagonals of the learned and the data-free kernel (about 4,700 for
# the GPU-trained weights, whose learned constant feature is large). Chosen on 8 training-split meshes
# at 10,000 points with noise 0.005 (factors 0 / 0.01 / 0.03 / 0.1 / 1: IoU 0.8143 / 0.8552 / 0.8645 /
# 0.8640 / 0.8466, Chamfer-L1 0.00446 / 0.00406 / 0.00409 / 0.00430 / 0.00497; splines 0.8582 / 0.00411).
NKF_NOISE_LAM_FACTOR = 0.03
# Inputs denser than the learned kernel was trained on (more than NKF_TRAINED_POINTS points, the
# training config's n_max) keep its learned spatial features only in proportion to the estimated
# noise s (nkf_model.points.noise): scale min(1, s / NKF_FEATURE_NOISE). Clean dense input is trusted as it
# is: the features, extrapolated past the training sizes, cost accuracy there; noisy input keeps
# them. Measured on 8 training-split meshes at 10,000 points (IoU; splines 0.8911 clean, 0.8582 at
# noise 0.005): features scaled by 1 / 0.5 / 0: clean 0.8867 / 0.8902 / 0.8917, noise 0.005 0.8645 /
# 0.8634 / 0.8589. Noise 0.005 reads as s of about 0.0042, noise 0.0025 as about 0.0023.
NKF_TRAINED_POINTS = 3000
NKF_FEATURE_NOISE = 0.002
# Scales below this drop the features: the kernel on [x : c : 1] has the same Gram as with zero
# features, and 5 numbers per point instead of 13 are cheaper to evaluate.
NKF_FEATURE_OFF = 0.01


def reconstruct(
    points,
    normals=None,
    *,
    options: Options | None = None,
    progress: Callable[[float, str], None] | None = None,
    cancel=None,
    viewpoints=None,
    colors=None,
    **settings,
) -> Mesh:
    """Reconstruct a surface from points (oriented or not).

    The settings come as one :class:`~nkf_model.options.Options` (``options=``), as keywords
    (``method="splines", lam=1e-8``), or both (keywords override ``options``); each is checked
    against :data:`nkf_model.options.SETTINGS` before any work.

    Parameters
    ----------
    points : array_like, (N, 3)
        Positions in any units and any coordinate frame (float32 or float64).
    normals : array_like, (N, 3), optional
        Outward normals, one per point; any positive length. ``None``: estimated (see
        ``normals_mode``).
    method : {"splines", "nkf"}
        ``"splines"``: the data-free Neural Splines kernel, no weights needed.
        ``"nkf"``: the learned Neural Kernel Field kernel (needs weights; the default when the
        package ships them, see :func:`nkf_model.kernel.weights.has_default_weights`). Above
        :data:`NKF_TRAINED_POINTS` points its learned features are scaled by
        ``min(1, s / NKF_FEATURE_NOISE)`` for the estimated noise ``s``: clean dense input is fitted
        almost as it is (``stats["feature_scale"]``; ``None`` for ``"splines"``).
    lam : float
        Regularisation per constraint, >= 0 (the paper's lambda; the solve uses
        ``(G + 2N lam I) alpha = y``). Larger values smooth the surface; 1e-12 to 1e-8 fit the points.
        Above 3,000 points the local fits of the partition of unity use at least ``8e-4 (s / h)^2``
        for the position noise ``s`` estimated from the input and its median point spacing ``h``
        (:func:`nkf_model.points.noise.noise_lam`: the same for any units or density), reported as
        ``stats["pou"]["patch_lam"]`` (``method="nkf"``: scaled to the learned kernel's magnitude,
        see :data:`NKF_NOISE_LAM_FACTOR`).
    options : nkf_model.Options, optional
        All settings below at once; default :class:`~nkf_model.options.Options()`.
    resolution : int
        Cells per side of the marching-cubes grid, 16 to 1024. The grid spans the input's
        bounding box plus 5 % on each side.
    device : {"auto", "cpu", "cuda"}
        ``"auto"`` uses a CUDA GPU when PyTorch sees one, else the CPU; above 3,000 points (the
        partition of unity, whose fused CPU loop is faster than its GPU path) it uses the CPU.
        If the GPU runs out of memory, the work continues on the CPU with a
        :class:`~nkf_model.pipeline.device_fallback.DeviceWarning`.
    progress : callable, optional
        ``progress(fraction, stage)``: ``fraction`` in [0, 1], ``stage`` one of ``"normalise"``,
        ``"reduce"``, ``"normals"``, ``"augment"``, ``"features"`` (nkf only), ``"solve"``, ``"evaluate"``,
        ``"mesh"``, ``"clean"``, ``"colors"``, then ``"done"`` (stages that do not run are skipped).
    cancel : threading.Event, optional
        When set, the work stops within 0.5 s by raising :class:`~nkf_model.errors.Cancelled`.
    eps : float, optional
        Offset of the constraints along the normals, as a fraction of the bounding box's longest
        side. Default: 0.01 up to 3,000 points, then shrinking with the point spacing.
    max_centres : int
        Largest exact solve (in constraints, 2 per point); larger inputs use the partition of unity
        (``solver="auto"``), and ``solver="falkon"`` uses this many Nystrom centres.
    seed : int
        Seed for the ``max_points`` subset, the choice of Nystrom centres and of thinned patches.
    max_points : int, optional
        Use a random subset (seeded by ``seed``, kept in input order) of at most this many points
        (>= 10); ``stats["subset"]`` says when it applied. ``None`` (default) uses all.
    normals_mode : {"auto", "given", "estimate"}
        ``"given"``: ``normals`` are required. ``"estimate"``: ``normals`` are ignored and
        estimated (PCA over 16 neighbours, oriented by :mod:`nkf_model.normals.estimate`). ``"auto"``:
        given when passed, else estimated, with an :class:`InputWarning` that says so.
    orientation : {"outward", "up", "viewpoint"}, optional
        How estimated normals are oriented: away from the object (views from all around),
        upwards (views from above), or towards ``viewpoints``. Default: ``"viewpoint"`` when
        ``viewpoints`` are given, else ``"outward"``.
    viewpoints : (3,) or (K, 3) float, optional
        Scanner or camera positions, in the frame of ``points``.
    colors : (N, 3) or (N, 4) array, optional
        Per-point colours: integers 0-255 or floats 0-1 (alpha ignored). Carried onto the mesh as
        ``Mesh.colors`` (V, 3) uint8, by inverse-distance weighting of the 8 nearest points.
    trim : float, optional
        Cut away the surface farther than ``trim`` point spacings (median nearest-neighbour
        distance; never less than one grid cell) from every input point, for open scans (which
        also turns off the winding-number far field, made for closed surfaces). ``None``
        (default) keeps the closed surface. Scans: :data:`nkf_model.options.SCAN_TRIM`.
    min_piece : float
        Remove connected pieces with less than this fraction of the mesh's total area (0 keeps
        all). Scans: :data:`nkf_model.options.SCAN_MIN_PIECE`.
    close : bool
        Cap the surface where it runs into the grid's bounds (the input's bounding box plus 5 %), so
        that the mesh is watertight, for example for 3D printing. Off by default: on open or thin
        models the caps are surface that the object does not have.
    reduce_to : int, optional
        Inputs with more points than this are reduced to at most this many by voxel-grid
        averaging (see :mod:`nkf_model.points.voxel_reduce`); ``None`` never reduces.
    solver : {"auto", "dense", "falkon", "pou"}
        ``"auto"``: exact up to ``max_centres`` constraints, then the partition of unity of local
        exact solves (:mod:`nkf_model.fit.partition_of_unity`). ``"falkon"``: Nystrom centres with a preconditioned
        conjugate gradient.
    memory_budget : float, optional
        Bytes the run may use; if :func:`nkf_model.pipeline.budget.estimate` predicts more, the call
        raises :class:`~nkf_model.errors.MemoryBudgetError` before any large allocation. Default:
        :func:`nkf_model.pipeline.budget.default_memory_budget`.
    weights : str or os.PathLike, optional
        Weights file (safetensors) for ``method="nkf"``; default: the weights shipped in the
        package. Ignored by ``method="splines"``.

    Returns
    -------
    Mesh
        ``vertices`` (V, 3) float32 in the input's frame, ``faces`` (F, 3) int32 facing out,
        ``normals`` (V, 3) float32, ``colors`` (V, 3) uint8 or ``None``, and ``stats`` (counts,
        warnings, time per stage in seconds, what was reduced, estimated and trimmed).

    Raises
    ------
    nkf_model.errors.NKFInputError
        A ``ValueError`` subclass for every bad input or setting (see :mod:`nkf_model.errors`);
        :class:`~nkf_model.errors.WeightsError` for a missing, corrupt or mismatched weights file.
    nkf_model.errors.Cancelled
        ``cancel`` was set.
    """
    opts = Options.build(options, **settings)
    if opts.normals_mode == "given" and normals is None:
        raise MissingNormalsError(
            "normals are required with normals_mode='given': pass one unit normal per point, "
            "or use normals_mode='auto' to estimate them"
        )
    model = load_weights(opts.weights) if opts.method == "nkf" else None
    with blas_threads(BLAS_THREADS):
        return _reconstruct(points, normals, opts, model=model, progress=progress, cancel=cancel,
                            viewpoints=viewpoints, colors=colors)


def fit(
    points,
    normals=None,
    *,
    options: Options | None = None,
    progress: Callable[[float, str], None] | None = None,
    cancel=None,
    viewpoints=None,
    colors=None,
    keep_factors: bool = True,
    **settings,
) -> Fit:
    """The stages of :func:`reconstruct` up to the solve; mesh the result with :meth:`Fit.mesh`.

    Takes exactly the arguments of :func:`reconstruct` (``options``, keywords, ``progress`` with
    the stages up to ``"solve"``, ``cancel``, ``viewpoints``, ``colors``). ``fit(...).mesh()`` gives
    the same mesh as ``reconstruct(...)``; :meth:`Fit.mesh` meshes it again at another resolution
    (evaluate and mesh only) and :meth:`Fit.with_lam` re-solves it for another lambda (no normals,
    features or patch layout again; after :meth:`Fit.factorize`, from a stored eigendecomposition).

    ``keep_factors``: keep the Gram matrix of a dense solve (8 (2N)^2 bytes: 288 MB at 3,000 points)
    for :meth:`Fit.factorize`, and the partition of unity's patch layout. ``False`` keeps only what
    :meth:`Fit.mesh` needs; :meth:`Fit.with_lam` then solves from the constraints.

    Returns
    -------
    Fit
    """
    opts = Options.build(options, **settings)
    if opts.normals_mode == "given" and normals is None:
        raise MissingNormalsError(
            "normals are required with normals_mode='given': pass one unit normal per point, "
            "or use normals_mode='auto' to estimate them"
        )
    model = load_weights(opts.weights) if opts.method == "nkf" else None
    with blas_threads(BLAS_THREADS):
        return _reconstruct(points, normals, opts, model=model, progress=progress, cancel=cancel,
                            viewpoints=viewpoints, colors=colors, mesh=False, keep=keep_factors)


def _reconstruct(points, normals, opts: Options, *, model, progress, cancel, viewpoints, colors,
                 mesh: bool = True, keep: bool = False):
    method, lam, resolution, seed = opts.method, opts.lam, opts.resolution, opts.seed
    normals_mode, trim = opts.normals_mode, opts.trim
    reduce_to, solver, max_centres = opts.reduce_to, opts.solver, opts.max_centres
    vp = check_viewpoints(viewpoints)
    orient = check_orientation(opts.orientation, vp)
    estimate_n = normals_mode == "estimate" or (normals_mode == "auto" and normals is None)
    n_in = _row_count(points)
    subset = opts.max_points is not None and n_in > opts.max_points
    plan = budget.plan_for(n_in, opts, estimate_normals=estimate_n, colors=colors is not None)
    budget.enforce(plan, opts.memory_budget)

    t_start = time.perf_counter()
    engine = select_engine(opts.device)
    stages = (["subsample"] if subset else []) + ["normalise"] + (["reduce"] if plan.reduced else [])
    stages += ["normals"] if estimate_n else []
    stages += ["augment"] + (["features"] if model is not None else []) + ["solve"]
    stages += mesh_stages(opts, colors is not None, n_in) if mesh else []
    track = Tracker(progress, cancel, stages=stages)
    subset_info = None
    if subset:
        track.begin("subsample")
        points, normals, colors = random_subset(points, None if estimate_n else normals, colors,
                                                opts.max_points, seed)
        subset_info = {"from": n_in, "to": len(points)}
    track.begin("normalise")
    clean = clean_points(points, None if estimate_n else normals, require_normals=not estimate_n,
                         allow_flat=trim is not None)
    for line in clean.warnings():
        warnings.warn(line, InputWarning, stacklevel=3)
    rgb = None if colors is None else as_rgb8(colors, len(points))[clean.index]
    norm = Normalisation.fit(clean.points)
    x = norm.to_unit(clean.points)
    nrm = clean.normals
    outlier_info = None
    if opts.outliers and len(x) >= OUTLIER_MIN_POINTS:
        bad = sparse_outliers(x)
        if bad.any():
            keep_pts = ~bad
            x = x[keep_pts]
            nrm = None if nrm is None else nrm[keep_pts]
            rgb = None if rgb is None else rgb[keep_pts]
        outlier_info = {"removed": int(bad.sum()), "of": int(len(bad))}
    reduction = None
    if plan.reduced and len(x) > reduce_to:
        track.begin("reduce")
        cell = 2.0 * GRID_HALF / resolution
        voxel = voxel_for_count(x, reduce_to, start=0.25 * cell)
        red = voxel_reduce(x, nrm, rgb, voxel)
        x, nrm, rgb = red.points, red.normals, red.colors
        reduction = {"voxel": voxel * norm.scale, "from": len(clean.points), "to": len(x)}
    n = len(x)

    normal_info = None
    if estimate_n:
        track.begin("normals")
        if normals_mode == "auto":
            warnings.warn(
                f"no normals given: estimated them from {NORMAL_K} neighbours, oriented '{orient}'",
                InputWarning, stacklevel=3,
            )
        unit_vp = None if vp is None else norm.to_unit(vp)
        nrm, normal_info = estimate_normals(x, orientation=orient, viewpoints=unit_vp, cancel_poll=track.cancel_poll)

    track.begin("augment")
    # One tree and one spacing per fit: the noise estimate and floor, and every mesh's clean step.
    tree = cKDTree(x)
    spacing = median_spacing(x, tree)
    # Misregistered scans (their normal estimation reads overlapping layers of one surface): each point
    # moves along its normal to the middle of its same-sheet neighbours before the fit, so that the
    # layers meet (nkf_model.points.denoise). Dense noisy samples of one surface are left alone: on
    # them the move cost bullet3__029 F 0.993 -> 0.971 and split kenney__key (docs/real_scans.md). The
    # noise estimated before the move sets the noise floor and the feature scale below: estimated
    # again after it, it reads lower and the fit follows what is left.
    kind = budget.choose_solver(n, max_centres, solver)
    layered = normal_info is not None and bool(normal_info.misregistered)
    # The noise is read where something uses it: the denoise step, the learned features beyond the
    # sizes they were trained on, the partition of unity's noise floor.
    needs_noise = layered or kind == "pou" or (model is not None and n > NKF_TRAINED_POINTS)
    sigma = estimate_noise(x, nrm, tree=tree) if needs_noise else None
    denoise_info = None
    if layered and n >= DENOISE_MIN_POINTS and sigma > 0:
        moves = along_normal_moves(x, nrm, spacing, tree=tree, cancel_poll=track.cancel_poll)
        if is_noisy(moves, spacing):
            moved = apply_moves(x, nrm, moves, sigma)
            denoise_info = {"noise": sigma * norm.scale, "median_move": float(np.median(np.abs(moves))) / spacing,
                            "moved": float(np.median(np.linalg.norm(moved - x, axis=1))) * norm.scale}
            x = moved
            tree = cKDTree(x)
    eps_used = float(opts.eps) if opts.eps is not None else default_eps(n)
    xa, y = augment(x, nrm, eps_used)
    phi = None
    feature_scale = None
    if model is None:
        a = homogeneous(xa)
    else:
        track.begin("features")
        feature_scale = 1.0
        if n > NKF_TRAINED_POINTS:
            feature_scale = min(1.0, sigma / NKF_FEATURE_NOISE)
            if feature_scale < NKF_FEATURE_OFF:
                feature_scale = 0.0
        prep = model.prepare(xa, y, feature_scale=feature_scale)
        a, y, phi = prep.a, prep.y, prep.phi
    if opts.device == "auto" and kind == "pou" and engine.device != "cpu":
        # The partition of unity's sum is one fused CPU loop; through PyTorch on a GPU it runs patch
        # by patch and was 5x slower (20,000 points: 9.2 s on an H100 against 1.8 s on its CPU).
        engine = cpu_engine()
    # Noisy input: the local solves of the partition of unity regularise in proportion to the
    # estimated noise variance over the squared point spacing (nkf_model.points.noise) instead of
    # interpolating the noise; clean input keeps ``lam``. The learned kernel's, scaled to its
    # magnitude (NKF_NOISE_LAM_FACTOR).
    # A function of lambda, so that a kept fit (nkf_model.pipeline.fitted.Fit.with_lam) re-solves as a
    # fresh run would.
    ratio = None
    if kind == "pou":
        if model is not None:
            ratio = float(np.mean(np.einsum("ij,ij->i", a, a)) / np.mean(np.einsum("ij,ij->i", xa, xa) + 1.0))

    def patch_lam(value: float):
        if kind != "pou":
            return None
        if model is None:
            return noise_lam(sigma, spacing, value)
        return max(float(value), NKF_NOISE_LAM_FACTOR * ratio * noise_lam(sigma, spacing, 0.0))

    # Away from the data the field follows the input's winding number, which assumes a closed
    # surface. Open scans (``trim`` set) keep the fit's own sign there: on the scene benchmark the far
    # field left extra surface near the data (splines, 3 rooms of 100,000 points: Chamfer-L1 0.00251
    # with it, 0.00234 without; F-score at 0.5 % 0.9332 against 0.9594).
    far_field = trim is None

    info = {
        "method": method,
        "weights": str(model.meta.get("path", "")) if model is not None else None,
        "points_in": n_in,
        "points_used": n,
        "dropped": dict(clean.dropped),
        "warnings": clean.warnings(),
        "eps": eps_used,
        "reduction": reduction,
        "outliers": outlier_info,
        "denoise": denoise_info,
        "subset": subset_info,
        "normals": "estimated" if estimate_n else "given",
        "orientation": None if normal_info is None else {
            "rule": normal_info.orientation, "pieces": normal_info.pieces, "decided_by_views": normal_info.seeded,
            "learned_check": normal_info.learned_check, "flipped_by_learned_check": normal_info.learned_flips,
            "flipped_by_tangent_planes": normal_info.consistent_flips,
            "misregistered": normal_info.misregistered,
        },
        "feature_scale": feature_scale,
    }
    prep = Prepared(
        options=opts, x=x, normals=nrm, rgb=rgb, norm=norm, spacing=spacing, a=a, y=y, phi=phi,
        coarse_a=None if phi is None else homogeneous(xa), kind=kind, engine=engine, patch_lam=patch_lam,
        far_field=far_field, info=info, n_in=n_in, estimate_normals=estimate_n,
    )
    fitted = Fit(prep, float(lam), _Shared(keep))
    fitted._solve(track)
    prep.timings = dict(track.timings)
    fitted.timings = dict(track.timings)
    if not mesh:
        track.finish()
        fitted.timings = dict(track.timings)
        return fitted
    return fitted._mesh(track, opts, t_start)


def _row_count(points) -> int:
    """Rows of ``points`` without copying it (0 when it has no length)."""
    shape = getattr(points, "shape", None)
    if shape is not None and len(shape) >= 1:
        return int(shape[0])
    try:
        return len(points)
    except TypeError:
        return 0
