"""Compiled depth-buffer loops for visibility-based normal orientation (see :mod:`nkf_model.normals.estimate`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True)
def zbuffer_visible(u, v, w, su, sv, radius, use, pixel, lo, hi, tol):  # pragma: no cover - compiled
    """Visibility of points drawn as tangent-plane discs into a depth buffer.

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
        Points to draw and test (others are reported invisible).
    pixel, lo, hi : float
        Pixel size and the image's extent ``[lo, hi]`` along u and v.
    tol : float
        A point is visible when its depth is at most the buffer's depth at its pixel plus ``tol``.

    Returns
    -------
    (N,) bool
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
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if not use[i]:
            continue
        a = int(math.floor((u[i] - lo) / pixel))
        b = int(math.floor((v[i] - lo) / pixel))
        if 0 <= a < size and 0 <= b < size:
            du = lo + (a + 0.5) * pixel - u[i]
            dv = lo + (b + 0.5) * pixel - v[i]
            z = w[i] + su[i] * du + sv[i] * dv
            out[i] = z <= zbuf[a, b] + tol
    return out
