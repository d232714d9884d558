"""Compiled depth-buffer loops for visibility-based normal orientation (see :mod:`nkf_model.normals.estimate`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True)
def zbuffer_margin(u, v, w, su, sv, radius, use, pixel, lo, hi):  # pragma: no cover - compiled
    """How far behind the front each point lies, its points drawn as tangent-plane discs into a depth
    buffer.

    Parameters
    ----------
    u, v : (N,) float64
        Image coordinates (same units as ``pixel``, ``lo``, ``hi``, ``radius``).
    w : (N,) float64
        Depth along the line of sight (smaller is nearer).
    su, sv : (N,) float64
        Depth slope of each point's tangent plane along u and v.
    radius : (N,) float64
        Disc radius of each point in image units.
    use : (N,) bool
        Points to draw and test (the others get an infinite margin).
    pixel, lo, hi : float
        Pixel size and the image's extent ``[lo, hi]`` along u and v.

    Returns
    -------
    (N,) float64
        Each point's depth (its plane's, at its pixel's centre) minus the buffer's depth there: a
        point is visible with a depth tolerance ``tol`` where this is at most ``tol``. Infinite for
        points not used or outside the image.
    """
    n = u.shape[0]
    size = int(math.ceil((hi - lo) / pixel)) + 1
    zbuf = np.full((size, size), np.inf)
    for i in range(n):
        if not use[i]:
            continue
        r = radius[i]
        i0 = max(0, int(math.floor((u[i] - r - lo) / pixel)))
        i1 = min(size - 1, int(math.floor((u[i] + r - lo) / pixel)))
        j0 = max(0, int(math.floor((v[i] - r - lo) / pixel)))
        j1 = min(size - 1, int(math.floor((v[i] + r - lo) / pixel)))
        r2 = r * r
        for a in range(i0, i1 + 1):
            du = lo + (a + 0.5) * pixel - u[i]
            for b in range(j0, j1 + 1):
                dv = lo + (b + 0.5) * pixel - v[i]
                if du * du + dv * dv > r2:
                    continue
                z = w[i] + su[i] * du + sv[i] * dv
                if z < zbuf[a, b]:
                    zbuf[a, b] = z
    out = np.full(n, np.inf)
    for i in range(n):
        if not use[i]:
            continue
        a = int(math.floor((u[i] - lo) / pixel))
        b = int(math.floor((v[i] - lo) / pixel))
        if 0 <= a < size and 0 <= b < size:
            du = lo + (a + 0.5) * pixel - u[i]
            dv = lo + (b + 0.5) * pixel - v[i]
            z = w[i] + su[i] * du + sv[i] * dv
            out[i] = z - zbuf[a, b]
    return out
