"""Stage 4 for large inputs: a partition of unity of small exact solves.

One global solve cannot hold the detail of 100,000 points or more: Nystrom/Falkon with a few
thousand centres smooths it away, and more centres cost ``M^3``. Instead, space is cut into a
regular grid of patches (spacing ``h``, chosen so that a patch holds about
:data:`POINTS_PER_PATCH` points). The patch at grid node ``c`` owns the points within ``h`` of it
along every axis (each point belongs to the 8 patches at the corners of its cell) and fits them
exactly, ``(G_p + n_p lam I) alpha_p = y_p``, with the same kernel as the global solve. The blended
function is::

    f(x) = sum_p w_p(x) g_p(x),   w_p(x) = prod_axis s(1 - |x - c_p| / h),   s(u) = 3u^2 - 2u^3

whose weights sum to one everywhere (:mod:`nkf_model.fit._pou_kernels`). Patches with fewer than
:data:`MIN_PATCH_POINTS` points use a coarse global fit ``f0`` instead (an exact solve on
:data:`COARSE_POINTS` points picked by farthest-point sampling with lambda :data:`COARSE_LAM`,
sampled once on a 48^3 grid and interpolated), which gives the field far from the data; given the
normals, its sign there is the point cloud's winding number's (:mod:`nkf_model.points.winding`).
Cost: the local solves are O(N P^2) in total for P points per patch, and every evaluation sums over
the centres of 8 patches (about 16 P kernel evaluations), whatever N is.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.linalg import lapack
from scipy.spatial import cKDTree

from ..kernel._numba_kernels import ACUTE_MIN_LAST
from ..kernel.engines import Engine, NumbaEngine
from ..kernel.neural_spline import homogeneous, split_unit
from ..points.farthest_point import farthest_point_sample
from ..points.normalise import GRID_HALF
from ..points.winding import FarField, follow_winding, winding_scale
from . import _pou_kernels as pk
from .solve import KernelFunction, solve_dense

POINTS_PER_PATCH = 50  # target median of points per patch
MAX_PATCH_POINTS = 4 * POINTS_PER_PATCH  # larger patches are randomly thinned to this
MIN_PATCH_POINTS = 8  # patches with fewer points use the coarse global fit
COARSE_POINTS = 1000  # points of the coarse global fit
# Regularisation per constraint of the coarse fit, whatever the fit's lambda: the default lambda
# (options.SETTING["lam"], so a run with it is unchanged). The coarse fit only stands in far from the
# data, where no patch has points, and (with normals) gives way there to the winding number's sign;
# lambda's job, how closely the surface follows the points, is the patches' (``patch_lam``, which
# noisy input already raises above lambda). Kept fixed, a new lambda does not touch the coarse fit
# or its 48^3 grid (117,649 nodes x 2,000 centres, 2 s of a 3 s solve at 10,000 points): a kept fit
# (PoURefit.refit) re-solves only the patches.
COARSE_LAM = 1e-10
COARSE_GRID = 48  # cells per side of the grid the coarse fit is sampled on
# Nodes of that grid nearer the data than this many of its cells keep the coarse fit's sign: there
# the winding number is at its 1/2 crossing, and noisy dense input pushes it either way
# (quaternius__Donut, 1,000,000 points, noise 0.002, every point kept: F-score 0.946 with the
# override there, 1.000 without; docs/scans.md).
FAR_NEAR_CELLS = 0.5

CancelPoll = Optional[Callable[[], None]]
Step = Optional[Callable[[float], None]]


@dataclass
class PoUInfo:
    """What :func:`fit_pou` did.

    Attributes
    ----------
    h : float
        Patch spacing in unit-box units.
    patches : int
        Patches with a local fit.
    median_points, max_points : int
        Points per fitted patch (after thinning).
    thinned : int
        Patches that had more than :data:`MAX_PATCH_POINTS` points and were thinned.
    centres : int
        Kernel centres over all patches (each constraint counts once per patch it belongs to).
    coarse_points : int
        Points of the coarse global fit.
    patch_lam : float
        Regularisation per constraint of the local solves.
    """

    h: float
    patches: int
    median_points: int
    max_points: int
    thinned: int
    centres: int
    coarse_points: int
    patch_lam: float = 0.0


def patch_spacing(x: np.ndarray, target: int = POINTS_PER_PATCH, sample: int = 50_000, seed: int = 0) -> float:
    """Patch spacing ``h`` (unit-box units) for which the median patch holds about ``target`` points.

    Counts are taken on a fixed random subsample of at most ``sample`` points and scaled up.
    """
    n = len(x)
    rng = np.random.default_rng(seed)
    sub = x if n <= sample else x[rng.choice(n, sample, replace=False)]
    scale = n / len(sub)
    # Start from the spacing at which a surface of area ~2 (the unit box's typical content) holds
    # the target; then correct by the measured counts (patch counts grow as h^2 on a surface).
    h = float(np.sqrt(2.0 * target / n)) / 2.0
    for _ in range(4):
        dims = int(math.ceil(2 * GRID_HALF / h)) + 2
        idx, _ = pk.corner_weights(np.ascontiguousarray(sub), -GRID_HALF, h, dims)
        _, counts = np.unique(idx, return_counts=True)
        med = float(np.median(counts)) * scale
        ratio = target / max(med, 1e-9)
        h_new = h * float(np.clip(np.sqrt(ratio), 0.5, 2.0))
        if abs(h_new / h - 1.0) < 0.05:
            h = h_new
            break
        h = h_new
    return float(min(max(h, 1e-4), GRID_HALF))


class PoUFunction:
    """The blended function ``f(x) = sum_p w_p(x) g_p(x)`` (see the module docstring).

    Call it with unit-box points (N, 3) float64; it returns (N,) float64.
    """

    def __init__(self, lo, h, dims, start, count, cu, beta, coarse: KernelFunction, engine: Engine, features=None,
                 far: FarField | None = None, cancel_poll: CancelPoll = None, far_nodes=None, f0_grid=None):
        self.lo, self.h, self.dims = float(lo), float(h), int(dims)
        self.start, self.count = start, count
        self.cu = np.ascontiguousarray(cu)  # (D, C)
        self.beta = beta
        self.coarse = coarse
        self.engine = engine
        self.features = features
        # The coarse fit is smooth and only stands in far from the data: sample it once on a grid
        # and interpolate, instead of summing its centres at every query. ``far`` (winding numbers
        # of the input, nkf_model.points.winding) overrides its sign where the two disagree, except at
        # nodes within FAR_NEAR_CELLS cells of the input points. ``far_nodes``: the winding numbers
        # and the near-data mask at the nodes from an earlier function of the same points (a refit).
        # ``f0_grid``: the sampled coarse fit of an earlier function with the same coarse fit (a
        # refit: the coarse fit's lambda is COARSE_LAM whatever the fit's), used as it is.
        self.f0_lo, self.f0_step = -GRID_HALF, 2 * GRID_HALF / COARSE_GRID
        self.far_nodes = far_nodes
        if f0_grid is not None:
            self.f0_grid = f0_grid
            return
        g = np.linspace(-GRID_HALF, GRID_HALF, COARSE_GRID + 1)
        nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        f0 = coarse(nodes, cancel_poll=cancel_poll)
        if far is not None and far_nodes is None:
            w = far(nodes, cancel_poll)
            d, _ = cKDTree(far.points).query(nodes, distance_upper_bound=FAR_NEAR_CELLS * self.f0_step, workers=-1)
            self.far_nodes = (w, np.isfinite(d))
        if self.far_nodes is not None:
            w, near = self.far_nodes
            f0 = np.where(near, f0, follow_winding(f0, w, winding_scale(w, f0)))
        self.f0_grid = np.ascontiguousarray(f0.reshape(COARSE_GRID + 1, COARSE_GRID + 1, COARSE_GRID + 1))

    def __call__(self, x: np.ndarray, cancel_poll: CancelPoll = None) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        return self.at(x, *self.query(x), cancel_poll=cancel_poll)

    def query(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The query side of ``x`` (N, 3), which does not depend on lambda: unit homogeneous vectors
        (N, D) and norms (N,), row by row (as :meth:`nkf_model.fit.solve.KernelFunction.query`)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        phi = None if self.features is None else self.features(x)
        return split_unit(homogeneous(x, phi))

    def at(self, x: np.ndarray, qu: np.ndarray, qr: np.ndarray, cancel_poll: CancelPoll = None) -> np.ndarray:
        """Values at ``x`` (N, 3) float64 from its :meth:`query`: the same as ``self(x)``."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if cancel_poll is not None:
            cancel_poll()
        if isinstance(self.engine, NumbaEngine):
            lim = ACUTE_MIN_LAST
            acute = qu.shape[1] == 4 and bool(qu[:, 3].min() >= lim) and bool(self.cu[3].min() >= lim)
            with NumbaEngine._lock:
                return pk.pou_sum(x, qu, qr, self.lo, self.h, self.dims, self.start, self.count, self.cu,
                                  self.beta, self.f0_grid, self.f0_lo, self.f0_step, acute)
        idx, w = pk.corner_weights(x, self.lo, self.h, self.dims)
        f0 = pk.interpolate(self.f0_grid, self.f0_lo, self.f0_step, x)
        return self._generic(qu, qr, idx, w, f0, cancel_poll)

    def _generic(self, qu, qr, idx, w, f0, cancel_poll: CancelPoll):
        """Same sum through ``engine.kernel_sum``, one patch at a time (for the PyTorch engines)."""
        n = len(qu)
        out = np.zeros(n)
        p = idx.reshape(-1)
        q = np.repeat(np.arange(n), 8)
        ww = w.reshape(-1)
        fitted = self.count[p] > 0
        np.add.at(out, q[~fitted], ww[~fitted] * f0[q[~fitted]])
        p, q, ww = p[fitted & (ww > 0)], q[fitted & (ww > 0)], ww[fitted & (ww > 0)]
        order = np.argsort(p, kind="stable")
        p, q, ww = p[order], q[order], ww[order]
        bounds = np.flatnonzero(np.r_[True, p[1:] != p[:-1], True])
        for s, e in zip(bounds[:-1], bounds[1:]):
            if cancel_poll is not None:
                cancel_poll()
            patch = p[s]
            cs = slice(self.start[patch], self.start[patch] + self.count[patch])
            cu = np.ascontiguousarray(self.cu[:, cs].T)
            vals = self.engine.kernel_sum(qu[q[s:e]], qr[q[s:e]], cu, np.ones(len(cu)), self.beta[cs])
            np.add.at(out, q[s:e], ww[s:e] * vals)
        return out


