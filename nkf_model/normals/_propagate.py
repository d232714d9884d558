"""Sign propagation along a minimum spanning forest hung from a virtual root, shared by the
orientation (:mod:`nkf_model.normals.estimate`) and the tangent-plane check
(:mod:`nkf_model.normals.consistent`)."""

from __future__ import annotations

import numpy as np

try:
    import numba as _nb

    @_nb.njit(cache=True, nogil=True)
    def propagate_signs(order, pred, relation, start):  # pragma: no cover - compiled
        """Signs (N,) from ``start`` (N,): in breadth-first ``order``, each point with a parent
        ``pred[v] >= 0`` takes its parent's sign times ``relation[v]``."""
        sign = start.copy()
        for pos in range(order.shape[0]):
            v = order[pos]
            p = pred[v]
            if p >= 0:
                sign[v] = sign[p] * relation[v]
        return sign

except ImportError:  # pragma: no cover - numba is a declared dependency

    def propagate_signs(order, pred, relation, start):
        sign = start.copy()
        for v in order:
            if pred[v] >= 0:
                sign[v] = sign[pred[v]] * relation[v]
        return sign


def first_points(labels: np.ndarray, n_pieces: int) -> np.ndarray:
    """The lowest index of each piece (``labels`` (N,) from ``connected_components``): (n_pieces,) int64."""
    first = np.full(n_pieces, -1, dtype=np.int64)
    first[labels[::-1]] = np.arange(len(labels))[::-1]
    return first


def spanning_order(g, roots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first ``order`` (N,) int64 and parents ``pred`` (N,) int64 (-1 for the roots) of the
    minimum spanning forest of the sparse cost graph ``g`` (N, N), every point of ``roots`` hung
    from one virtual root by the cheapest edges, so that the traversal reaches each piece that holds
    a root; the input of :func:`propagate_signs`."""
    from scipy.sparse import coo_matrix  # SciPy's graph module only when orienting
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    n = g.shape[0]
    g = g.tocoo()
    roots = np.asarray(roots, dtype=np.int64)
    full = coo_matrix((np.concatenate([g.data, np.full(len(roots), 1e-12)]),
                       (np.concatenate([g.row, np.full(len(roots), n)]), np.concatenate([g.col, roots]))),
                      shape=(n + 1, n + 1)).tocsr()
    order, pred = breadth_first_order(minimum_spanning_tree(full), n, directed=False, return_predecessors=True)
    pred = pred[:n].astype(np.int64)
    pred[(pred == n) | (pred < 0)] = -1
    return order[order != n].astype(np.int64), pred
