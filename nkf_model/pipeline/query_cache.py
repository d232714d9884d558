"""The query side of a fitted function at grid nodes, kept across lambdas of one fit
(:class:`QueryCache`, used by :class:`nkf_model.pipeline.fitted.Fit`)."""

from __future__ import annotations

import threading

import numpy as np

from ..surface import _flood_kernels as _fk


class _Known:
    """Stands in for a function whose values at the next call's points are already known."""

    def __init__(self, values: np.ndarray):
        self.values = values

    def __call__(self, x, cancel_poll=None):
        return self.values


class QueryCache:
    """The query side of the fitted function at grid nodes: for each node that :meth:`Fit.mesh`
    evaluated, its unit homogeneous vector ``[x : phi(x) : 1] / |...|`` and norm (``fn.query``), per
    grid level (``(r, cell)`` of :func:`nkf_model.surface.evaluate.evaluate_sparse`).

    Lambda does not change them: every fit of one :func:`nkf_model.fit` call shares the cache, and a
    new lambda (a live preview, a re-mesh after :meth:`Fit.with_lam`) sums only the weighted kernel at
    the nodes it saw before, without the learned features again. The rows are computed row by row
    (``query`` of a subset gives the same rows to the bit), so every value is what a fresh run gives.
    At most ``max_bytes`` are kept: a level that does not fit drops the others first, then stops
    growing (its new nodes are computed and not kept)."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._levels: dict = {}  # level -> [keys table, row table, qu (cap, D), qr (cap,), rows used]
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        return int(sum(e[0].nbytes + e[1].nbytes + e[2].nbytes + e[3].nbytes for e in self._levels.values()))

    def values(self, fn, pts: np.ndarray, keys: np.ndarray, level, cancel_poll=None) -> np.ndarray:
        """``fn(pts)`` for the nodes ``keys`` of ``level`` at ``pts``, through ``fn.query``/``fn.at``."""
        with self._lock:
            e = self._levels.get(level)
            rows = _fk.lookup(e[0], e[1], keys) if e is not None else np.full(len(keys), np.nan)
            miss = np.isnan(rows)
            n_miss = int(miss.sum())
            if n_miss < len(keys):
                hit = np.flatnonzero(~miss)
                idx = rows[hit].astype(np.int64)
                qu = np.empty((len(keys), e[2].shape[1]))
                qr = np.empty(len(keys))
                qu[hit] = e[2][idx]
                qr[hit] = e[3][idx]
        if n_miss == len(keys):
            qu, qr = fn.query(pts)
            self._keep(level, keys, qu, qr)
        elif n_miss:
            m = np.flatnonzero(miss)
            mu, mr = fn.query(pts[m])
            qu[m] = mu
            qr[m] = mr
            self._keep(level, keys[m], mu, mr)
        self.hits += len(keys) - n_miss
        self.misses += n_miss
        return fn.at(pts, qu, qr, cancel_poll=cancel_poll)

    def _keep(self, level, keys: np.ndarray, qu: np.ndarray, qr: np.ndarray) -> None:
        with self._lock:
            e = self._levels.get(level)
            used = 0 if e is None else e[4]
            need = used + len(keys)
            cap = max(1024, 1 << int(need - 1).bit_length())
            row_bytes = 8 * (qu.shape[1] + 1) + 32  # the rows and two table slots at a load of 1/2
            if cap * row_bytes > self.max_bytes:
                return
            others = sum(o[0].nbytes + o[1].nbytes + o[2].nbytes + o[3].nbytes
                         for lv, o in self._levels.items() if lv != level)
            for lv in list(self._levels):
                if others + cap * row_bytes <= self.max_bytes:
                    break
                if lv != level:
                    o = self._levels.pop(lv)
                    others -= o[0].nbytes + o[1].nbytes + o[2].nbytes + o[3].nbytes
            if others + cap * row_bytes > self.max_bytes:
                return
            if e is None:
                tk, tv = _fk.new_table(cap)
                e = [tk, tv, np.empty((cap, qu.shape[1])), np.empty(cap), 0]
                self._levels[level] = e
            elif len(e[3]) < need:
                e[2] = np.concatenate([e[2][:used], np.empty((cap - used, qu.shape[1]))])
                e[3] = np.concatenate([e[3][:used], np.empty(cap - used)])
            e[0], e[1] = _fk.grow(e[0], e[1], need)
            e[2][used:need] = qu
            e[3][used:need] = qr
            _fk.insert(e[0], e[1], np.ascontiguousarray(keys, dtype=np.int64),
                       np.arange(used, need, dtype=np.float64))
            e[4] = need
