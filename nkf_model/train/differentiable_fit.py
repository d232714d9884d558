"""Differentiable kernel fit for training the learned kernel (PyTorch, float64).

The forward passes reuse the core's kernel: on the CPU the numba Gram rows of
:mod:`nkf_model.kernel._numba_kernels` (through :class:`nkf_model.kernel.engines.NumbaEngine`), on a GPU the
PyTorch formula of :func:`nkf_model.kernel.neural_spline.ns_kernel_torch`. On the CPU the backward pass is the
closed form of :mod:`nkf_model.train._numba_grad` (about 100x faster than autograd through the element-wise
formula); the solve's backward needs one more triangular solve with the forward's Cholesky factor,
not autograd through the factorisation.

Everything here is float64: a float32 Gram matrix flips the sign of the field near the surface.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..kernel.neural_spline import ns_kernel_torch, split_unit


class IllConditionedError(RuntimeError):
    """The regularised Gram matrix could not be factored even with jitter."""


def _engine():
    from ..kernel.engines import cpu_engine

    return cpu_engine()


class _KernelMatrixCPU(torch.autograd.Function):
    """``K(a_i, b_j)`` for float64 CPU tensors (N, D) and (M, D), with a fused backward."""

    @staticmethod
    def forward(ctx, a, b):
        an = a.detach().numpy()
        bn = b.detach().numpy()
        au, ar = split_unit(an)
        bu, br = split_unit(bn)
        k = _engine().kernel_matrix(au, ar, bu, br)
        ctx.np = (an, au, ar, bn, bu, br)
        return torch.from_numpy(k)

    @staticmethod
    def backward(ctx, w):
        from ._numba_grad import pair_terms

        an, au, ar, bn, bu, br = ctx.np
        q, r = pair_terms(au, np.ascontiguousarray(bu.T), np.ascontiguousarray(w.numpy(), dtype=np.float64))
        ga = gb = None
        if ctx.needs_input_grad[0]:
            ga = torch.from_numpy((au * (r @ br)[:, None] + q @ bn) / math.pi)
        if ctx.needs_input_grad[1]:
            gb = torch.from_numpy((bu * (r.T @ ar)[:, None] + q.T @ an) / math.pi)
        return ga, gb


def kernel_matrix(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Neural Spline kernel matrix ``K(a_i, b_j)`` (N, M) float64, differentiable in ``a`` and ``b``.

    Parameters
    ----------
    a : (N, D) float64 tensor
        Homogeneous inputs ``[x : phi(x) : 1]`` (possibly scaled by per-point weights).
    b : (M, D) float64 tensor
    """
    if a.device.type == "cpu":
        return _KernelMatrixCPU.apply(a, b)
    return ns_kernel_torch(a, b)


class _SPDSolve(torch.autograd.Function):
    """``A^{-1} y`` for a symmetric positive definite float64 matrix, by Cholesky."""

    @staticmethod
    def forward(ctx, A, y):
        n = A.shape[0]
        L, info = torch.linalg.cholesky_ex(A)
        jitter = 0.0
        tries = 0
        while int(info) != 0:
            tries += 1
            if tries > 6:
                raise IllConditionedError(f"Gram matrix of size {n} is not positive definite")
            step = 1e-12 * float(torch.diagonal(A).mean()) * 10.0 ** tries
            jitter += step
            L, info = torch.linalg.cholesky_ex(A + jitter * torch.eye(n, dtype=A.dtype, device=A.device))
        alpha = torch.cholesky_solve(y[:, None], L)[:, 0]
        ctx.save_for_backward(L, alpha)
        return alpha

    @staticmethod
    def backward(ctx, g_alpha):
        L, alpha = ctx.saved_tensors
        gbar = torch.cholesky_solve(g_alpha[:, None], L)[:, 0]
        g_a = -gbar[:, None] * alpha[None, :] if ctx.needs_input_grad[0] else None
        return g_a, gbar


def spd_solve(A: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Solve ``A x = y`` for symmetric positive definite ``A`` (N, N) float64; ``y`` (N,).

    Differentiable in both; adds diagonal jitter if the factorisation fails and raises
    :class:`IllConditionedError` if it still fails.
    """
    return _SPDSolve.apply(A, y)


def fit_and_evaluate(a: torch.Tensor, y: torch.Tensor, lam: float, queries: torch.Tensor):
    """Kernel ridge fit on constraints ``a`` and its values at ``queries``.

    Solves ``(G + N lam I) alpha = y`` with ``G = K(a, a)`` (as :func:`nkf_model.fit.solve.solve_dense`)
    and returns ``f(q) = sum_j alpha_j K(q, a_j)``.

    Parameters
    ----------
    a : (N, D) float64 tensor
        Homogeneous constraint points (also the centres).
    y : (N,) float64 tensor
        Targets (+1 outside, -1 inside).
    lam : float
        Regularisation per constraint.
    queries : (M, D) float64 tensor
        Homogeneous query points.

    Returns
    -------
    (M,) float64 tensor
    """
    n = a.shape[0]
    G = kernel_matrix(a, a)
    G = G + (n * lam) * torch.eye(n, dtype=G.dtype, device=G.device)
    alpha = spd_solve(G, y)
    return kernel_matrix(queries, a) @ alpha
