"""Make normal signs consistent along the surface: Hoppe's tangent-plane propagation.

Hoppe et al. (SIGGRAPH 1992, "Surface reconstruction from unorganized points") orient normals along a
minimum spanning tree of the k-nearest-neighbour graph weighted by ``1 - |n_i . n_j|``: the tree
follows the flattest paths, and each point takes its parent's side. Open3D's
``orient_normals_consistent_tangent_plane`` is the same method. It knows nothing of which side is out;
here each connected piece of the graph takes the side a ``reference`` orientation (the views', layers'
and winding number's of :mod:`nkf_model.normals.estimate`) gives most of its points.

Why: on simulated turntable range scans (benchmarks/range_scans.py, the bottom never scanned) the
views look into the open bottom and seed whole faces from the inside; 3 to 7 % of the signs came out
wrong. The propagation itself is nearly always right on such dense, smooth data (0.01 to 0.15 % wrong
with Open3D's implementation on the same points); the reference only has to be right on most of each
piece.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from .estimate import _propagate_signs

# Neighbours per point in the graph (Open3D's documented example uses 15 too).
CONSISTENT_K = 15


def consistent_signs(points: np.ndarray, normals: np.ndarray, reference: np.ndarray | None = None,
                     k: int = CONSISTENT_K, tree: cKDTree | None = None) -> tuple[np.ndarray, int]:
    """Signs that make ``normals`` consistent along the surface, piece by piece.

    Parameters
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals (any signs).
    reference : (N,) float64, optional
        +1/-1 per point: the sign each point should have if the reference orientation were right.
        Each connected piece of the neighbour graph is flipped as a whole to agree with the
        reference on most of its points. None: every piece keeps its root's current sign.
    k : int
        Neighbours per point.
    tree : scipy.spatial.cKDTree, optional
        A tree over ``points``.

    Returns
    -------
    signs : (N,) float64
        +1/-1: ``normals * signs[:, None]`` is consistent along the spanning tree.
    pieces : int
        Connected pieces of the neighbour graph.
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    n = len(p)
    if n == 0:
        return np.ones(0), 0
    k = min(k, n - 1)
    if k < 1:
        return np.ones(n), n
    tree = tree if tree is not None else cKDTree(p)
    _, idx = tree.query(p, k=k + 1)
    rows = np.repeat(np.arange(n), k)
    cols = idx[:, 1:].reshape(-1)
    keep = cols < n  # fewer distinct points than k + 1
    rows, cols = rows[keep], cols[keep]
    cos = np.einsum("ij,ij->i", nrm[rows], nrm[cols])
    # Flattest paths first; a tiny floor keeps parallel neighbours as edges (a sparse zero is no edge).
    w = 1.0 - np.abs(cos) + 1e-9
    g = coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
    g = g.maximum(g.T)
    mst = minimum_spanning_tree(g).tocoo()
    n_pieces, labels = connected_components(mst, directed=False)
    # One traversal for all pieces: a virtual root (index n) joined to each piece's first point.
    first = np.full(n_pieces, -1, dtype=np.int64)
    first[labels[::-1]] = np.arange(n)[::-1]
    full = coo_matrix((np.concatenate([mst.data, np.full(n_pieces, 1e-12)]),
                       (np.concatenate([mst.row, np.full(n_pieces, n)]), np.concatenate([mst.col, first]))),
                      shape=(n + 1, n + 1)).tocsr()
    order, pred = breadth_first_order(full, n, directed=False, return_predecessors=True)
    order = order[order != n].astype(np.int64)
    pred = pred[:n].astype(np.int64)
    pred[(pred == n) | (pred < 0)] = -1
    relation = np.ones(n)
    child = np.flatnonzero(pred >= 0)
    relation[child] = np.where(np.einsum("ij,ij->i", nrm[child], nrm[pred[child]]) >= 0, 1.0, -1.0)
    signs = _propagate_signs(order, pred, relation, np.ones(n))
    if reference is not None:
        ref = np.asarray(reference, dtype=np.float64)
        agree = np.bincount(labels, weights=signs * ref, minlength=n_pieces)
        signs *= np.where(agree < 0, -1.0, 1.0)[labels]
    return signs, int(n_pieces)
