"""The winding number of an oriented point cloud, for the sign far from the data.

For points ``x_j`` with outward unit normals ``n_j`` standing for surface pieces of area ``a_j``, the
generalised winding number (Barill et al. 2018, "Fast winding numbers for soups and clouds") is::

    w(q) = sum_j a_j n_j . (x_j - q) / (4 pi |x_j - q|^3)

About 1 inside a closed sampled surface and 0 outside. Away from the data it is a sum of dipoles and
tends to 0 whatever the surface's shape: the two close sheets of a thin part cancel instead of
leaving a sign to chance, and an open part leaves at most a smooth bump. The partition-of-unity
solver (:mod:`nkf_model.fit.partition_of_unity`) uses it where no patch holds data, and :class:`BlendedField` blends a
global fit into it away from the data. Far from the data the sum needs no detail, so
:class:`FarField` lumps the points into clusters, each one dipole (the first term of the paper's
Barnes-Hut expansion).
"""

from __future__ import annotations

import math
from typing import Optional

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from .farthest_point import farthest_point_sample

AREA_NEIGHBOURS = 8  # a point's area: the disc through its 8th neighbour, shared by 8 points
FAR_CLUSTERS = 1000  # clusters of the winding-number sum
FAR_BETA = 2.0  # a cluster counts as one dipole beyond this many of its radii (Barill et al.: 2)
FAR_CHUNK = 16_384  # queries per compiled call of FarField, between cancellation checks


def point_areas(points: np.ndarray, k: int = AREA_NEIGHBOURS) -> np.ndarray:
    """Surface area (N,) each point stands for, in squared units of ``points``.

    Parameters
    ----------
    points : (N, 3) float64
        At least ``k + 1`` points.
    k : int
        The disc through the ``k``-th nearest neighbour is shared by ``k`` points.
    """
    d, _ = cKDTree(points).query(points, k=k + 1)
    return math.pi * d[:, -1] ** 2 / k


