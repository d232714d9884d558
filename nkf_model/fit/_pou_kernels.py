"""Compiled loops for the partition-of-unity solver (see :mod:`nkf_model.fit.partition_of_unity`).

Patches sit at the nodes of a regular grid with spacing ``h`` starting at ``lo`` (``dims`` nodes per
axis, flat index ``(i * dims + j) * dims + k``). A point in the cell with lower corner node
``(i, j, k)`` and fractional position ``t`` in it has weight ``s(1 - t)`` or ``s(t)`` per axis
towards the cell's 8 corner patches, with ``s(u) = 3u^2 - 2u^3``; since ``s(u) + s(1 - u) = 1`` the
weights sum to one everywhere (a C1 partition of unity).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..kernel._numba_kernels import _g, _sum4

_OPTS = dict(nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz"})


@nb.njit(inline="always")
def _smooth(u):
    return u * u * (3.0 - 2.0 * u)


@nb.njit(inline="always")
def _cell(x0, x1, x2, lo, h, dims):
    """Lower corner node (ix, iy, iz) of the grid cell that holds (x0, x1, x2), clamped to the grid,
    and the fractional position (tx, ty, tz) in it, each in [0, 1]."""
    fx = (x0 - lo) / h
    fy = (x1 - lo) / h
    fz = (x2 - lo) / h
    ix = min(max(int(math.floor(fx)), 0), dims - 2)
    iy = min(max(int(math.floor(fy)), 0), dims - 2)
    iz = min(max(int(math.floor(fz)), 0), dims - 2)
    return ix, iy, iz, min(max(fx - ix, 0.0), 1.0), min(max(fy - iy, 0.0), 1.0), min(max(fz - iz, 0.0), 1.0)


@nb.njit(inline="always")
def _corner(ix, iy, iz, tx, ty, tz, dims, a, b, c):
    """Flat patch index and weight of the corner ``(ix + a, iy + b, iz + c)`` (a, b, c each 0 or 1) of
    the cell that :func:`_cell` gives, at the fractional position (tx, ty, tz).

    Both callers step a, b, c in three nested loops (corner ``q = 4a + 2b + c``); that loop shape is
    kept on purpose: a single ``for q in range(8)`` changes how LLVM compiles :func:`pou_sum` under
    fastmath and moves its results in the last bits."""
    wx = _smooth(tx) if a == 1 else _smooth(1.0 - tx)
    wy = _smooth(ty) if b == 1 else _smooth(1.0 - ty)
    wz = _smooth(tz) if c == 1 else _smooth(1.0 - tz)
    return ((ix + a) * dims + (iy + b)) * dims + (iz + c), wx * wy * wz


@nb.njit(**_OPTS)
def gram_general(u, r, diag):  # pragma: no cover - compiled
    """Kernel matrix ``r_i r_j g(|u_i - u_j|^2) / pi`` (n, n) of unit vectors ``u`` (n, D), plus
    ``diag`` on the diagonal. Serial: the caller runs several patches in parallel threads."""
    n, d = u.shape
    G = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(d):
                t = u[i, k] - u[j, k]
                s += t * t
            v = _g(s) * r[i] * r[j] / math.pi
            G[i, j] = v
            G[j, i] = v
        G[i, i] += diag
    return G


@nb.njit(inline="always", **_OPTS)
def _sum12(qu, i, cu, beta, j0, j1):
    """sum_j beta[j] g(|qu[i] - c[j]|^2) over centres j0..j1 of 12-D unit vectors (``cu`` by columns,
    (12, C)): the learned kernel's ``[x : phi : 1]``. One pass over the centres that LLVM vectorises;
    the generic loop over a run-time dimension in :func:`pou_sum` did not (5x slower)."""
    q0 = qu[i, 0]
    q1 = qu[i, 1]
    q2 = qu[i, 2]
    q3 = qu[i, 3]
    q4 = qu[i, 4]
    q5 = qu[i, 5]
    q6 = qu[i, 6]
    q7 = qu[i, 7]
    q8 = qu[i, 8]
    q9 = qu[i, 9]
    q10 = qu[i, 10]
    q11 = qu[i, 11]
    r0 = cu[0]
    r1 = cu[1]
    r2 = cu[2]
    r3 = cu[3]
    r4 = cu[4]
    r5 = cu[5]
    r6 = cu[6]
    r7 = cu[7]
    r8 = cu[8]
    r9 = cu[9]
    r10 = cu[10]
    r11 = cu[11]
    s = 0.0
    for j in range(j0, j1):
        t0 = q0 - r0[j]
        t1 = q1 - r1[j]
        t2 = q2 - r2[j]
        t3 = q3 - r3[j]
        t4 = q4 - r4[j]
        t5 = q5 - r5[j]
        t6 = q6 - r6[j]
        t7 = q7 - r7[j]
        t8 = q8 - r8[j]
        t9 = q9 - r9[j]
        t10 = q10 - r10[j]
        t11 = q11 - r11[j]
        d2 = (t0 * t0 + t1 * t1 + t2 * t2 + t3 * t3 + t4 * t4 + t5 * t5
              + t6 * t6 + t7 * t7 + t8 * t8 + t9 * t9 + t10 * t10 + t11 * t11)
        s += beta[j] * _g(d2)
    return s


@nb.njit(inline="always")
def _trilinear(grid, lo, step, x0, x1, x2):
    n = grid.shape[0] - 1
    f0 = min(max((x0 - lo) / step, 0.0), n - 1e-9)
    f1 = min(max((x1 - lo) / step, 0.0), n - 1e-9)
    f2 = min(max((x2 - lo) / step, 0.0), n - 1e-9)
    i = int(f0)
    j = int(f1)
    k = int(f2)
    a = f0 - i
    b = f1 - j
    c = f2 - k
    return (
        (1 - a) * ((1 - b) * ((1 - c) * grid[i, j, k] + c * grid[i, j, k + 1])
                   + b * ((1 - c) * grid[i, j + 1, k] + c * grid[i, j + 1, k + 1]))
        + a * ((1 - b) * ((1 - c) * grid[i + 1, j, k] + c * grid[i + 1, j, k + 1])
               + b * ((1 - c) * grid[i + 1, j + 1, k] + c * grid[i + 1, j + 1, k + 1]))
    )


@nb.njit(parallel=True, **_OPTS)
def pou_sum(x, qu, qr, lo, h, dims, start, count, cu, beta, f0, f0_lo, f0_step, acute):  # pragma: no cover
    """Blended value ``sum_p w_p(x) g_p(x)`` at each query.

    Parameters
    ----------
    x : (Nq, 3) float64
        Unit-box positions (they pick the patches and weights).
    qu, qr : (Nq, D) float64, (Nq,) float64
        Unit homogeneous vectors of the queries and their norms.
    lo, h : float
        Grid origin and spacing; ``dims`` nodes per axis.
    start, count : (dims^3,) int64
        Slice of each patch's centres in ``cu`` / ``beta``; ``count == 0`` means "no local fit",
        and ``f0`` stands in for it.
    cu : (D, C) float64
        Unit centres of all patches, by columns.
    beta : (C,) float64
        ``alpha_j * |c_j|`` of each centre.
    f0 : (G, G, G) float64
        The coarse global fit sampled on a regular grid from ``f0_lo`` with spacing ``f0_step``;
        interpolated trilinearly where a corner patch has no fit.
    acute : bool
        Every query and centre is a 4-D ``[x : 1]`` with ``|x| < 1`` (so the faster branch-free
        angle term of :func:`nkf_model.kernel._numba_kernels._g_acute` applies).
    """
    nq = x.shape[0]
    d = qu.shape[1]
    out = np.empty(nq)
    for i in nb.prange(nq):
        ix, iy, iz, tx, ty, tz = _cell(x[i, 0], x[i, 1], x[i, 2], lo, h, dims)
        total = 0.0
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    p, w = _corner(ix, iy, iz, tx, ty, tz, dims, a, b, c)
                    if w == 0.0:
                        continue
                    m = count[p]
                    if m == 0:
                        total += w * _trilinear(f0, f0_lo, f0_step, x[i, 0], x[i, 1], x[i, 2])
                        continue
                    s0 = start[p]
                    acc = 0.0
                    if d == 4:
                        acc = _sum4(qu[i, 0], qu[i, 1], qu[i, 2], qu[i, 3], cu[0], cu[1], cu[2], cu[3], beta,
                                    s0, s0 + m, acute)
                    elif d == 12:
                        acc = _sum12(qu, i, cu, beta, s0, s0 + m)
                    else:
                        for j in range(s0, s0 + m):
                            s = 0.0
                            for k in range(d):
                                t = qu[i, k] - cu[k, j]
                                s += t * t
                            acc += beta[j] * _g(s)
                    total += w * acc * qr[i] / math.pi
        out[i] = total
    return out


@nb.njit(**_OPTS)
def corner_weights(x, lo, h, dims):  # pragma: no cover - compiled
    """Patch indices (N, 8) int64 and weights (N, 8) float64 of each point's 8 corner patches."""
    n = x.shape[0]
    idx = np.empty((n, 8), dtype=np.int64)
    wts = np.empty((n, 8))
    for i in range(n):
        ix, iy, iz, tx, ty, tz = _cell(x[i, 0], x[i, 1], x[i, 2], lo, h, dims)
        q = 0
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    idx[i, q], wts[i, q] = _corner(ix, iy, iz, tx, ty, tz, dims, a, b, c)
                    q += 1
    return idx, wts


