"""Voxel-grid reduction of dense point clouds.

Points are binned into cubic voxels and every occupied voxel is replaced by the mean of its points
(positions, normals, colours). Means, not picks: averaging k points also averages their noise, so
the reduced cloud keeps most of the accuracy that the extra points carried. When normals are given,
points whose normals point to different sides (the two faces of a plate thinner than a voxel) are
binned apart, by the signed axis their normal is closest to, so the two faces survive.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class Reduced:
    """A reduced point cloud.

    Attributes
    ----------
    points : (M, 3) float64
        Voxel means, in the units of the input.
    normals : (M, 3) float64 or None
        Unit mean normals (``None`` when the input had none).
    colors : (M, 3) float64 or None
        Mean colours in the input's colour units (``None`` when the input had none).
    voxel : float
        Voxel side in the units of the input (0 when nothing was reduced).
    counts : (M,) int64
        Input points behind each reduced point.
    """

    points: np.ndarray
    normals: Optional[np.ndarray]
    colors: Optional[np.ndarray]
    voxel: float
    counts: np.ndarray


def _normal_bin(normals: np.ndarray) -> np.ndarray:
    """0..5: the signed coordinate axis each unit normal (N, 3) is closest to."""
    axis = np.argmax(np.abs(normals), axis=1)
    negative = normals[np.arange(len(normals)), axis] < 0
    return 2 * axis + negative


def voxel_reduce(points, normals=None, colors=None, voxel: float = 0.0) -> Reduced:
    """Average points per voxel of side ``voxel`` (same units as ``points``).

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float, optional
        Unit normals; averaged and renormalised per (voxel, normal side).
    colors : (N, C) float or int, optional
        Per-point colours; averaged (returned as float64).
    voxel : float
        Voxel side; ``<= 0`` returns the input unchanged.

    Returns
    -------
    Reduced
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    if voxel <= 0 or n == 0:
        return Reduced(
            p,
            None if normals is None else np.asarray(normals, dtype=np.float64),
            None if colors is None else np.asarray(colors, dtype=np.float64),
            0.0,
            np.ones(n, dtype=np.int64),
        )
    ijk = np.floor((p - p.min(axis=0)) / voxel).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    if normals is not None:
        key = key * 6 + _normal_bin(np.asarray(normals, dtype=np.float64))
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    m = len(counts)

    def mean(a):
        a = np.asarray(a, dtype=np.float64)
        out = np.empty((m, a.shape[1]))
        for c in range(a.shape[1]):
            out[:, c] = np.bincount(inverse, weights=a[:, c], minlength=m)
        return out / counts[:, None]

    rp = mean(p)
    rn = None
    if normals is not None:
        rn = mean(normals)
        length = np.linalg.norm(rn, axis=1, keepdims=True)
        rn = rn / np.maximum(length, 1e-12)
    rc = None if colors is None else mean(colors)
    return Reduced(rp, rn, rc, float(voxel), counts.astype(np.int64))


def voxel_for_count(points: np.ndarray, target: int, start: float, max_steps: int = 8) -> float:
    """Smallest voxel side, starting from ``start`` and growing by factors of about 1.2-2, at which
    the number of occupied voxels of ``points`` (N, 3) is at most ``target``."""
    p = np.asarray(points, dtype=np.float64)
    lo = p.min(axis=0)
    v = float(start)
    for _ in range(max_steps):
        ijk = np.floor((p - lo) / v).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        occupied = len(np.unique((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]))
        if occupied <= target:
            return v
        # On a surface the count falls as v^2.
        v *= float(np.clip(np.sqrt(occupied / target) * 1.05, 1.2, 2.0))
    return v