def winding_number(queries: np.ndarray, points: np.ndarray, normals: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Winding number (Q,) of an oriented point cloud at ``queries`` (Q, 3), summed directly.

    Parameters
    ----------
    queries : (Q, 3) float64
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit outward normals.
    areas : (N,) float64
        Area per point (:func:`point_areas`).
    """
    x = np.ascontiguousarray(points, dtype=np.float64)
    m = np.ascontiguousarray(normals * areas[:, None], dtype=np.float64)
    # Every point its own cluster of radius 0: always summed as a dipole (a query on a point skips it).
    return _clustered_sum(np.ascontiguousarray(queries, dtype=np.float64), x, m, np.zeros(len(x)),
                          np.arange(len(x) + 1, dtype=np.int64), x, m)


@nb.njit(inline="always", nogil=True, cache=True)
def _offset(a, k, q, i):  # pragma: no cover - compiled
    """``a[k] - q[i]`` as ``(dx, dy, dz, squared length)``."""
    dx = a[k, 0] - q[i, 0]
    dy = a[k, 1] - q[i, 1]
    dz = a[k, 2] - q[i, 2]
    return dx, dy, dz, dx * dx + dy * dy + dz * dz


@nb.njit(parallel=True, nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz"})
def _clustered_sum(q, cx, cm, cr2, first, x, m):  # pragma: no cover - compiled
    """Winding numbers at ``q``: cluster ``c`` (dipole ``cm[c]`` at ``cx[c]``) counts as one dipole
    where it is farther than ``sqrt(cr2[c])``, else point by point (rows ``first[c]:first[c+1]``)."""
    out = np.empty(q.shape[0])
    for i in nb.prange(q.shape[0]):
        s = 0.0
        for c in range(cx.shape[0]):
            dx, dy, dz, r2 = _offset(cx, c, q, i)
            if r2 > cr2[c]:
                s += (cm[c, 0] * dx + cm[c, 1] * dy + cm[c, 2] * dz) / (r2 * math.sqrt(r2))
                continue
            for j in range(first[c], first[c + 1]):
                dx, dy, dz, r2 = _offset(x, j, q, i)
                if r2 > 0.0:
                    s += (m[j, 0] * dx + m[j, 1] * dy + m[j, 2] * dz) / (r2 * math.sqrt(r2))
        out[i] = s / (4.0 * math.pi)
    return out


class _Clusters:
    """Points split among ``clusters`` farthest-point-sampled centres (each point to its nearest),
    sorted by cluster: ``points``, ``area`` (:func:`point_areas`) and ``order`` (input index of each
    sorted point), ``first`` (C + 1,) (cluster ``c`` holds rows ``first[c]:first[c+1]``), ``owner``
    (N,), the area-weighted ``centre`` (C, 3) and ``radius`` (C,) of each cluster."""

    def __init__(self, points, clusters: int, seed: int = 0, cancel_poll=None):
        points = np.asarray(points, dtype=np.float64)
        if len(points) <= AREA_NEIGHBOURS:
            raise ValueError(f"at least {AREA_NEIGHBOURS + 1} points are needed, got {len(points)}")
        area = point_areas(points)
        k = min(clusters, len(points))
        if cancel_poll is not None:
            cancel_poll()
        centres = points[farthest_point_sample(points, k, seed=seed)]
        if cancel_poll is not None:
            cancel_poll()
        _, owner = cKDTree(centres).query(points)
        order = np.argsort(owner, kind="stable")
        owner, points, area = owner[order], points[order], area[order]
        count = np.bincount(owner, minlength=k)
        kept = count > 0  # (a centre can lose its points only to an exact duplicate of itself)
        self.first = np.r_[0, np.cumsum(count[kept])].astype(np.int64)
        self.owner = (np.cumsum(kept) - 1)[owner]
        self.order, self.area = order, area
        self.points = np.ascontiguousarray(points)
        weight = np.maximum(self._sum(area), 1e-300)
        self.centre = np.ascontiguousarray(self.total(area[:, None] * points) / weight[:, None])
        dist = np.linalg.norm(points - self.centre[self.owner], axis=1)
        self.radius = np.zeros(len(self.centre))
        np.maximum.at(self.radius, self.owner, dist)

    def _sum(self, v):
        return np.bincount(self.owner, weights=v, minlength=len(self.first) - 1)

    def sort(self, v: np.ndarray) -> np.ndarray:
        """Per-point values (N, ...) in input order, sorted like :attr:`points`."""
        return v[self.order]

    def total(self, v: np.ndarray) -> np.ndarray:
        """Sums (C, 3) over each cluster of sorted per-point vectors ``v`` (N, 3)."""
        return np.ascontiguousarray(np.stack([self._sum(v[:, c]) for c in range(3)], 1))


class FarField:
    """Winding number of an oriented point cloud, summed by clusters (one level of Barnes-Hut).

    The points are split among ``clusters`` farthest-point-sampled centres (each point to its
    nearest centre). Each cluster is one dipole, the sum of its points' ``a_j n_j`` at their
    area-weighted centroid, for queries farther than :data:`FAR_BETA` times the cluster's radius
    from that centroid (the error falls as (radius / distance)^2); nearer queries sum its points one
    by one, as Barill et al. do. Set-up O(N log N); a call on Q queries costs about
    O(Q * (clusters + the points of the few clusters near each query)).

    Parameters
    ----------
    points : (N, 3) float64
        At least ``AREA_NEIGHBOURS + 1`` points.
    normals : (N, 3) float64
        Unit outward normals.
    clusters : int
        Number of clusters (every point is its own when there are fewer points).

    Call it with queries (Q, 3) float64 (and ``cancel_poll``, called between chunks of queries); it
    returns (Q,) float64. ``cancel_poll`` given to the constructor is called between its set-up steps.
    ``points`` (N, 3) holds the input points (sorted by cluster).
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, clusters: int = FAR_CLUSTERS, seed: int = 0,
                 cancel_poll=None):
        c = _Clusters(points, clusters, seed, cancel_poll)
        moment = c.sort(np.asarray(normals, dtype=np.float64)) * c.area[:, None]
        self._args = (c.centre, c.total(moment), (FAR_BETA * c.radius) ** 2)
        self._first = c.first
        self.points, self._m = c.points, np.ascontiguousarray(moment)

    def __call__(self, queries: np.ndarray, cancel_poll=None) -> np.ndarray:
        q = np.ascontiguousarray(queries, dtype=np.float64)
        out = np.empty(len(q))
        for s in range(0, len(q), FAR_CHUNK):  # ``cancel_poll`` (cancellation) between chunks
            if cancel_poll is not None:
                cancel_poll()
            out[s : s + FAR_CHUNK] = _clustered_sum(q[s : s + FAR_CHUNK], *self._args, self._first, self.points,
                                                    self._m)
        return out


