"""Move noisy points to the middle of their surface: one bilateral step along each point's normal.

Real range scans are layered: overlapping range images that do not register perfectly leave two or
more copies of one surface a fraction of a millimetre apart, each with its own noise. A fit that
interpolates every point follows each layer; this step moves every point along its normal to the
weighted mean height of its neighbours on the same sheet, so that the layers meet in the middle
(the bilateral filter of Fleishman, Drori and Cohen-Or, "Bilateral mesh denoising", 2003, on points):

    x_i' = x_i + n_i * sum_j w_ij ((x_j - x_i) . n_i) / (1 + sum_j w_ij)

with Gaussian weights on the tangential distance (the point itself has weight 1 and height 0), over
the neighbours whose normals lie within about 25 degrees of the point's own, the same way round: the
other face of a thin part, or a neighbour across a sharp edge, does not pull the point. The part of
each move that its neighbours share (the same weighted mean of their moves) is taken out: noise and
interleaved layers differ from point to point, the surface's own bend does not, so curved and
detailed surfaces keep their shape (forced onto a clean 10,000-point sample of
bullet3__textured-0008192 with estimated normals, the plain step costs 0.0105 IoU, this one 0.0019).
Each move is at most ``max_move`` noise levels, so no point travels further than the noise could
have put it.

Used by :func:`nkf_model.reconstruct` on clouds whose normal estimation reads them as misregistered
scans (layers on either side as often), of :data:`DENOISE_MIN_POINTS` points or more, whose median
move is at least :data:`DENOISE_MIN_MOVE` spacings (:func:`is_noisy`). Measured with estimated
normals: clean 10,000-point samples of 5 `val` meshes read 0.02 to 0.07 (their estimated noise 0.1
to 0.3 spacings, from the bend), and none of 18 reaches 0.1 at 10,000 or 50,000 points; at 1,000
points 5 of those 18 read 0.10 to 0.15 (hence the size). With noise 0.005 (their own normals) the same 5 read
0.23 to 0.38 at 10,000 points, their simulated all-round range scans 0.21 to 0.25.
Dense noisy samples of one surface are not moved: on them it cost detail (docs/real_scans.md).
Chosen on simulated all-round range scans.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from .noise import SAME_SHEET_COS  # normals within about 25 degrees, the same way round: one sheet

DENOISE_MIN_POINTS = 10_000  # smaller inputs are left alone (sparse clean samples bend too much per spacing)
DENOISE_MIN_MOVE = 0.1  # median move (curvature taken out), in spacings, from which the points are moved
DENOISE_NEIGHBOURS = 16
DENOISE_RADIUS = 1.5  # Gaussian width of the tangential weights, in point spacings
DENOISE_MAX_MOVE = 1.5  # largest move, in noise levels
_CHUNK = 50_000


def along_normal_moves(points: np.ndarray, normals: np.ndarray, spacing: float, *,
                       k: int = DENOISE_NEIGHBOURS, radius: float = DENOISE_RADIUS, tree: Optional[cKDTree] = None,
                       cancel_poll: Optional[Callable[[], None]] = None, keep_curvature: bool = True) -> np.ndarray:
    """How far each point lies from the middle of its same-sheet neighbours, along its normal.

    Parameters
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals, oriented (the other face of a thin part points the other way).
    spacing : float
        Median distance to the nearest neighbour, in the units of ``points``.
    k : int
        Neighbours per point.
    radius : float
        Width of the tangential Gaussian weight, in spacings.
    tree : scipy.spatial.cKDTree, optional
        A tree over ``points``.
    cancel_poll : callable, optional
        Called between chunks of points; raises to stop.
    keep_curvature : bool
        Take out the part of each move its neighbours share (the default); ``False`` gives each
        point's own weighted mean height (a plain bilateral step, which flattens bends).

    Returns
    -------
    (N,) float64
        The signed move along each normal, in the units of ``points``, unbounded; zeros when there
        are at most ``k`` points or ``spacing`` is not positive.
    """
    x = np.asarray(points, dtype=np.float64)
    n = len(x)
    if n <= k or not spacing > 0:
        return np.zeros(n)
    nrm = np.asarray(normals, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(x)
    inv = 1.0 / (2.0 * (radius * spacing) ** 2)
    moves = np.empty(n)
    neighbours = np.empty((n, k), dtype=np.int64)
    weights = np.empty((n, k))
    for lo in range(0, n, _CHUNK):
        if cancel_poll is not None:
            cancel_poll()
        hi = min(n, lo + _CHUNK)
        _, nb = tree.query(x[lo:hi], k=k + 1, workers=-1)
        nb = nb[:, 1:]
        ni = nrm[lo:hi]
        d = x[nb] - x[lo:hi, None]
        h = np.einsum("nkj,nj->nk", d, ni)
        t2 = np.maximum(np.einsum("nkj,nkj->nk", d, d) - h * h, 0.0)
        same = np.einsum("nkj,nj->nk", nrm[nb], ni) > SAME_SHEET_COS
        w = np.where(same, np.exp(-t2 * inv), 0.0)
        moves[lo:hi] = (w * h).sum(axis=1) / (w.sum(axis=1) + 1.0)
        neighbours[lo:hi] = nb
        weights[lo:hi] = w
    if keep_curvature:
        # The part of the move its neighbours share is the surface's own bend, not noise: take it out.
        moves = moves - (moves + (weights * moves[neighbours]).sum(axis=1)) / (weights.sum(axis=1) + 1.0)
    return moves


def apply_moves(points: np.ndarray, normals: np.ndarray, moves: np.ndarray, noise: float,
                max_move: float = DENOISE_MAX_MOVE) -> np.ndarray:
    """``points + clip(moves, +-max_move * noise) * normals``, a new (N, 3) array."""
    limit = max_move * max(float(noise), 0.0)
    return np.asarray(points, np.float64) + np.clip(moves, -limit, limit)[:, None] * np.asarray(normals, np.float64)


def is_noisy(moves: np.ndarray, spacing: float) -> bool:
    """Whether the median move is at least :data:`DENOISE_MIN_MOVE` spacings (noisy input)."""
    return len(moves) > 0 and spacing > 0 and float(np.median(np.abs(moves))) >= DENOISE_MIN_MOVE * spacing


def denoise_along_normals(points: np.ndarray, normals: np.ndarray, spacing: float, noise: float, *,
                          max_move: float = DENOISE_MAX_MOVE, **kw) -> np.ndarray:
    """Points moved along their normals to the middle of their same-sheet neighbours
    (:func:`along_normal_moves`, keywords as there), each by at most ``max_move * noise``.

    ``noise`` is the position noise (a standard deviation, as
    :func:`nkf_model.points.noise.estimate_noise` gives) in the units of ``points``. Returns a new
    (N, 3) array; ``points`` is not changed (a copy when ``noise`` is not positive).
    """
    if not noise > 0:
        return np.array(points, dtype=np.float64, copy=True)
    return apply_moves(points, normals, along_normal_moves(points, normals, spacing, **kw), noise, max_move)
