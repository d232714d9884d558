"""A fit you can keep: everything upstream of the grid, meshed at any resolution, re-solved for a new lambda.

:func:`nkf_model.fit` (in :mod:`nkf_model.pipeline.reconstruct`) runs the stages up to the solve
(subset, normalise, reduce, normals, augment, features, solve) and returns a :class:`Fit`:

* :meth:`Fit.mesh` evaluates the fitted function on a grid and meshes it (stages evaluate, mesh,
  clean, colors): a new ``resolution``, ``close``, ``min_piece`` or ``trim`` value costs only those;
* :meth:`Fit.with_lam` solves again for a new lambda from the kept constraints (no normals, features,
  patch layout, coarse fit or winding numbers again): by Cholesky, the same function as a fresh run to the bit,
  or, after :meth:`Fit.factorize` (one eigendecomposition of the Gram matrix, or of every patch's;
  :mod:`nkf_model.fit.refit`), by two matrix-vector products per matrix.

:func:`nkf_model.reconstruct` is ``fit`` followed by ``mesh`` with one progress bar.
"""

from __future__ import annotations

import copy
import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputWarning, InvalidParameterError, NoSurfaceError
from ..fit.balloon_check import BalloonCheck, CheckNodes, needs_data_free, prefer_data_free
from ..fit.partition_of_unity import PoURefit, fit_pou, patch_spacing
from ..fit.refit import GramEigen
from ..fit.solve import KernelFunction, SolveInfo, solve_dense, solve_falkon
from ..kernel.neural_spline import homogeneous, split_unit
from ..options import Options
from ..points.farthest_point import farthest_point_sample
from ..points.normalise import GRID_HALF, Normalisation
from ..points.outliers import OUTLIER_MIN_POINTS
from ..points.winding import BlendedField, winding_scale
from ..surface.colors import transfer_colors
from ..surface.evaluate import evaluate_sparse
from ..surface.mesh import Mesh, triangulate, vertex_normals
from ..surface.trim import clean_scan_mesh
from . import budget
from .blas_threads import blas_threads
from .device_fallback import run_with_cpu_fallback
from .progress import Tracker
from .query_cache import QueryCache, _Known

# Settings that only change the evaluation and meshing (Fit.mesh); every other one needs a new fit,
# except lam (Fit.with_lam). trim may change its value but not between None and a number: trim=None
# also turns on the winding-number far field, which is part of the fit.
MESH_SETTINGS = ("resolution", "close", "trim", "min_piece")
# BlendedField's calibration sample (nkf_model.points.winding.BlendedField: 4,000 uniform points).
BLEND_CALIBRATION = 4000
_KEEP = object()


@dataclass
class Prepared:
    """Everything upstream of the solve, made by :func:`nkf_model.pipeline.reconstruct.fit`.

    Attributes
    ----------
    options : Options
        The settings of the fit (``lam``, ``resolution`` etc. as first asked for).
    x : (n, 3) float64
        Points in the unit box (after subset, cleaning and reduction).
    normals : (n, 3) float64
        Unit outward normals of ``x`` (given or estimated).
    rgb : (n, 3) uint8 or None
        Colours of ``x``.
    norm : Normalisation
        Unit box <-> input frame (``x * scale + center``, input units).
    spacing : float
        Median nearest-neighbour distance of ``x`` (:func:`~nkf_model.normals.estimate.median_spacing`).
    a : (2n, D) float64, y : (2n,) float64
        Homogeneous constraints and their labels.
    phi : callable or None
        The learned features for query points (``method="nkf"``).
    coarse_a : (2n, 4) float64 or None
        Data-free constraints for the partition of unity's coarse fit (learned kernel only).
    kind : str
        ``"dense"``, ``"falkon"`` or ``"pou"``.
    engine : Engine
    patch_lam : callable
        ``patch_lam(lam) -> float or None``: the partition of unity's local regularisation.
    far_field : bool
        Whether the field follows the winding number away from the data (``trim is None``).
    info : dict
        Upstream entries of ``Mesh.stats`` (points, normals, reduction, features, ...).
    n_in : int
        Input rows.
    estimate_normals : bool
    """

    options: Options
    x: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray | None
    norm: Normalisation
    spacing: float
    a: np.ndarray
    y: np.ndarray
    phi: Any
    coarse_a: np.ndarray | None
    kind: str
    engine: Any
    patch_lam: Any
    far_field: bool
    info: dict
    n_in: int
    estimate_normals: bool
    timings: dict = field(default_factory=dict)


