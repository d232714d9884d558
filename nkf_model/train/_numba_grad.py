"""Fused CPU loops for the gradient of the Neural Spline kernel matrix (training only), numba.

For homogeneous inputs ``a = r_a u`` and ``b = r_b v`` (unit vectors ``u``, ``v``) the kernel is
``K(a, b) = r_a r_b g(d2) / pi`` with ``d2 = |u - v|^2`` and ``g`` as in :mod:`nkf_model.kernel.neural_spline`.
With ``t`` the angle between ``a`` and ``b`` and ``h = cot t + 2 (pi - t)`` (``h = -2 dg/dd2``)::

    dK/da = r_b / pi * (g u + h (v - cos t u)),      v - cos t u = (v - u) + (d2 / 2) u

The second term is bounded (``h ~ 1/t`` and ``|v - cos t u| = sin t``) but its direction is
undefined at ``t = 0``; it is set to zero there (a point paired with itself), as in
:func:`nkf_model.kernel.neural_spline.ns_kernel_torch`.

Given the gradient ``W`` (N, M) of a loss with respect to the matrix ``K(a_i, b_j)``, the gradients
with respect to the inputs are sums over pairs. :func:`pair_terms` computes, per pair, the two
scalars from which BLAS products finish them (see :func:`nkf_model.train.differentiable_fit.kernel_matrix`)::

    Q_ij = W_ij h_ij
    R_ij = W_ij (g_ij + h_ij d2_ij / 2) - Q_ij
    dL/da = (u * (R @ r_b)[:, None] + Q @ b) / pi
    dL/db = (v * (R.T @ r_a)[:, None] + Q.T @ a) / pi
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..kernel._numba_kernels import _angle

PI = math.pi
_OPTS = dict(nogil=True, cache=True, fastmath={"contract"})


@nb.njit(parallel=True, **_OPTS)
def pair_terms(au, bt, w):
    """Per-pair gradient scalars ``Q`` and ``R`` (both (N, M) float64) for ``W = w``.

    ``au`` (N, D) are unit vectors, ``bt`` (D, M) the other unit vectors transposed; ``w`` (N, M)
    is dL/dK.
    """
    n = au.shape[0]
    m = bt.shape[1]
    dim = au.shape[1]
    q_out = np.empty((n, m))
    r_out = np.empty((n, m))
    for i in nb.prange(n):
        d2 = r_out[i]  # row buffer, overwritten below
        for j in range(m):
            d2[j] = 0.0
        for k in range(dim):
            ak = au[i, k]
            row = bt[k]
            for j in range(m):
                t = ak - row[j]
                d2[j] += t * t
        for j in range(m):
            dd = min(max(d2[j], 0.0), 4.0)
            ang = _angle(dd)
            s = 0.5 * math.sqrt(dd * (4.0 - dd))  # sin t
            c = 1.0 - 0.5 * dd  # cos t
            g = s + 2.0 * (PI - ang) * c
            h = c / s + 2.0 * (PI - ang) if s > 0.0 else 0.0
            wij = w[i, j]
            qv = wij * h
            q_out[i, j] = qv
            r_out[i, j] = wij * (g + 0.5 * h * dd) - qv
    return q_out, r_out
