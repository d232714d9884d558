"""Choosing well-spread subsets of points (for Nystrom centres)."""

from __future__ import annotations

import numpy as np

try:
    import numba as _nb
except ImportError:  # pragma: no cover - numba is a declared dependency
    _nb = None


def _fps_numpy(points: np.ndarray, k: int, start: int) -> np.ndarray:
    idx = np.empty(k, dtype=np.int64)
    idx[0] = start
    d = np.sum((points - points[start]) ** 2, axis=1)
    for i in range(1, k):
        j = int(np.argmax(d))
        idx[i] = j
        np.minimum(d, np.sum((points - points[j]) ** 2, axis=1), out=d)
    return idx


if _nb is not None:

    @_nb.njit(nogil=True, cache=True)
    def _fps_numba(points, k, start):  # pragma: no cover - compiled
        n = points.shape[0]
        idx = np.empty(k, dtype=np.int64)
        d = np.empty(n)
        idx[0] = start
        for i in range(n):
            a = points[i, 0] - points[start, 0]
            b = points[i, 1] - points[start, 1]
            c = points[i, 2] - points[start, 2]
            d[i] = a * a + b * b + c * c
        for s in range(1, k):
            j = 0
            best = -1.0
            for i in range(n):
                if d[i] > best:
                    best = d[i]
                    j = i
            idx[s] = j
            for i in range(n):
                a = points[i, 0] - points[j, 0]
                b = points[i, 1] - points[j, 1]
                c = points[i, 2] - points[j, 2]
                e = a * a + b * b + c * c
                if e < d[i]:
                    d[i] = e
        return idx


def farthest_point_sample(points: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices (k,) int64 of ``k`` points of ``points`` (N, 3) chosen by farthest-point sampling.

    Starts from a point picked with ``seed``; each next point is the one farthest from those
    already chosen, so the subset covers the cloud evenly. O(N k) time, O(N) memory.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    k = int(min(k, n))
    start = int(np.random.default_rng(seed).integers(n))
    if _nb is not None:
        return _fps_numba(points, k, start)
    return _fps_numpy(points, k, start)
