"""Estimate the position noise of an oriented point cloud, for noise-aware regularisation.

For each point, the distances along its normal to its nearest neighbours on the same sheet (normals
within about 25 degrees) are taken; the median of their per-point medians is the estimate. On a
noise-free sampling of flat or gently curved parts it is near 0; with Gaussian position noise of
standard deviation ``s`` it is about ``0.85 s`` while the point spacing is larger than ``s``
(measured on training meshes of the corpus at 10,000 points; less at denser sampling).
The regularisation it sets (:func:`noise_lam`) is relative to the point spacing. Neighbours
on the other side of a thin part (opposite normals) are left out, so thin parts do not read as noise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NOISE_NEIGHBOURS = 16
SAME_SHEET_COS = 0.9
# Local regularisation per constraint for the partition-of-unity solves: lam = NOISE_LAM_PER_RATIO *
# (s / h)^2 for an estimated noise s and a median point spacing h (both in the same units, so the rule
# does not depend on the units or on the density). Chosen 2026-12-04 with splines on 6 `val` meshes
# (every 10th from the second) at 10,000, 30,000 and 100,000 points with Gaussian noise 0.002 and
# 0.005: 8e-4 was best or within 0.0005 IoU of the best at every size and noise among 4e-4, 8e-4,
# 1.6e-3 and 3.2e-3. The earlier rule, 6 s^2 (chosen at 10,000 points), regularised dense input far
# too little: at 100,000 points and noise 0.005 IoU 0.9401 against 0.9491 now; on 13 simulated
# turntable range scans normal consistency 0.9339 against 0.9424 (docs/real_scans.md).
NOISE_LAM_PER_RATIO = 8e-4


def estimate_noise(points: np.ndarray, normals: np.ndarray, k: int = NOISE_NEIGHBOURS, sample: int = 20_000,
                   seed: int = 0, tree: cKDTree | None = None) -> float:
    """Position noise (a standard deviation, in the units of ``points``) of an oriented point cloud.

    Parameters
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals (given or estimated).
    k : int
        Neighbours per point.
    sample : int
        At most this many points are examined (a fixed random subset), against all points.
    tree : scipy.spatial.cKDTree, optional
        A tree over ``points`` (built here when not given).

    Returns
    -------
    float
        0 for fewer than ``k + 1`` points.
    """
    n = len(points)
    if n <= k:
        return 0.0
    rng = np.random.default_rng(seed)
    sel = np.arange(n) if n <= sample else rng.choice(n, sample, replace=False)
    tree = tree if tree is not None else cKDTree(points)
    _, idx = tree.query(points[sel], k=k + 1)
    idx = idx[:, 1:]
    nrm = normals[sel]
    h = np.abs(np.einsum("nkj,nj->nk", points[idx] - points[sel][:, None], nrm))
    same = np.einsum("nkj,nj->nk", normals[idx], nrm) > SAME_SHEET_COS
    h = np.where(same, h, np.inf)
    h.sort(axis=1)
    count = same.sum(axis=1)
    ok = count > 0
    per = h[ok, (count[ok] - 1) // 2]  # the median (lower) of each point's same-sheet distances
    return float(np.median(per)) if len(per) else 0.0


def noise_lam(sigma: float, spacing: float, lam: float) -> float:
    """Regularisation per constraint for local fits of input with estimated noise ``sigma`` and median
    point spacing ``spacing`` (the same units): ``NOISE_LAM_PER_RATIO * (sigma / spacing)^2``, at
    least ``lam``; just ``lam`` for a spacing of 0."""
    if not spacing > 0:
        return float(lam)
    return max(float(lam), NOISE_LAM_PER_RATIO * (float(sigma) / float(spacing)) ** 2)