@nb.njit(parallel=True, **_OPTS)
def interpolate(grid, lo, step, x):  # pragma: no cover - compiled
    """Trilinear interpolation (N,) of a node grid (G, G, G) at points (N, 3)."""
    out = np.empty(x.shape[0])
    for i in nb.prange(x.shape[0]):
        out[i] = _trilinear(grid, lo, step, x[i, 0], x[i, 1], x[i, 2])
    return out


@nb.njit(parallel=True, **_OPTS)
def eigen_solve_all(q, q_off, e, b, r, v_off, m, floor, out_off, lam, out):  # pragma: no cover - compiled
    """Every patch's ``beta = r * Q ((Q^T y) / max(e + m lam, floor))`` from its eigendecomposition.

    Patch ``p`` has ``m[p]`` constraints; its eigenvectors ``Q`` (m, m), row-major, are
    ``q[q_off[p] : q_off[p] + m^2]``; its eigenvalues ``e``, ``b = Q^T y`` and norms ``r`` are at
    ``v_off[p] : v_off[p] + m`` of ``e``, ``b``, ``r``; the result goes to ``out[out_off[p] :][:m]``.
    """
    for p in nb.prange(m.shape[0]):
        n = m[p]
        qo = q_off[p]
        vo = v_off[p]
        shift = n * lam
        c = np.empty(n)
        for k in range(n):
            c[k] = b[vo + k] / max(e[vo + k] + shift, floor[p])
        oo = out_off[p]
        for i in range(n):
            s = 0.0
            row = qo + i * n
            for k in range(n):
                s += q[row + k] * c[k]
            out[oo + i] = s * r[vo + i]
    return out
