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
detailed surfaces keep their shape (on clean 10,000-point samples with estimated normals the
estimated noise reads up to 0.3 spacings, from the bend and not from noise: without this, IoU of
bullet3__textured-0008192 0.8157 -> 0.8052; with it 0.8138). Each move is at most ``max_move``
noise levels, so no point travels further than the noise could have put it.

Used by :func:`nkf_model.reconstruct` on input whose estimated noise is at least
:data:`DENOISE_MIN_RATIO` of the point spacing (simulated range scans read 0.36 to 0.39, the dragon of
``../shared/data/scans`` 0.26; clean samples with their own normals 0 to 0.08). Chosen on simulated
all-round range scans (docs/real_scans.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

DENOISE_MIN_RATIO = 0.15  # estimated noise / median spacing from which the points are moved
DENOISE_NEIGHBOURS = 16
DENOISE_RADIUS = 1.5  # Gaussian width of the tangential weights, in point spacings
DENOISE_SAME_SHEET = 0.9  # cos between two normals (oriented) that count as the same sheet
DENOISE_MAX_MOVE = 1.5  # largest move, in noise levels
_CHUNK = 50_000


def denoise_along_normals(points: np.ndarray, normals: np.ndarray, spacing: float, noise: float, *,
                          k: int = DENOISE_NEIGHBOURS, radius: float = DENOISE_RADIUS,
                          max_move: float = DENOISE_MAX_MOVE, tree: Optional[cKDTree] = None,
                          cancel_poll: Optional[Callable[[], None]] = None, keep_curvature: bool = True) -> np.ndarray:
    """Points moved along their normals to the weighted mean height of their same-sheet neighbours.

    Parameters
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals, oriented (the other face of a thin part points the other way).
    spacing : float
        Median distance to the nearest neighbour, in the units of ``points``.
    noise : float
        Position noise (a standard deviation, as :func:`nkf_model.points.noise.estimate_noise`
        gives), in the same units; each point moves at most ``max_move * noise``.
    k : int
        Neighbours per point.
    radius : float
        Width of the tangential Gaussian weight, in spacings.
    tree : scipy.spatial.cKDTree, optional
        A tree over ``points``.
    cancel_poll : callable, optional
        Called between chunks of points; raises to stop.
    keep_curvature : bool
        Take out the part of each move its neighbours share (the default); ``False`` moves each point
        by its own weighted mean height (a plain bilateral step, which flattens bends).

    Returns
    -------
    (N, 3) float64
        A new array (``points`` is not changed); a copy of ``points`` when there are at most ``k``
        points or ``noise`` or ``spacing`` is not positive.
    """
    x = np.array(points, dtype=np.float64, copy=True)
    n = len(x)
    if n <= k or not noise > 0 or not spacing > 0:
        return x
    nrm = np.asarray(normals, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(x)
    limit = max_move * noise
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
        same = np.einsum("nkj,nj->nk", nrm[nb], ni) > DENOISE_SAME_SHEET
        w = np.where(same, np.exp(-t2 * inv), 0.0)
        moves[lo:hi] = (w * h).sum(axis=1) / (w.sum(axis=1) + 1.0)
        neighbours[lo:hi] = nb
        weights[lo:hi] = w
    if keep_curvature:
        # The part of the move its neighbours share is the surface's own bend, not noise: take it out.
        moves = moves - (moves + (weights * moves[neighbours]).sum(axis=1)) / (weights.sum(axis=1) + 1.0)
    np.clip(moves, -limit, limit, out=moves)
    return x + moves[:, None] * nrm
