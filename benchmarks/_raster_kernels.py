"""Compiled depth-buffer rasteriser for the synthetic scanners (:mod:`benchmarks.scenes`,
:mod:`benchmarks.range_scans`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True)
def rasterise_faces(cam, size, near):  # pragma: no cover - compiled
    """Nearest triangle seen through each pixel of a pinhole camera.

    Parameters
    ----------
    cam : (F, 3, 3) float64
        Triangle corners in camera coordinates ``(a, b, w)``: ``w`` along the viewing axis (> 0 in
        front), ``a`` and ``b`` already divided by the tangent of the half field of view, so that the
        image covers ``|a / w| <= 1``, ``|b / w| <= 1``.
    size : int
        Pixels per side.
    near : float
        Triangles with a corner nearer than this are skipped.

    Returns
    -------
    depth : (size, size) float64
        Smallest ``w`` seen through each pixel (``inf`` where nothing is seen).
    face : (size, size) int64
        Index of that triangle (-1 where nothing is seen).
    """
    zbuf = np.full((size, size), np.inf)
    fbuf = np.full((size, size), -1, dtype=np.int64)
    half = 0.5 * size
    for f in range(cam.shape[0]):
        w0 = cam[f, 0, 2]
        w1 = cam[f, 1, 2]
        w2 = cam[f, 2, 2]
        if w0 < near or w1 < near or w2 < near:
            continue
        x0 = (cam[f, 0, 0] / w0 + 1.0) * half
        y0 = (cam[f, 0, 1] / w0 + 1.0) * half
        x1 = (cam[f, 1, 0] / w1 + 1.0) * half
        y1 = (cam[f, 1, 1] / w1 + 1.0) * half
        x2 = (cam[f, 2, 0] / w2 + 1.0) * half
        y2 = (cam[f, 2, 1] / w2 + 1.0) * half
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        i0 = max(0, int(math.floor(min(x0, x1, x2))))
        i1 = min(size - 1, int(math.ceil(max(x0, x1, x2))))
        j0 = max(0, int(math.floor(min(y0, y1, y2))))
        j1 = min(size - 1, int(math.ceil(max(y0, y1, y2))))
        if i0 > i1 or j0 > j1:
            continue
        iw0 = 1.0 / w0
        iw1 = 1.0 / w1
        iw2 = 1.0 / w2
        for i in range(i0, i1 + 1):
            px = i + 0.5
            for j in range(j0, j1 + 1):
                py = j + 0.5
                l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                l2 = 1.0 - l0 - l1
                if l0 < -1e-9 or l1 < -1e-9 or l2 < -1e-9:
                    continue
                w = 1.0 / (l0 * iw0 + l1 * iw1 + l2 * iw2)  # perspective-correct depth
                if w < zbuf[i, j]:
                    zbuf[i, j] = w
                    fbuf[i, j] = f
    return zbuf, fbuf


@nb.njit(nogil=True, cache=True)
def lookup_depth(zbuf, a, b, w):  # pragma: no cover - compiled
    """Buffer depth at the pixel of each point (camera coordinates), ``-inf`` outside the image."""
    size = zbuf.shape[0]
    half = 0.5 * size
    out = np.full(a.shape[0], -np.inf)
    for k in range(a.shape[0]):
        if w[k] <= 0:
            continue
        i = int(math.floor((a[k] / w[k] + 1.0) * half))
        j = int(math.floor((b[k] / w[k] + 1.0) * half))
        if 0 <= i < size and 0 <= j < size:
            out[k] = zbuf[i, j]
    return out