@nb.njit(inline="always", nogil=True, cache=True)
def _dipole_gradient(m, k, dx, dy, dz, r2):  # pragma: no cover - compiled
    """Gradient (times 4 pi) at the query of dipole ``m[k]`` at offset ``(dx, dy, dz)`` from it."""
    r3 = r2 * math.sqrt(r2)
    t = 3.0 * (m[k, 0] * dx + m[k, 1] * dy + m[k, 2] * dz) / (r3 * r2)
    return t * dx - m[k, 0] / r3, t * dy - m[k, 1] / r3, t * dz - m[k, 2] / r3


@nb.njit(parallel=True, nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz"})
def _clustered_gradient(q, cx, cm, cr2, first, x, m, ex2):  # pragma: no cover - compiled
    """Gradients (Q, 3) of the winding number at ``q``, leaving out the points within
    ``sqrt(ex2)`` of each query; cluster ``c`` counts as one dipole beyond ``sqrt(cr2[c])``."""
    out = np.empty((q.shape[0], 3))
    for i in nb.prange(q.shape[0]):
        gx = 0.0
        gy = 0.0
        gz = 0.0
        for c in range(cx.shape[0]):
            dx, dy, dz, r2 = _offset(cx, c, q, i)
            if r2 > cr2[c]:
                ax, ay, az = _dipole_gradient(cm, c, dx, dy, dz, r2)
                gx += ax
                gy += ay
                gz += az
                continue
            for j in range(first[c], first[c + 1]):
                dx, dy, dz, r2 = _offset(x, j, q, i)
                if r2 > ex2:
                    ax, ay, az = _dipole_gradient(m, j, dx, dy, dz, r2)
                    gx += ax
                    gy += ay
                    gz += az
        out[i, 0] = gx / (4.0 * math.pi)
        out[i, 1] = gy / (4.0 * math.pi)
        out[i, 2] = gz / (4.0 * math.pi)
    return out


class WindingGradient:
    """Gradient of a point cloud's winding number, for normals whose signs are still being chosen.

    For points ``x_j`` with unit normals ``n_j``, signs ``s_j`` and areas ``a_j`` (:func:`point_areas`),
    at a query ``q``, leaving out the points within ``exclude`` of it::

        g(q) = sum_j a_j s_j (3 (n_j . r) r / |r|^5 - n_j / |r|^3) / (4 pi),   r = x_j - q

    At a point of a consistently oriented closed surface, ``-g`` points outward: the winding number
    rises from 0 outside to 1 inside, and the rest of the surface (the point's own neighbourhood,
    whose field is singular there, is left out) says which side is which. Clusters (as in
    :class:`FarField`) count as one dipole beyond :data:`FAR_BETA` radii and beyond ``exclude``
    plus their radius.

    Parameters
    ----------
    points, normals : (N, 3) float64
        At least ``AREA_NEIGHBOURS + 1`` points; unit normals of any sign.
    exclude : float
        Radius left out around each query, in the units of ``points``.

    Call it with signs (N,) in {-1, +1} (and optionally queries (Q, 3), default the points
    themselves, and ``cancel_poll``, called between chunks); it returns (Q, 3) float64.
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, exclude: float, clusters: int = FAR_CLUSTERS,
                 seed: int = 0, cancel_poll=None):
        self._c = c = _Clusters(points, clusters, seed, cancel_poll)
        self._n = c.sort(np.asarray(normals, dtype=np.float64)) * c.area[:, None]
        self._far2 = np.maximum(FAR_BETA * c.radius, float(exclude) + c.radius) ** 2
        self._ex2 = float(exclude) ** 2
        self._queries = np.ascontiguousarray(np.asarray(points, dtype=np.float64))

    def __call__(self, signs: np.ndarray, queries: Optional[np.ndarray] = None, cancel_poll=None) -> np.ndarray:
        c = self._c
        m = np.ascontiguousarray(self._n * c.sort(np.asarray(signs, dtype=np.float64))[:, None])
        q = self._queries if queries is None else np.ascontiguousarray(queries, dtype=np.float64)
        cm = c.total(m)
        out = np.empty((len(q), 3))
        for s in range(0, len(q), FAR_CHUNK):
            if cancel_poll is not None:
                cancel_poll()
            out[s : s + FAR_CHUNK] = _clustered_gradient(q[s : s + FAR_CHUNK], c.centre, cm, self._far2, c.first,
                                                         c.points, m, self._ex2)
        return out


def far_field(queries: np.ndarray, points: np.ndarray, normals: np.ndarray, clusters: int = FAR_CLUSTERS,
              seed: int = 0) -> np.ndarray:
    """Winding number (Q,) at ``queries`` (Q, 3): ``FarField(points, normals, clusters, seed)(queries)``."""
    return FarField(points, normals, clusters, seed)(queries)


def winding_scale(w: np.ndarray, fitted: np.ndarray) -> float:
    """Scale ``A`` for far-field values ``A (1/2 - w)`` that join a fitted function at its magnitude.

    The median of ``|fitted| / |1/2 - w|`` over the samples where the fitted values (M,) agree in sign
    with the winding numbers ``w`` (M,) at the same points (inside where ``w > 1/2``).
    """
    d = 0.5 - np.asarray(w, dtype=np.float64)
    fitted = np.asarray(fitted, dtype=np.float64)
    agree = (np.sign(fitted) == np.sign(d)) & (np.abs(d) > 1e-3)
    if agree.any():
        scale = float(np.median(np.abs(fitted[agree]) / np.abs(d[agree])))
    elif len(fitted):
        scale = float(np.median(np.abs(fitted))) / 0.5
    else:
        scale = 1.0
    return max(scale, 1e-12)


def follow_winding(fitted: np.ndarray, w: np.ndarray, scale: float) -> np.ndarray:
    """Fitted values (M,) where their sign agrees with the winding numbers ``w`` (M,) (inside where
    ``w > 1/2``), else ``scale * (1/2 - w)``: the fit's magnitude is kept wherever its sign is right."""
    d = 0.5 - w
    return np.where(np.sign(fitted) == np.sign(d), fitted, scale * d)


class BlendedField:
    """A fitted function near the data and the winding number's sign away from it.

    ``g(x) = (1 - b) f(x) + b F(x)`` with ``b = s((d - start) / (end - start))`` clamped
    to [0, 1], ``s(u) = 3u^2 - 2u^3``, ``d`` the distance from ``x`` to the nearest input point and
    ``F = f`` where ``f`` agrees in sign with the point cloud's winding number ``w`` (:class:`FarField`),
    else ``A (1/2 - w)`` (:func:`follow_winding`), ``A`` from :func:`winding_scale` on
    ``calibration`` uniform points of ``box`` farther than ``start`` from the data. Within ``start`` of
    a point, ``g = f`` exactly.

    A global fit through all points is right near them but guesses where they leave it free: behind
    an open or missing side it closes the surface far away, or puts spurious inside regions there
    (see :data:`nkf_model.pipeline.reconstruct.FAR_START` for what it did on the corpus).

    Parameters
    ----------
    fn : callable
        The fitted function: ``fn(x (Q, 3), check=None) -> (Q,)``.
    points, normals : (N, 3) float64
        Unit-box input points and unit outward normals.
    start, end : float
        Distances (unit-box units) where the blend begins and where the far field takes over.
    box : float
        Half-width of the cube sampled for the scale.

    Call it with queries (Q, 3) float64 (and ``cancel_poll``, passed on to ``fn``); it returns (Q,) float64.
    """

    def __init__(self, fn, points: np.ndarray, normals: np.ndarray, start: float, end: float, box: float,
                 calibration: int = 4000, seed: int = 0, cancel_poll=None):
        if not 0 < start < end:
            raise ValueError(f"need 0 < start < end, got {start!r}, {end!r}")
        self.fn = fn
        self.tree = cKDTree(points)
        self.near = NearCells(points, start)
        self.far = FarField(points, normals, seed=seed, cancel_poll=cancel_poll)
        self.start, self.end = float(start), float(end)
        q = np.random.default_rng(seed).uniform(-box, box, (calibration, 3))
        d, _ = self.tree.query(q, distance_upper_bound=self.start)
        q = q[~np.isfinite(d)]
        self.scale = winding_scale(self.far(q, cancel_poll), fn(q, cancel_poll=cancel_poll)) if len(q) else 1.0

    def __call__(self, x: np.ndarray, cancel_poll=None) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        f = self.fn(x, cancel_poll=cancel_poll)
        # Most queries lie in cells wholly within ``start`` of a point (b = 0): only the rest go to the
        # KD-tree. Beyond ``end`` it gives inf, which the clamp turns into b = 1.
        rest = np.flatnonzero(~self.near(x))
        if len(rest) == 0:
            return f
        xr = x[rest]
        d, _ = self.tree.query(xr, distance_upper_bound=self.end)
        t = np.clip((d - self.start) / (self.end - self.start), 0.0, 1.0)
        b = t * t * (3.0 - 2.0 * t)
        far = b > 0
        if far.any():
            bf = b[far]
            idx = rest[far]
            ff = f[idx]
            f[idx] = (1.0 - bf) * ff + bf * follow_winding(ff, self.far(xr[far], cancel_poll), self.scale)
        return f


class NearCells:
    """A conservative, fast test for "within ``radius`` of some point": cells of a regular grid that
    lie wholly within ``radius`` of an input point.

    A point in cell ``k`` (size ``c``) is within ``|o| c + c sqrt(3)`` of everything in cell ``k + o``,
    so the cells ``k + o`` with ``|o| c <= radius - c sqrt(3)`` are marked for every point's cell.
    ``c = radius / 6``, or coarser so that the grid has at most ``max_cells`` cells along an axis.

    Call with queries (Q, 3) float64 (unit-box units, like ``points``); returns (Q,) bool, True only
    where the query is within ``radius`` of a point (False says nothing).
    """

    def __init__(self, points: np.ndarray, radius: float, max_cells: int = 256, chunk: int = 1 << 21):
        points = np.asarray(points, dtype=np.float64)
        lo, hi = points.min(axis=0), points.max(axis=0)
        c = max(radius / 6.0, float(np.max(hi - lo)) / max_cells, 1e-12)
        reach = radius - c * math.sqrt(3.0)
        self.grid = None
        if reach < 0:
            return
        r = int(reach // c)
        o = np.stack(np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        o = o[(o * o).sum(axis=1) * (c * c) <= reach * reach]
        self.lo, self.c = lo, c
        # Padded by r cells on each side so that a point's cell plus any offset stays inside.
        self.shape = tuple(int(v) for v in np.floor((hi - lo) / c).astype(np.int64) + 1 + 2 * r)
        self.pad = r
        k = np.unique(np.floor((points - lo) / c).astype(np.int64) + r, axis=0)
        flat_k = np.ravel_multi_index(k.T, self.shape)
        flat_o = np.ravel_multi_index((o + r).T, self.shape) - np.ravel_multi_index((r, r, r), self.shape)
        grid = np.zeros(int(np.prod(self.shape)), dtype=bool)
        step = max(1, chunk // len(flat_o))
        for i in range(0, len(flat_k), step):
            grid[(flat_k[i : i + step, None] + flat_o[None, :]).ravel()] = True
        self.grid = grid.reshape(self.shape)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros(len(x), dtype=bool)
        if self.grid is None or len(x) == 0:
            return out
        k = np.floor((x - self.lo) / self.c)
        k += self.pad
        inside = np.all((k >= 0) & (k < np.asarray(self.shape)), axis=1)
        ki = k[inside].astype(np.int64)
        out[inside] = self.grid[ki[:, 0], ki[:, 1], ki[:, 2]]
        return out
