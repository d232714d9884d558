"""Compiled bookkeeping of the coarse-to-fine evaluation (:mod:`nkf_model.surface.evaluate`).

One finer level is filled by a flood fill over coarse "parent" cells: each parent's 27 child nodes
are looked up or scheduled for evaluation, then the child cells that change sign are collected, and
the parents that the fine surface runs into are queued. These loops do that with open-addressing
hash tables (int64 keys, -1 for empty) instead of sorting the growing key arrays with numpy after
every step: the function evaluations and everything else stay in Python.

Keys are those of :func:`nkf_model.surface.evaluate.node_keys` and :func:`nkf_model.surface.evaluate.cell_keys`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_OPTS = dict(nogil=True, cache=True)
_MULT = np.uint64(0x9E3779B97F4A7C15)


def new_table(capacity: int):
    """Empty table with room for about ``capacity`` keys: (keys int64, values float64)."""
    cap = 1 << max(10, int(2 * capacity - 1).bit_length())
    return np.full(cap, -1, dtype=np.int64), np.full(cap, np.nan)


@nb.njit(inline="always", **_OPTS)
def _home(key, mask):
    return np.int64((np.uint64(key) * _MULT) >> np.uint64(17)) & mask


@nb.njit(**_OPTS)
def _find(keys, key):
    """Slot of ``key``, or -(slot + 1) of the empty slot where it would go."""
    mask = keys.shape[0] - 1
    s = _home(key, mask)
    while True:
        k = keys[s]
        if k == key:
            return s
        if k == -1:
            return -(s + 1)
        s = (s + 1) & mask


@nb.njit(**_OPTS)
def grow(keys, vals, need):
    """The same table with room for ``need`` keys at a load of at most one half."""
    used = 0
    for k in keys:
        if k != -1:
            used += 1
    cap = keys.shape[0]
    if 2 * (used + need) <= cap:
        return keys, vals
    while 2 * (used + need) > cap:
        cap *= 2
    nk = np.full(cap, -1, dtype=np.int64)
    nv = np.full(cap, np.nan)
    for s in range(keys.shape[0]):
        if keys[s] != -1:
            t = -_find(nk, keys[s]) - 1
            nk[t] = keys[s]
            nv[t] = vals[s]
    return nk, nv


@nb.njit(**_OPTS)
def gather(frontier, r, keys, vals, prev_keys, prev_vals, r_prev, done_keys):
    """Slots of the 27 child nodes of each parent cell in ``frontier`` (P, 3) on the ``r``-cell grid.

    Nodes seen before keep their slot; new even nodes take their value from the previous level's
    table ``prev_keys``/``prev_vals`` when it has them; the others are inserted with NaN and
    returned for evaluation. The frontier's parents are added to the set ``done_keys``. The tables
    must have room (see :func:`grow`).

    Returns
    -------
    slots : (P, 27) int64
    todo_ijk : (M, 3) int64
        Nodes to evaluate, each once.
    todo_slots : (M,) int64
    """
    n = r + 1
    p = frontier.shape[0]
    slots = np.empty((p, 27), dtype=np.int64)
    todo_ijk = np.empty((27 * p, 3), dtype=np.int64)
    todo_slots = np.empty(27 * p, dtype=np.int64)
    m = 0
    np1 = r_prev + 1
    for q in range(p):
        pi, pj, pk = frontier[q, 0], frontier[q, 1], frontier[q, 2]
        d = _find(done_keys, (pi * r_prev + pj) * r_prev + pk)
        if d < 0:
            done_keys[-d - 1] = (pi * r_prev + pj) * r_prev + pk
        c = 0
        for a in range(3):
            for b in range(3):
                for e in range(3):
                    i, j, k = 2 * pi + a, 2 * pj + b, 2 * pk + e
                    key = (i * n + j) * n + k
                    s = _find(keys, key)
                    if s < 0:
                        s = -s - 1
                        keys[s] = key
                        value = np.nan
                        if a % 2 == 0 and b % 2 == 0 and e % 2 == 0:
                            t = _find(prev_keys, ((i // 2) * np1 + j // 2) * np1 + k // 2)
                            if t >= 0:
                                value = prev_vals[t]
                        vals[s] = value
                        if np.isnan(value):
                            todo_ijk[m, 0] = i
                            todo_ijk[m, 1] = j
                            todo_ijk[m, 2] = k
                            todo_slots[m] = s
                            m += 1
                    slots[q, c] = s
                    c += 1
    return slots, todo_ijk[:m], todo_slots[:m]


@nb.njit(**_OPTS)
def advance(frontier, slots, vals, r_prev, done_keys):
    """Crossing child cells of the frontier's parents, and the parents the surface runs into next.

    A child cell crosses when its 8 corners are not all of one sign (negative or not). The fine
    surface leaves a crossing child through an outer face whose 4 corners change sign; the parent
    across that face is queued unless it is in ``done_keys`` (it is added there at once, so each
    parent is queued only once). ``done_keys`` must have room for the new parents (see :func:`grow`).

    Returns
    -------
    cells : (C, 3) int64
        Crossing cells of the finer grid.
    nxt : (K, 3) int64
        Parent cells for the next step.
    """
    p = frontier.shape[0]
    cells = np.empty((8 * p, 3), dtype=np.int64)
    nxt = np.empty((6 * 8 * p, 3), dtype=np.int64)
    nc = 0
    nn = 0
    neg = np.empty((3, 3, 3), dtype=np.bool_)
    ch = np.empty(3, dtype=np.int64)
    ix = np.empty(3, dtype=np.int64)
    nbr = np.empty(3, dtype=np.int64)
    for q in range(p):
        c = 0
        for a in range(3):
            for b in range(3):
                for e in range(3):
                    neg[a, b, e] = vals[slots[q, c]] < 0.0
                    c += 1
        for a in range(2):
            for b in range(2):
                for e in range(2):
                    cnt = 0
                    for da in range(2):
                        for db in range(2):
                            for de in range(2):
                                if neg[a + da, b + db, e + de]:
                                    cnt += 1
                    if cnt == 0 or cnt == 8:
                        continue
                    cells[nc, 0] = 2 * frontier[q, 0] + a
                    cells[nc, 1] = 2 * frontier[q, 1] + b
                    cells[nc, 2] = 2 * frontier[q, 2] + e
                    nc += 1
                    ch[0] = a
                    ch[1] = b
                    ch[2] = e
                    for axis in range(3):
                        side = ch[axis]
                        o1 = 0 if axis != 0 else 1
                        o2 = 2 if axis != 2 else 1
                        fc = 0
                        for d1 in range(2):
                            for d2 in range(2):
                                ix[axis] = 2 * side
                                ix[o1] = ch[o1] + d1
                                ix[o2] = ch[o2] + d2
                                if neg[ix[0], ix[1], ix[2]]:
                                    fc += 1
                        if fc == 0 or fc == 4:
                            continue
                        nbr[0] = frontier[q, 0]
                        nbr[1] = frontier[q, 1]
                        nbr[2] = frontier[q, 2]
                        nbr[axis] += 1 if side == 1 else -1
                        if nbr[axis] < 0 or nbr[axis] >= r_prev:
                            continue
                        key = (nbr[0] * r_prev + nbr[1]) * r_prev + nbr[2]
                        t = _find(done_keys, key)
                        if t >= 0:
                            continue
                        done_keys[-t - 1] = key
                        nxt[nn, 0] = nbr[0]
                        nxt[nn, 1] = nbr[1]
                        nxt[nn, 2] = nbr[2]
                        nn += 1
    return cells[:nc], nxt[:nn]


@nb.njit(**_OPTS)
def insert(keys, vals, new_keys, new_vals):
    """Put ``new_keys`` (K,) with ``new_vals`` (K,) into the table (it must have room)."""
    for m in range(new_keys.shape[0]):
        s = _find(keys, new_keys[m])
        if s < 0:
            s = -s - 1
            keys[s] = new_keys[m]
        vals[s] = new_vals[m]


@nb.njit(**_OPTS)
def lookup(keys, vals, query):
    """Values (N,) of the keys ``query`` (N,); NaN for keys not in the table."""
    out = np.empty(query.shape[0])
    for m in range(query.shape[0]):
        s = _find(keys, query[m])
        out[m] = vals[s] if s >= 0 else np.nan
    return out