class _Shared:
    """What every :class:`Fit` made from one :func:`fit` call shares: the kept Gram matrix, the
    factorisation, the first partition of unity (whose layout later lambdas reuse)."""

    def __init__(self, keep: bool):
        self.keep = keep
        self.gram: np.ndarray | None = None
        self.eigen: GramEigen | None = None
        self.eigen_b: np.ndarray | None = None  # eigen.project(y): each later lambda is one product
        self.pou: PoURefit | None = None
        self.blend: BlendedField | None = None
        self.blend_q: np.ndarray | None = None
        self.blend_w: np.ndarray | None = None
        # K(calibration points, centres) (Q, 2N), made by factorize() for the dense solver: the far
        # field's scale for a new lambda is then one product instead of a kernel sum.
        self.blend_k: np.ndarray | None = None
        # The learned features at the grid nodes already evaluated (QueryCache), for every lambda.
        self.queries: QueryCache | None = QueryCache(QUERY_CACHE_BYTES) if keep and QUERY_CACHE_BYTES > 0 else None
        # The balloon check's lattice nodes (nkf_model.fit.balloon_check), the same for every lambda.
        self.check_nodes: CheckNodes | None = None
        self.lock = threading.Lock()


class Fit:
    """A fitted implicit function and everything needed to mesh it again or re-solve it.

    Made by :func:`nkf_model.fit`; do not construct it directly.

    Attributes
    ----------
    options : Options
        Its settings (``options.lam`` is this fit's lambda; ``options.resolution`` etc. are the
        defaults of :meth:`mesh`).
    lam : float
        Regularisation per constraint of this fit.
    solver : str
        ``"dense"``, ``"falkon"`` or ``"pou"``.
    points_used : int
        Points fitted (after subset, cleaning and reduction).
    resolution_dependent : bool
        True when the input was reduced (more than ``reduce_to`` points): the voxel size was chosen
        from ``options.resolution``, so :meth:`mesh` at another resolution is not what a fresh run at
        that resolution would give (it keeps this fit's points).
    timings : dict
        Seconds per stage of the fit.
    """

    def __init__(self, prep: Prepared, lam: float, shared: _Shared):
        self._prep = prep
        self.lam = float(lam)
        self._shared = shared
        self.options = prep.options if prep.options.lam == self.lam else prep.options.replace(lam=self.lam)
        self._sol = None
        self.timings: dict[str, float] = dict(prep.timings)

    # -- public ------------------------------------------------------------------------------
    @property
    def solver(self) -> str:
        return self._prep.kind

    @property
    def points_used(self) -> int:
        return int(len(self._prep.x))

    @property
    def resolution_dependent(self) -> bool:
        return self._prep.info.get("reduction") is not None

    @property
    def factorized(self) -> bool:
        """True once :meth:`factorize` has run: :meth:`with_lam` is then two matrix-vector products
        per matrix (the partition of unity: per patch; its coarse fit does not depend on lambda)."""
        if self._prep.kind == "dense":
            return self._shared.eigen is not None
        if self._prep.kind == "pou":
            return self._shared.pou is not None and self._shared.pou.factorized
        return False

    @property
    def can_factorize(self) -> bool:
        """Whether :meth:`factorize` applies (the dense and partition-of-unity solvers of a fit made
        with ``keep_factors=True``; Falkon always solves again)."""
        if not self._shared.keep or self._prep.kind == "falkon":
            return False
        return self._shared.gram is not None or self._shared.eigen is not None or self._shared.pou is not None

    @property
    def nbytes(self) -> int:
        """Bytes this fit holds (arrays of the constraints, the kept Gram matrix or factorisations,
        the partition of unity's patches), for a cache bounded by memory."""
        p, s = self._prep, self._shared
        total = p.x.nbytes + p.normals.nbytes + p.a.nbytes + p.y.nbytes
        total += 0 if p.coarse_a is None else p.coarse_a.nbytes
        total += 0 if s.gram is None else s.gram.nbytes
        total += 0 if s.eigen is None else s.eigen.nbytes
        total += 0 if s.blend_k is None else s.blend_k.nbytes
        total += 0 if s.queries is None else s.queries.nbytes
        if s.pou is not None:
            fn = s.pou.fn
            total += fn.cu.nbytes + fn.beta.nbytes + fn.start.nbytes + fn.count.nbytes + s.pou.nbytes
        sol = self._sol
        if sol is not None and p.kind != "pou":
            total += sol.fn.alpha.nbytes if hasattr(sol.fn, "alpha") else 0
        return int(total)

    @property
    def stats(self) -> dict:
        """The fit's part of ``Mesh.stats`` (points, normals, solver, lambda, timings)."""
        sol = self._sol
        pou = None if sol.pou_info is None else dict(sol.pou_info.__dict__)
        return {**self._prep.info, "lam": self.lam, "solver": sol.info.method, "centres": sol.info.centres,
                "balloon_check": None if sol.check is None else dict(sol.check.__dict__),
                "cg_iterations": sol.info.iterations, "pou": pou, "timings": dict(self.timings)}

    def mesh(self, resolution: int | None = None, *, close: bool | None = None, trim=_KEEP,
             min_piece: float | None = None, progress=None, cancel=None) -> Mesh:
        """Evaluate the fitted function on a grid and mesh it.

        Parameters
        ----------
        resolution : int, optional
            Marching-cubes cells per side of the grid (16 to 1024); default ``options.resolution``.
        close, min_piece : optional
            As in :func:`nkf_model.reconstruct`; default: the fit's.
        trim : float, optional
            Trim distance in point spacings. Only its value may change: switching between ``None``
            and a number changes the fit (the far field) and raises :class:`InvalidParameterError`.
        progress, cancel :
            As in :func:`nkf_model.reconstruct` (stages ``"evaluate"``, ``"mesh"``, ``"clean"``,
            ``"colors"``).

        Returns
        -------
        Mesh
            The same as :func:`nkf_model.reconstruct` with these settings and the fit's others
            (``stats["timings"]`` holds only the stages this call ran; ``stats["fit_timings"]`` the
            fit's).
        """
        changes = {}
        if resolution is not None:
            changes["resolution"] = resolution
        if close is not None:
            changes["close"] = close
        if min_piece is not None:
            changes["min_piece"] = min_piece
        if trim is not _KEEP:
            if (trim is None) != (self.options.trim is None):
                raise InvalidParameterError(
                    "trim between None (closed surface) and a distance changes the fit (the far field): "
                    "make a new fit with nkf_model.fit(..., trim=...)"
                )
            changes["trim"] = trim
        opts = self.options.replace(**changes) if changes else self.options
        t0 = time.perf_counter()
        with blas_threads(BLAS_THREADS):
            track = Tracker(progress, cancel, stages=mesh_stages(opts, self._prep.rgb is not None, len(self._prep.x)))
            out = self._mesh(track, opts, t0)
        out.stats["fit_timings"] = dict(self.timings)
        return out

    def with_lam(self, lam: float, *, progress=None, cancel=None) -> Fit:
        """The fit for another lambda, from the kept constraints (stage ``"solve"`` only).

        Without :meth:`factorize` it solves by Cholesky, as a fresh run does (the same function to
        the bit); after it, from the eigendecomposition (vertices within 1e-6 of the box of a fresh
        run's). Raises :class:`InvalidParameterError` for a bad ``lam``.
        """
        opts = self.options.replace(lam=lam)  # validates
        new = Fit(self._prep, opts.lam, self._shared)
        with blas_threads(BLAS_THREADS):
            track = Tracker(progress, cancel, stages=["solve"])
            new._solve(track)
            track.finish()
        new.timings = {**self.timings, "solve": track.timings.get("solve", 0.0)}
        return new

    def factorize(self, cancel=None) -> bool:
        """Make every later :meth:`with_lam` cheap: one eigendecomposition of the Gram matrix
        (dense), or of every patch's (partition of unity). Slow (dense: about 17
        times the Cholesky of the first solve), so run it in the background after the first result.
        ``cancel`` (a ``threading.Event``) is checked between patches only: one dense
        eigendecomposition cannot be interrupted. Returns :attr:`factorized`; thread-safe."""
        s = self._shared
        poll = Tracker(None, cancel, stages=["solve"]).cancel_poll
        with s.lock, blas_threads(BLAS_THREADS):
            if self._prep.kind == "dense" and s.eigen is None and s.gram is not None:
                poll()
                eigen = GramEigen.of(s.gram)
                s.gram = None
                s.eigen_b = eigen.project(self._prep.y)
                if self._prep.far_field and s.blend is not None:
                    s.blend_k = self._calibration_matrix(poll)
                s.eigen = eigen
            elif self._prep.kind == "pou" and s.pou is not None:
                s.pou.factorize(cancel_poll=poll)
        return self.factorized

    # -- stages ------------------------------------------------------------------------------
    def _solve(self, track: Tracker) -> None:
        p = self._prep
        self._sol = run_with_cpu_fallback(lambda eng: self._solve_on(eng, track), p.engine)

    def _solve_on(self, eng, track: Tracker):
        p, s, lam = self._prep, self._shared, self.lam
        track.begin("solve")
        pou_info = None
        x, seed = p.x, p.options.seed
        first = s.pou is None and s.blend is None and s.gram is None and s.eigen is None
        if p.kind == "dense":
            if s.eigen is not None and eng is p.engine:
                alpha = s.eigen.solve_projected(s.eigen_b, len(p.a) * lam)
                info = SolveInfo("dense", len(p.a), len(p.a))
            elif s.keep and first:
                alpha, info, s.gram = solve_dense(p.a, p.y, lam, eng, cancel_poll=track.cancel_poll, keep_gram=True)
            else:
                alpha, info = solve_dense(p.a, p.y, lam, eng, cancel_poll=track.cancel_poll)
            fn = KernelFunction(p.a, alpha, eng, features=p.phi)
            n_centres = len(p.a)
        elif p.kind == "falkon":
            n, max_centres = len(x), p.options.max_centres
            half = farthest_point_sample(x, min(n, max_centres // 2), seed=seed)
            idx = np.concatenate([half, half + n])
            alpha, info = solve_falkon(p.a, p.y, idx, lam, eng, tol=FALKON_TOL, cancel_poll=track.cancel_poll,
                                       step=track.step)
            fn = KernelFunction(p.a[idx], alpha, eng, features=p.phi)
            n_centres = len(idx)
        else:
            patch_lam = p.patch_lam(lam)
            if s.pou is not None and s.pou.fn.engine is eng:
                state = s.pou.refit(lam, patch_lam, cancel_poll=track.cancel_poll)
                fn, pou_info = state.fn, state.info
            else:
                fn, pou_info, state = fit_pou(x, p.a, p.y, lam, eng, seed=seed, cancel_poll=track.cancel_poll,
                                              step=track.step, features=p.phi, coarse_a=p.coarse_a,
                                              normals=p.normals if p.far_field else None, patch_lam=patch_lam,
                                              keep=True)
                if s.keep and s.pou is None:
                    s.pou = state
            info = SolveInfo("pou", len(p.a), pou_info.centres)
            n_centres = 16 * pou_info.median_points  # kernel sums per evaluated grid point, typically
        if p.kind != "pou" and p.far_field:
            fn = self._blend(fn, eng, track)
        check = None
        if p.kind == "dense" and p.phi is not None and p.options.balloon_check:
            fn, check = self._balloon_check(fn, eng, track)
        return _Solution(fn=fn, info=info, pou_info=pou_info, n_centres=n_centres, engine=eng, check=check)

    def _balloon_check(self, fn, eng, track: Tracker):
        """The learned function, or the data-free one fitted to the same points where the learned
        surface balloons beyond them (:mod:`nkf_model.fit.balloon_check`); and what was found."""
        p, s = self._prep, self._shared
        if s.check_nodes is None:
            s.check_nodes = CheckNodes.around(p.x, GRID_HALF)
        nodes = s.check_nodes
        if not len(nodes.points):
            return fn, BalloonCheck(0.0, None, "nkf")
        reach = nodes.reach_of(fn(nodes.points, cancel_poll=track.cancel_poll))
        if not needs_data_free(reach):
            return fn, BalloonCheck(reach, None, "nkf")
        n = len(p.x)
        y0 = np.concatenate([np.ones(n), -np.ones(n)])  # the labels before the learned kernel's weights
        alpha0, _ = solve_dense(p.coarse_a, y0, self.lam, eng, cancel_poll=track.cancel_poll)
        free = KernelFunction(p.coarse_a, alpha0, eng)
        if isinstance(fn, BlendedField):  # the same far field, its scale fitted to the data-free values
            q = self._calibration_q(track.cancel_poll)
            blended = copy.copy(fn)
            blended.fn = free
            blended.scale = winding_scale(s.blend_w, free(q, cancel_poll=track.cancel_poll)) if len(q) else 1.0
            free = blended
        free_reach = nodes.reach_of(free(nodes.points, cancel_poll=track.cancel_poll))
        if prefer_data_free(reach, free_reach):
            check = BalloonCheck(reach, free_reach, "splines")
            warnings.warn(check.message(), InputWarning, stacklevel=2)
            return free, check
        return fn, BalloonCheck(reach, free_reach, "nkf")

    def _blend(self, fn, eng, track: Tracker):
        """``BlendedField(fn, ...)`` as a fresh run makes it, reusing the KD-tree and winding
        numbers of the first one (they depend on the points only)."""
        p, s = self._prep, self._shared
        if s.blend is None or s.blend.fn.engine is not eng:
            h = patch_spacing(p.x, seed=p.options.seed)
            blend = BlendedField(fn, p.x, p.normals, FAR_START * h, FAR_END * h, GRID_HALF, seed=p.options.seed,
                                 cancel_poll=track.cancel_poll)
            if s.blend is None:
                s.blend = blend
            return blend
        q = self._calibration_q(track.cancel_poll)
        new = copy.copy(s.blend)
        new.fn = fn
        if not len(q):
            new.scale = 1.0
        elif s.blend_k is not None and s.eigen is not None and eng is p.engine:
            new.scale = winding_scale(s.blend_w, s.blend_k @ fn.alpha)  # factorised: the same sum, reordered
        else:
            new.scale = winding_scale(s.blend_w, fn(q, cancel_poll=track.cancel_poll))
        return new

    def _calibration_q(self, cancel_poll):
        """The far field's calibration points (those of ``BlendedField``) and their winding numbers."""
        p, s = self._prep, self._shared
        if s.blend_q is None:
            q = np.random.default_rng(p.options.seed).uniform(-GRID_HALF, GRID_HALF, (BLEND_CALIBRATION, 3))
            d, _ = s.blend.tree.query(q, distance_upper_bound=s.blend.start)
            s.blend_q = q[~np.isfinite(d)]
            s.blend_w = s.blend.far(s.blend_q, cancel_poll) if len(s.blend_q) else None
        return s.blend_q

    def _calibration_matrix(self, cancel_poll) -> np.ndarray | None:
        """``K(q, a)`` (Q, 2N) for the calibration points ``q`` and the dense solve's centres."""
        p = self._prep
        q = self._calibration_q(cancel_poll)
        if not len(q):
            return None
        phi = None if p.phi is None else p.phi(q)
        qu, qr = split_unit(homogeneous(q, phi))
        cu, cr = split_unit(p.a)
        return p.engine.kernel_matrix(qu, qr, cu, cr, cancel_poll=cancel_poll)

    def _node_values(self, fn, cancel_poll):
        """``node_f`` for :func:`evaluate_sparse` that keeps the learned features at the grid's nodes
        in the shared :class:`QueryCache` (a fit that keeps its factors, ``method="nkf"``), or None."""
        p, s = self._prep, self._shared
        if s.queries is None or p.phi is None:
            return None
        blend = fn if isinstance(fn, BlendedField) else None
        inner = fn.fn if blend is not None else fn
        if not (hasattr(inner, "query") and hasattr(inner, "at")) or getattr(inner, "features", None) is None:
            return None  # (the data-free function of a fit whose balloon check fell back has no features)
        cache = s.queries

        def node_f(pts, keys, level):
            vals = cache.values(inner, pts, keys, level, cancel_poll)
            if blend is None:
                return vals
            b = copy.copy(blend)  # the far field's blend, as BlendedField.__call__ makes it
            b.fn = _Known(vals)
            return b(pts, cancel_poll=cancel_poll)

        return node_f

    def _mesh(self, track: Tracker, opts: Options, t_start: float) -> Mesh:
        p = self._prep
        resolution, close, trim, min_piece = opts.resolution, opts.close, opts.trim, opts.min_piece

        def evaluate(eng):
            if eng is not self._sol.engine:  # the GPU ran out of memory: solve again on the CPU
                self._sol = self._solve_on(eng, track)
            track.begin("evaluate")
            fn = self._sol.fn
            return evaluate_sparse(lambda q: fn(q, cancel_poll=track.cancel_poll), resolution,
                                   cancel_poll=track.cancel_poll, step=track.step, seeds=p.x, close=close,
                                   node_f=self._node_values(fn, track.cancel_poll))

        field_ = run_with_cpu_fallback(evaluate, self._sol.engine)
        sol, norm, x = self._sol, p.norm, p.x
        track.begin("mesh")
        unit_v, faces = triangulate(field_, cancel_poll=track.cancel_poll, step=track.step)
        if len(faces) == 0:
            raise NoSurfaceError(
                "the fitted function has no zero crossing inside the grid; check that the normals "
                "point out of the surface, or lower lambda"
            )
        trim_info = None
        floaters = removes_floaters(opts, len(x))
        if trim is not None or min_piece > 0 or floaters:
            track.begin("clean")
            spacing = p.spacing
            min_area = FLOATER_AREA * spacing**2 if floaters else 0.0
            faces, kept, trim_info = clean_scan_mesh(
                unit_v, faces, x, spacing, trim=trim, min_piece=min_piece, floor=2.0 * GRID_HALF / resolution,
                min_area=min_area, max_share=FLOATER_SHARE,
            )
            unit_v = unit_v[kept]
            trim_info.threshold *= norm.scale  # report it in the input's units
            if len(faces) == 0:
                raise NoSurfaceError(
                    "trimming removed the whole surface; raise trim (in point spacings) or lower min_piece"
                )
        normals_v = vertex_normals(unit_v, faces)
        vertex_rgb = None
        if p.rgb is not None:
            track.begin("colors")
            vertex_rgb = transfer_colors(unit_v, x, p.rgb)
        local = unit_v * norm.scale
        track.finish()
        info = p.info
        plan = budget.plan_for(p.n_in, opts, estimate_normals=p.estimate_normals, colors=p.rgb is not None)
        stats = {
            "method": info["method"],
            "weights": info["weights"],
            "points_in": info["points_in"],
            "points_used": info["points_used"],
            "dropped": dict(info["dropped"]),
            "warnings": list(info["warnings"]) + ([sol.check.message()] if sol.check and sol.check.fell_back else []),
            "eps": info["eps"],
            "lam": self.lam,
            "solver": sol.info.method,
            "centres": sol.info.centres,
            "cg_iterations": sol.info.iterations,
            "kernel_evaluations_grid": int(field_.evaluations) * sol.n_centres,
            "grid_points_evaluated": int(field_.evaluations),
            "level_evaluations": field_.level_evaluations,
            "engine": f"{sol.engine.name}:{sol.engine.device}",
            "vertices": int(len(unit_v)),
            "triangles": int(len(faces)),
            "reduction": info["reduction"],
            "subset": info["subset"],
            "outliers": info.get("outliers"),
            "denoise": info.get("denoise"),
            "normals": info["normals"],
            "orientation": info["orientation"],
            "pou": None if sol.pou_info is None else dict(sol.pou_info.__dict__),
            "feature_scale": info["feature_scale"],
            "balloon_check": None if sol.check is None else dict(sol.check.__dict__),
            "far_field": p.far_field,
            "close": close,
            "trim": None if trim_info is None else dict(trim_info.__dict__),
            "estimate": plan.as_dict(),
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
            colors=vertex_rgb,
            stats=stats,
        )


@dataclass
class _Solution:
    fn: Any
    info: SolveInfo
    pou_info: Any
    n_centres: int
    engine: Any
    check: BalloonCheck | None = None


def removes_floaters(opts: Options, n_points: int) -> bool:
    """Whether :meth:`Fit.mesh` drops pieces smaller than :data:`FLOATER_AREA` point spacings squared:
    with ``outliers`` on, for inputs of :data:`~nkf_model.points.outliers.OUTLIER_MIN_POINTS` or more
    (and only pieces under :data:`FLOATER_SHARE` of the whole area)."""
    return bool(opts.outliers) and n_points >= OUTLIER_MIN_POINTS


def mesh_stages(opts: Options, colors: bool, n_points: int = 0) -> list[str]:
    """The stages :meth:`Fit.mesh` runs with ``opts`` on ``n_points`` fitted points."""
    stages = ["evaluate", "mesh"]
    stages += ["clean"] if (opts.trim is not None or opts.min_piece > 0 or removes_floaters(opts, n_points)) else []
    return stages + (["colors"] if colors else [])


# Bytes of learned features at grid nodes a kept fit holds for later lambdas (QueryCache): about
# 140 bytes a node, so the nodes of a mesh at 128 and a preview at 64 (about 160,000) take 22 MB.
QUERY_CACHE_BYTES = 96 * 2**20

# Solver constants shared with nkf_model.pipeline.reconstruct (which re-exports them).
# Relative residual at which Falkon's conjugate gradient stops: 1e-6 gave the same IoU and Chamfer as
# 1e-9 on 12 validation meshes at 10,000 points, in 17 iterations instead of 25.
FALKON_TOL = 1e-6
# Threads for dense linear algebra (OpenBLAS). One: on a busy 2-core machine (Blender's UI, another
# job) two OpenBLAS threads ran a 2,000 x 2,000 Cholesky 8x slower than one, and a 6,000 one 2x slower.
BLAS_THREADS = 1
# Global fits (dense, Falkon) follow the point cloud's winding number away from the data: the blend
# starts FAR_START and ends FAR_END patch spacings (pou.patch_spacing, about 0.1 of the box at 1,000
# points) from the nearest point (nkf_model.points.winding.BlendedField); see
# nkf_model.pipeline.reconstruct for how they were chosen.
FAR_START = 1.5
FAR_END = 3.0
# Dense inputs (outliers on, OUTLIER_MIN_POINTS points or more) lose every piece of surface smaller
# than this many point spacings squared: floaters that wrongly oriented patches of estimated normals
# leave beside the surface. On a simulated range scan of geocentral__cat_head (73,000 points) the
# 238 pieces beside the main one each had at most 0.03 % of the area (about 11 spacings squared).
FLOATER_AREA = 400.0
# ... and only if smaller than this share of the whole area, so that a sparser input (400 spacings
# squared is about 4 % of the area at 10,000 points) keeps its real small parts. The floaters measured
# were far smaller: at most 0.03 % each (cat_head, above), 0.2 % on a simulated rifle scan of 18,186 points.
FLOATER_SHARE = 0.005
