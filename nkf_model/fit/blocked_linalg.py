"""Dense float64 factorisations cut into blocks, so that a cancel request is seen between blocks.

A single LAPACK call on a 5,000 x 5,000 matrix runs for about a second on this project's 2-core
reference CPU; these left-looking blocked versions do the same arithmetic as BLAS-3 products on
panels of :data:`BLOCK` columns and call ``check()`` after each panel.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg import lapack, solve_triangular

BLOCK = 1024
# Below this size one LAPACK call takes under about 0.1 s and is not worth splitting.
SINGLE_CALL = 2500
# Floating-point operations between two calls of ``cancel_poll`` (about 0.05 s on one core of the reference
# CPU, so that a cancel request is seen within 0.5 s even on a busy machine).
FLOPS_PER_CHECK = 1.5e9


class NotPositiveDefinite(np.linalg.LinAlgError):
    """The matrix handed to :func:`cholesky` is not numerically positive definite."""


def cholesky(
    a: np.ndarray, cancel_poll: Callable[[], None] | None = None, block: int = BLOCK, overwrite: bool = False
) -> np.ndarray:
    """Lower Cholesky factor ``L`` with ``a = L L^T``, computed in place of a copy of ``a`` (or of
    ``a`` itself with ``overwrite``, when it is a C-contiguous float64 array).

    Only the lower triangle of ``a`` (n, n) float64 is read. Raises :class:`NotPositiveDefinite`.
    """
    n = a.shape[0]
    if n <= SINGLE_CALL:
        L, info = lapack.dpotrf(np.asarray(a, dtype=np.float64), lower=1, clean=1)
        if info != 0:
            raise NotPositiveDefinite(f"leading minor {info} is not positive definite")
        if cancel_poll is not None:
            cancel_poll()
        return L
    own = overwrite and a.dtype == np.float64 and a.flags.c_contiguous
    L = a if own else np.array(a, dtype=np.float64, order="C", copy=True)
    if cancel_poll is not None:
        cancel_poll()
    for k in range(0, n, block):
        e = min(n, k + block)
        if k > 0:
            # Panel update with the finished columns: L[k:, k:e] -= L[k:, :k] @ L[k:e, :k]^T,
            # in row chunks so that cancellation is seen often.
            right = np.ascontiguousarray(L[k:e, :k].T)
            rows = max(256, int(FLOPS_PER_CHECK / (2.0 * k * (e - k))))
            for r in range(k, n, rows):
                L[r : r + rows, k:e] -= L[r : r + rows, :k] @ right
                if cancel_poll is not None:
                    cancel_poll()
        d, info = lapack.dpotrf(L[k:e, k:e], lower=1, clean=1)
        if info != 0:
            raise NotPositiveDefinite(f"leading minor {k + info} is not positive definite")
        L[k:e, k:e] = d
        if e < n:
            # The panel below the diagonal block, in row chunks too (a 5,000 x 1,024 panel is
            # 5 GFlop: more than a second on a busy machine).
            rows = max(256, int(FLOPS_PER_CHECK / float((e - k) * (e - k))))
            for r in range(e, n, rows):
                L[r : r + rows, k:e] = solve_triangular(d, L[r : r + rows, k:e].T, lower=True, check_finite=False).T
                if cancel_poll is not None:
                    cancel_poll()
            L[k:e, e:] = 0.0
        if cancel_poll is not None:
            cancel_poll()
    return L


def gram_of_factor(
    L: np.ndarray, cancel_poll: Callable[[], None] | None = None, block: int = BLOCK, scale: float = 1.0
) -> np.ndarray:
    """``S = scale * L^T L`` for lower-triangular ``L`` (n, n); only the lower triangle of ``S`` is
    filled."""
    n = L.shape[0]
    S = np.zeros((n, n))  # calloc: pages are zeroed lazily
    for i in range(0, n, block):
        e = min(n, i + block)
        # S[i:e, :e] = L[i:, i:e]^T L[i:, :e]  (L[k, i:e] = 0 for k < i)
        left = L[i:, i:e].T  # a strided view: BLAS reads it in place
        cols = max(64, int(FLOPS_PER_CHECK / (2.0 * (e - i) * (n - i))))
        for c in range(0, e, cols):
            S[i:e, c : min(e, c + cols)] = left @ L[i:, c : min(e, c + cols)]
            if scale != 1.0:
                S[i:e, c : min(e, c + cols)] *= scale
            if cancel_poll is not None:
                cancel_poll()
    return S


def solve_lower(L: np.ndarray, b: np.ndarray, transpose: bool = False) -> np.ndarray:
    """Solve ``L x = b`` (or ``L^T x = b`` when ``transpose``) for lower-triangular ``L``."""
    return solve_triangular(L, b, lower=True, trans="T" if transpose else "N", check_finite=False)
