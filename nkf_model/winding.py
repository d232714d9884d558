"""The winding number of an oriented point cloud, for the sign far from the data.

For points ``x_j`` with outward unit normals ``n_j`` standing for surface pieces of area ``a_j``, the
generalised winding number (Barill et al. 2018, "Fast winding numbers for soups and clouds") is::

    w(q) = sum_j a_j n_j . (x_j - q) / (4 pi |x_j - q|^3)

About 1 inside a closed sampled surface and 0 outside. Away from the data it is a sum of dipoles and
tends to 0 whatever the surface's shape: the two close sheets of a thin part cancel instead of
leaving a sign to chance, and an open part leaves at most a smooth bump. The partition-of-unity
solver (:mod:`nkf_model.pou`) uses it where no patch holds data. Far from the data the sum needs no
detail, so :func:`far_field` lumps the points into clusters, each one dipole (the first term of the
paper's Barnes-Hut expansion).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from .sampling import farthest_point_sample

AREA_NEIGHBOURS = 8  # a point's area: the disc through its 8th neighbour, shared by 8 points
FAR_CLUSTERS = 1000  # dipoles of the far-field sum


@nb.njit(parallel=True, nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz"})
def _dipole_sum(q, x, m):  # pragma: no cover - compiled
    out = np.empty(q.shape[0])
    for i in nb.prange(q.shape[0]):
        s = 0.0
        for j in range(x.shape[0]):
            dx = x[j, 0] - q[i, 0]
            dy = x[j, 1] - q[i, 1]
            dz = x[j, 2] - q[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 > 0.0:
                s += (m[j, 0] * dx + m[j, 1] * dy + m[j, 2] * dz) / (r2 * math.sqrt(r2))
        out[i] = s / (4.0 * math.pi)
    return out


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
    m = np.ascontiguousarray(normals * areas[:, None], dtype=np.float64)
    return _dipole_sum(np.ascontiguousarray(queries, dtype=np.float64),
                       np.ascontiguousarray(points, dtype=np.float64), m)


def far_field(queries: np.ndarray, points: np.ndarray, normals: np.ndarray, clusters: int = FAR_CLUSTERS,
              seed: int = 0) -> np.ndarray:
    """Winding number (Q,) at ``queries`` away from the data, from ``clusters`` lumped dipoles.

    The points are split among ``clusters`` farthest-point-sampled centres (each point to its
    nearest centre); each cluster becomes one dipole, the sum of its points' ``a_j n_j`` at their
    area-weighted centroid. Accurate at distances
    well above the cluster size (about the spacing of the centres); near the data use
    :func:`winding_number`. O(Q * clusters) after an O(N log N) set-up.

    Parameters
    ----------
    queries : (Q, 3) float64
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit outward normals.
    clusters : int
        Number of dipoles (all points are used as they are when there are fewer).
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if len(points) <= AREA_NEIGHBOURS:
        raise ValueError(f"at least {AREA_NEIGHBOURS + 1} points are needed, got {len(points)}")
    area = point_areas(points)
    moment = normals * area[:, None]
    if len(points) > clusters:
        centres = points[farthest_point_sample(points, clusters, seed=seed)]
        _, owner = cKDTree(centres).query(points)

        def total(v):
            return np.bincount(owner, weights=v, minlength=clusters)

        # Each cluster is one dipole at its members' area-weighted centroid.
        weight = total(area)
        kept = weight > 0  # (a centre can lose its points only to an exact duplicate of itself)
        points = np.stack([total(area * points[:, c]) for c in range(3)], 1)[kept] / weight[kept, None]
        moment = np.stack([total(moment[:, c]) for c in range(3)], 1)[kept]
    return _dipole_sum(np.ascontiguousarray(queries, dtype=np.float64), np.ascontiguousarray(points),
                       np.ascontiguousarray(moment))
