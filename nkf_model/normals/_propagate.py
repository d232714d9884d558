"""The sign propagation loop along a spanning tree, shared by the orientation
(:mod:`nkf_model.normals.estimate`) and the tangent-plane check (:mod:`nkf_model.normals.consistent`)."""

from __future__ import annotations

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
