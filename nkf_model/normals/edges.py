"""Sign relations along the edges of the neighbour graph, shared by the orientation steps
(:mod:`nkf_model.normals.estimate`) and the learned sign check (:mod:`nkf_model.normals.sign_check`)."""

from __future__ import annotations

import numpy as np

SIG_NOISE = 1.5  # offsets along the normals below this many noise levels are noise
WINDING_EXCLUDE = 3.0  # radius the winding-number step leaves out around each point, in spacings


def across_significant(across, length, i, j, noise):
    """Whether an edge's offset along the normals stands out of the noise (:data:`SIG_NOISE`)."""
    if noise is None:
        return np.ones(len(across), dtype=bool)
    return 0.5 * across * length > SIG_NOISE * np.maximum(noise[i], noise[j])


def edge_relation(points, normals, i, j, noise=None) -> np.ndarray:
    """For edges ``(i, j)``: +1 if the estimated normals keep their relative sign, -1 if one flips.

    Along the surface (the offset lies in both tangent planes) they agree; straight across a thin
    plate or a narrow gap (the offset runs along both normals) the outward normals point opposite
    ways; at a sharp edge (normals more than 60 degrees apart) the edge is taken as convex, each
    normal pointing away from the other point. ``noise`` (N,), the points' plane-fit residuals:
    offsets along the normals within :data:`SIG_NOISE` of them do not count as "across".
    """
    off = points[j] - points[i]
    length = np.linalg.norm(off, axis=1)
    off = off / np.maximum(length, 1e-300)[:, None]
    dot = np.sum(normals[i] * normals[j], axis=1)
    a = np.sum(normals[i] * off, axis=1)
    b = np.sum(normals[j] * off, axis=1)
    across = (np.abs(a) + np.abs(b) > 1.0) & across_significant(np.abs(a) + np.abs(b), length, i, j, noise)
    smooth = np.where(dot >= 0, 1.0, -1.0) * np.where(across, -1.0, 1.0)
    convex = -np.where(a >= 0, 1.0, -1.0) * np.where(b >= 0, 1.0, -1.0)
    return np.where(np.abs(dot) >= 0.5, smooth, convex)


def relation_matrix(g, points, normals, noise=None):
    """Signed edge weights (sparse, like the neighbour graph ``g`` of costs): ``w_ij * r_ij`` with
    ``r_ij`` from :func:`edge_relation` (+1 when the two estimated normals should keep their relative
    sign, -1 when one of them should flip) and ``w_ij = exp(-cost_ij / 0.2)`` (confident edges weigh
    about 1, ambiguous ones about 0)."""
    from scipy.sparse import coo_matrix

    g = g.tocoo()
    i, j = g.row, g.col
    rel = edge_relation(points, normals, i, j, noise)
    w = np.exp(-g.data / 0.2)
    return coo_matrix((w * rel, (i, j)), shape=g.shape).tocsr()
