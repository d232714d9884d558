"""Stage 4: fit the kernel weights to the labelled constraints.

The fitted function is ``f(a) = sum_j alpha_j K(a, c_j)`` over centres ``c_j``. With ``N``
constraints ``(a_i, y_i)`` and regularisation ``lam`` (per constraint), it minimises::

    (1/N) sum_i (f(a_i) - y_i)^2 + lam * ||f||_K^2

* When every constraint can be a centre (``N <= max_centres``), this is the exact kernel ridge
  regression ``(G + N lam I) alpha = y``, solved by Cholesky in float64 (:func:`solve_dense`).
* Otherwise ``M = max_centres`` constraints are chosen as Nystrom centres and the normal equations
  are solved by conjugate gradient with Falkon's preconditioner (Rudi, Carratino and Rosasco,
  NeurIPS 2017) (:func:`solve_falkon`). Memory is O(M^2 + N), never O(N^2): the products with the
  N x M kernel matrix are recomputed in fused loops.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..kernel.engines import Engine
from ..kernel.neural_spline import homogeneous, split_unit
from . import blocked_linalg as linalg

CancelPoll = Optional[Callable[[], None]]
Step = Optional[Callable[[float], None]]


@dataclass
class SolveInfo:
    """What the solver did.

    Attributes
    ----------
    method : str
        ``"dense"`` or ``"falkon"``.
    constraints : int
        Number of constraints N.
    centres : int
        Number of centres M.
    iterations : int
        Conjugate-gradient iterations (0 for the dense solve).
    residual : float
        Relative residual of the last iteration (0 for the dense solve).
    jitter : float
        Diagonal added to ``K_MM`` to factor it (Falkon only).
    """

    method: str
    constraints: int
    centres: int
    iterations: int = 0
    residual: float = 0.0
    jitter: float = 0.0


@dataclass
class KernelFunction:
    """``f(x) = sum_j alpha_j K([x : phi(x) : 1], c_j)``, evaluated by ``engine``.

    Attributes
    ----------
    centres : (M, D) float64
        Homogeneous centres.
    alpha : (M,) float64
        Weights.
    engine : Engine
    features : callable or None
        ``phi``: unit-box points (N, 3) -> features (N, d); ``None`` for Neural Splines.
    """

    centres: np.ndarray
    alpha: np.ndarray
    engine: Engine
    features: Callable[[np.ndarray], np.ndarray] | None = None

    def __post_init__(self):
        self._cu, self._cr = split_unit(self.centres)

    def __call__(self, x: np.ndarray, cancel_poll: CancelPoll = None) -> np.ndarray:
        """Values at unit-box points ``x`` (N, 3): (N,) float64."""
        return self.at(x, *self.query(x), cancel_poll=cancel_poll)

    def query(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The query side of ``x`` (N, 3), which does not depend on the weights: unit homogeneous
        vectors ``[x : phi(x) : 1] / |...|`` (N, D) and their norms (N,). Row by row: the rows of a
        subset of ``x`` are the same to the bit (``nkf_model.pipeline.fitted`` keeps them per grid node)."""
        phi = None if self.features is None else self.features(x)
        return split_unit(homogeneous(x, phi))

    def at(self, x: np.ndarray, qu: np.ndarray, qr: np.ndarray, cancel_poll: CancelPoll = None) -> np.ndarray:
        """Values at ``x`` from its :meth:`query` (``qu``, ``qr``): the same as ``self(x)``."""
        return self.engine.kernel_sum(qu, qr, self._cu, self._cr, self.alpha, cancel_poll)


def solve_dense(a: np.ndarray, y: np.ndarray, lam: float, engine: Engine, cancel_poll: CancelPoll = None,
                keep_gram: bool = False):
    """Exact solve of ``(G + N lam I) alpha = y``.

    Parameters
    ----------
    a : (N, D) float64
        Homogeneous constraint points, which are also the centres.
    y : (N,) float64
        Target values.
    lam : float
        Regularisation per constraint (>= 0).

    keep_gram : bool
        Also return the Gram matrix ``G`` (N, N) float64 without ``N lam`` and jitter on its
        diagonal, for :mod:`nkf_model.fit.refit` (a new lambda without a new Gram matrix).

    Returns
    -------
    alpha : (N,) float64
    info : SolveInfo
    gram : (N, N) float64, only with ``keep_gram``
    """
    u, r = split_unit(a)
    n = len(a)
    G = engine.gram(u, r, n * lam, cancel_poll=cancel_poll)
    if cancel_poll is not None:
        cancel_poll()
    jitter = 0.0
    while True:
        try:
            L = linalg.cholesky(G, cancel_poll=cancel_poll)
            break
        except linalg.NotPositiveDefinite:
            # Exactly repeated constraints, or lam = 0 with a numerically singular Gram matrix.
            step = 1e-13 * float(np.trace(G)) / n if jitter == 0.0 else 9.0 * jitter
            G[np.diag_indices(n)] += step
            jitter += step
    alpha = linalg.solve_lower(L, linalg.solve_lower(L, y), transpose=True)
    if keep_gram:
        del L
        G[np.diag_indices(n)] -= n * lam + jitter  # the factorisation worked on a copy
        return alpha, SolveInfo("dense", n, n, jitter=jitter), G
    return alpha, SolveInfo("dense", n, n, jitter=jitter)