def _solve_patch(a_rows: np.ndarray, y: np.ndarray, lam: float):
    """Exact solve of one patch: returns unit centres (m, D) and ``alpha * |c|`` (m,)."""
    u, r = split_unit(a_rows)
    m = len(u)
    G = pk.gram_general(u, r, m * lam)
    jitter = 0.0
    while True:
        L, info = lapack.dpotrf(G, lower=1, clean=0, overwrite_a=0)
        if info == 0:
            break
        step = 1e-13 * float(np.trace(G)) / m if jitter == 0.0 else 9.0 * jitter
        G[np.diag_indices(m)] += step
        jitter += step
    alpha, _ = lapack.dpotrs(L, y, lower=1)
    return u, alpha * r


def fit_pou(
    x: np.ndarray,
    a: np.ndarray,
    y: np.ndarray,
    lam: float,
    engine: Engine,
    *,
    features=None,
    coarse_a: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    patch_lam: float | None = None,
    coarse_lam: float = COARSE_LAM,
    points_per_patch: int = POINTS_PER_PATCH,
    coarse_points: int = COARSE_POINTS,
    seed: int = 0,
    cancel_poll: CancelPoll = None,
    step: Step = None,
    keep: bool = False,
):
    """Fit the partition-of-unity function to labelled constraints.

    Parameters
    ----------
    x : (N, 3) float64
        Unit-box input points (they decide which patches a constraint belongs to).
    a : (2N, D) float64
        Homogeneous constraints: rows ``i`` and ``N + i`` are the outer and inner offsets of
        point ``i`` (as :func:`nkf_model.fit.augment.augment` makes them).
    y : (2N,) float64
        Labels (+1 outer, -1 inner).
    lam : float
        Regularisation per constraint, as in the global solve: the local solves' default.
    patch_lam : float, optional
        Regularisation per constraint of the local solves (default ``lam``); larger values smooth
        noisy input (see :func:`nkf_model.points.noise.noise_lam`).
    coarse_lam : float
        Regularisation per constraint of the coarse fit (default :data:`COARSE_LAM`).
    engine : Engine
        Evaluates the blended function (the local solves always run on the CPU).
    features : callable, optional
        ``phi`` for query points, as in :class:`nkf_model.fit.solve.KernelFunction`.
    coarse_a : (2N, 4) float64, optional
        Constraints for the coarse fit instead of ``a``: the learned kernel passes the data-free
        ``[x : 1]`` rows here. The coarse fit only decides the sign far from the data, where the
        learned features (trained on inputs of up to 3,000 points) have nothing to condition on;
        with them, it put spurious inside regions far from 10,000-point inputs.
    normals : (N, 3) float64, optional
        Unit outward normals of ``x``. When given, far from the data (patches without a local fit)
        the coarse fit gives way to the point cloud's winding number (:mod:`nkf_model.points.winding`)
        wherever their signs disagree, at the coarse fit's scale: a global spline through
        :data:`COARSE_POINTS` points guesses the sign away from thin parts (both sheets cancel) and
        put spurious inside regions there (IoU 0.73 instead of 0.96 on a manta ray of 10,000 points).
        Within :data:`FAR_NEAR_CELLS` cells of the coarse grid from the data the coarse fit is kept.
    keep : bool
        Also return a :class:`PoURefit` that fits a new lambda without redoing the patches' layout,
        the winding numbers or (after :meth:`PoURefit.factorize`) any factorisation.

    Returns
    -------
    PoUFunction, PoUInfo (and PoURefit with ``keep``)
    """
    n = len(x)
    local_lam = lam if patch_lam is None else float(patch_lam)
    rng = np.random.default_rng(seed)
    h = patch_spacing(x, points_per_patch, seed=seed)
    lo = -GRID_HALF - 1e-9
    dims = int(math.ceil(2 * GRID_HALF / h)) + 2
    max_pts = 4 * points_per_patch

    # Coarse global fit for patches without data.
    n_coarse = min(coarse_points, n)
    sub = farthest_point_sample(x, n_coarse, seed=seed)
    # The coarse fit reuses the given constraints of the chosen points (same eps, same features).
    rows_c = rows = np.concatenate([sub, sub + n])
    ac, yc = (a if coarse_a is None else coarse_a)[rows], y[rows]
    alpha_c, _ = solve_dense(ac, yc, float(coarse_lam), engine, cancel_poll=cancel_poll)
    coarse = KernelFunction(ac, alpha_c, engine, features=features if coarse_a is None else None)
    if step is not None:
        step(0.05)

    # Patch membership: each point belongs to the 8 patches at the corners of its cell.
    idx, _ = pk.corner_weights(np.ascontiguousarray(x), lo, h, dims)
    key = idx.reshape(-1)
    member = np.repeat(np.arange(n), 8)
    order = np.argsort(key, kind="stable")
    key, member = key[order], member[order]
    bounds = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    jobs = []
    thinned = 0
    for s, e in zip(bounds[:-1], bounds[1:]):
        if e - s < MIN_PATCH_POINTS:
            continue
        ids = member[s:e]
        if len(ids) > max_pts:
            ids = np.sort(rng.choice(ids, max_pts, replace=False))
            thinned += 1
        jobs.append((int(key[s]), ids))
    del key, member, order, idx

    def work(job):
        patch, ids = job
        rows = np.concatenate([ids, ids + n])
        return patch, _solve_patch(a[rows], y[rows], local_lam)

    results = []
    workers = max(1, min(os.cpu_count() or 1, _numba_threads()))
    with _single_thread_blas(), ThreadPoolExecutor(workers) as ex:
        try:
            batch = max(64, len(jobs) // 50)
            for b in range(0, len(jobs), batch):
                if cancel_poll is not None:
                    cancel_poll()
                results.extend(ex.map(work, jobs[b : b + batch]))
                if step is not None:
                    step(0.05 + 0.95 * min(1.0, (b + batch) / max(1, len(jobs))))
        except BaseException:
            ex.shutdown(wait=True, cancel_futures=True)
            raise

    count = np.zeros(dims**3, dtype=np.int64)
    start = np.zeros(dims**3, dtype=np.int64)
    sizes = np.array([len(u) for _, (u, _) in results], dtype=np.int64)
    offs = np.r_[0, np.cumsum(sizes)]
    d = a.shape[1]
    cu = np.empty((d, int(offs[-1])))
    beta = np.empty(int(offs[-1]))
    for (patch, (u, b)), o, m in zip(results, offs[:-1], sizes):
        start[patch] = o
        count[patch] = m
        cu[:, o : o + m] = u.T
        beta[o : o + m] = b
    pts = sizes // 2
    info = PoUInfo(
        h=h,
        patches=len(results),
        median_points=int(np.median(pts)) if len(pts) else 0,
        max_points=int(pts.max()) if len(pts) else 0,
        thinned=thinned,
        centres=int(offs[-1]),
        coarse_points=n_coarse,
        patch_lam=local_lam,
    )
    far = None if normals is None else FarField(x, normals, seed=seed, cancel_poll=cancel_poll)
    fn = PoUFunction(lo, h, dims, start, count, cu, beta, coarse, engine, features, far=far, cancel_poll=cancel_poll)
    if keep:
        state = PoURefit(fn=fn, info=info, a=a, y=y, coarse_rows=rows_c, coarse_a=coarse_a,
                         patches=[(p, np.concatenate([ids, ids + n])) for p, ids in jobs], lam=float(lam))
        return fn, info, state
    return fn, info


def _numba_threads() -> int:
    try:
        import numba

        return int(numba.get_num_threads())
    except ImportError:  # pragma: no cover - numba is a declared dependency
        return 1


def _single_thread_blas():
    """Limit BLAS/LAPACK to one thread while patches are solved in parallel threads."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1)


class PoURefit:
    """What a new lambda needs from a fitted partition of unity (:func:`fit_pou` with ``keep``).

    The patches' layout and members are kept, and the coarse fit with its sampled grid: its lambda
    is :data:`COARSE_LAM` whatever the fit's, so a new lambda leaves it as it is. :meth:`refit`
    solves the patches again with a new lambda, by Cholesky as :func:`fit_pou` does (the same
    function to the bit), or, after :meth:`factorize`, from each patch's eigendecomposition
    (:class:`PatchEigen`): one compiled pass over their eigenvectors. When the
    patches' lambda does not change either (noisy input: the noise floor), the function is this one.

    Attributes
    ----------
    a : (2N, D) float64, y : (2N,) float64
        The constraints (shared, not copied).
    patches : list of (int, (m,) int)
        Fitted patch index and its constraint rows.
    lam : float
        The lambda of ``fn``.
    """

    def __init__(self, *, fn: PoUFunction, info: PoUInfo, a, y, coarse_rows, coarse_a, patches, lam: float):
        self.fn, self.info, self.a, self.y = fn, info, a, y
        self.coarse_rows, self.coarse_a, self.patches, self.lam = coarse_rows, coarse_a, patches, lam
        self.patch_eigen = None  # PatchEigen

    @property
    def factorized(self) -> bool:
        return self.patch_eigen is not None

    @property
    def nbytes(self) -> int:
        """Bytes held by the factorisations and the coarse grid (the rest is shared with the fit)."""
        return int(self.fn.f0_grid.nbytes) + (0 if self.patch_eigen is None else self.patch_eigen.nbytes)

    def factorize(self, cancel_poll: CancelPoll = None) -> None:
        """Eigendecompose every patch's Gram matrix (once)."""
        from .refit import GramEigen

        if self.factorized:
            return
        pe = PatchEigen.empty(np.array([len(rows) for _, rows in self.patches], dtype=np.int64),
                              np.array([self.fn.start[patch] for patch, _ in self.patches], dtype=np.int64))
        for i, (_, rows) in enumerate(self.patches):
            if cancel_poll is not None and i % 64 == 0:
                cancel_poll()
            u, r = split_unit(self.a[rows])
            pe.put(i, GramEigen.of(pk.gram_general(u, r, 0.0)), self.y[rows], r)
        self.patch_eigen = pe

    def refit(self, lam: float, patch_lam: float | None = None, cancel_poll: CancelPoll = None) -> PoURefit:
        """The partition of unity for a new ``lam`` (``patch_lam`` for the patches, default ``lam``)."""
        old = self.fn
        local_lam = float(lam) if patch_lam is None else float(patch_lam)
        if local_lam == self.info.patch_lam:
            fn = old  # the same patches and the same coarse fit: the same function
        else:
            beta = np.empty_like(old.beta)
            if self.patch_eigen is not None:
                self.patch_eigen.solve(local_lam, beta)
            else:
                def work(job):
                    return job[0], _solve_patch(self.a[job[1]], self.y[job[1]], local_lam)[1]

                workers = max(1, min(os.cpu_count() or 1, _numba_threads()))
                with _single_thread_blas(), ThreadPoolExecutor(workers) as ex:
                    for patch, b in ex.map(work, self.patches):
                        beta[old.start[patch] : old.start[patch] + old.count[patch]] = b
            if cancel_poll is not None:
                cancel_poll()
            fn = PoUFunction(old.lo, old.h, old.dims, old.start, old.count, old.cu, beta, old.coarse, old.engine,
                             old.features, far_nodes=old.far_nodes, f0_grid=old.f0_grid)
        info = PoUInfo(**{**self.info.__dict__, "patch_lam": local_lam})
        new = PoURefit(fn=fn, info=info, a=self.a, y=self.y, coarse_rows=self.coarse_rows, coarse_a=self.coarse_a,
                       patches=self.patches, lam=float(lam))
        new.patch_eigen = self.patch_eigen
        return new


@dataclass
class PatchEigen:
    """Every patch's eigendecomposition (:class:`nkf_model.fit.refit.GramEigen`) in flat arrays, with
    ``b = Q^T y`` (lambda does not change it): a new lambda is then one pass over the eigenvectors in
    one compiled loop (:func:`nkf_model.fit._pou_kernels.eigen_solve_all`) instead of two
    matrix-vector products per patch from Python (0.07 s for the 1,620 patches of 10,000 points)."""

    q: np.ndarray
    q_off: np.ndarray
    e: np.ndarray
    b: np.ndarray
    r: np.ndarray
    v_off: np.ndarray
    m: np.ndarray
    floor: np.ndarray
    out_off: np.ndarray

    @classmethod
    def empty(cls, m: np.ndarray, out_off: np.ndarray) -> PatchEigen:
        """Room for patches of ``m`` (P,) constraints whose weights start at ``out_off`` (P,) in beta."""
        q_off = np.concatenate([[0], np.cumsum(m * m)[:-1]]).astype(np.int64)
        v_off = np.concatenate([[0], np.cumsum(m)[:-1]]).astype(np.int64)
        nq, nv = int((m * m).sum()), int(m.sum())
        return cls(q=np.empty(nq), q_off=q_off, e=np.empty(nv), b=np.empty(nv), r=np.empty(nv), v_off=v_off,
                   m=m, floor=np.empty(len(m)), out_off=out_off)

    def put(self, p: int, eig, y: np.ndarray, r: np.ndarray) -> None:
        """Patch ``p``'s :class:`nkf_model.fit.refit.GramEigen`, its labels ``y`` and norms ``r``."""
        n, qo, vo = int(self.m[p]), int(self.q_off[p]), int(self.v_off[p])
        self.q[qo : qo + n * n] = eig.Q.reshape(-1)
        self.e[vo : vo + n] = eig.e
        self.b[vo : vo + n] = eig.Q.T @ y
        self.r[vo : vo + n] = r
        self.floor[p] = eig.floor

    def solve(self, lam: float, out: np.ndarray) -> np.ndarray:
        """Write every patch's ``alpha * r`` for the local lambda ``lam`` into ``out`` (the beta array)."""
        with NumbaEngine._lock:  # numba's parallel loops may not run from two threads at once
            return pk.eigen_solve_all(self.q, self.q_off, self.e, self.b, self.r, self.v_off, self.m, self.floor,
                                      self.out_off, float(lam), out)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.q, self.q_off, self.e, self.b, self.r, self.v_off, self.m,
                                           self.floor, self.out_off)))