def solve_falkon(
    a: np.ndarray,
    y: np.ndarray,
    centre_index: np.ndarray,
    lam: float,
    engine: Engine,
    *,
    max_iter: int = 200,
    tol: float = 1e-9,
    cancel_poll: CancelPoll = None,
    step: Step = None,
):
    """Nystrom kernel ridge regression by Falkon's preconditioned conjugate gradient.

    Parameters
    ----------
    a : (N, D) float64
        Homogeneous constraint points.
    y : (N,) float64
        Target values.
    centre_index : (M,) int
        Rows of ``a`` used as centres.
    lam : float
        Regularisation per constraint (>= 0).
    max_iter, tol :
        CG stops after ``max_iter`` iterations or when the preconditioned residual falls below
        ``tol`` times its initial value.
    check : callable
        Raises to cancel; called between blocks of work.
    step : callable
        ``step(fraction)`` progress within this solve.

    Returns
    -------
    alpha : (M,) float64
        Weights of the centres ``a[centre_index]``.
    info : SolveInfo
    """
    n = len(a)
    xu, xr = split_unit(a)
    cu, cr = xu[centre_index], xr[centre_index]
    m = len(centre_index)
    kmm = engine.kernel_matrix(cu, cr, cu, cr, cancel_poll=cancel_poll)
    if cancel_poll is not None:
        cancel_poll()
    # T = chol(K_MM + jitter I) (here lower: K_MM = L L^T and Falkon's T = L^T). The factorisation
    # overwrites K_MM; in the rare case that the jitter is too small, K_MM is computed again.
    base = 1e-14 * float(np.trace(kmm)) / m
    jitter = base
    while True:
        kmm[np.diag_indices(m)] += jitter
        try:
            L = linalg.cholesky(kmm, cancel_poll=cancel_poll, overwrite=True)
            break
        except linalg.NotPositiveDefinite:
            jitter *= 10.0
            kmm = engine.kernel_matrix(cu, cr, cu, cr, cancel_poll=cancel_poll)
    del kmm
    if step is not None:
        step(0.2)
    # A = chol(T T^T / M + lam I) = chol(L^T L / M + lam I).
    S = linalg.gram_of_factor(L, cancel_poll=cancel_poll, scale=1.0 / m)
    S[np.diag_indices(m)] += max(lam, 1e-15)
    if cancel_poll is not None:
        cancel_poll()
    La = linalg.cholesky(S, cancel_poll=cancel_poll, overwrite=True)
    del S
    if step is not None:
        step(0.4)

    def knm_normal(u, v):
        return engine.normal_product(xu, xr, cu, cr, u, v, cancel_poll=cancel_poll)

    def precond_apply(beta):  # B beta = T^{-1} A^{-1} beta
        return linalg.solve_lower(L, linalg.solve_lower(La, beta, transpose=True), transpose=True)

    def op(beta):
        v = linalg.solve_lower(La, beta, transpose=True)
        c = knm_normal(linalg.solve_lower(L, v, transpose=True), np.zeros(n)) / n
        return linalg.solve_lower(La, linalg.solve_lower(L, c) + lam * v)

    rhs = linalg.solve_lower(La, linalg.solve_lower(L, knm_normal(np.zeros(m), y / n)))
    beta = np.zeros(m)
    res = rhs.copy()
    p = res.copy()
    rr = float(res @ res)
    r0 = np.sqrt(rr) if rr > 0 else 1.0
    it = 0
    rel = 0.0
    for it in range(1, max_iter + 1):
        ap = op(p)
        alpha_cg = rr / float(p @ ap)
        beta += alpha_cg * p
        res -= alpha_cg * ap
        rr_new = float(res @ res)
        rel = np.sqrt(rr_new) / r0
        if step is not None:
            step(0.4 + 0.6 * min(1.0, np.log(max(rel, tol)) / np.log(tol)))
        if rel < tol:
            break
        p = res + (rr_new / rr) * p
        rr = rr_new
    alpha = precond_apply(beta)
    return alpha, SolveInfo("falkon", n, m, iterations=it, residual=float(rel), jitter=jitter)
