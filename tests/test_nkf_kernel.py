"""The learned kernel's differentiable fit and its fused CPU loops."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nkf_model.kernel import _numba_kernels as nk
from nkf_model.kernel.engines import cpu_engine
from nkf_model.kernel.neural_spline import homogeneous, ns_kernel, ns_kernel_torch, split_unit
from nkf_model.train.differentiable_fit import fit_and_evaluate, kernel_matrix, spd_solve


def _homog(n, d, seed, scale=0.15):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, size=(n, 3))
    phi = rng.normal(scale=scale, size=(n, d))
    return homogeneous(x, phi)


def test_zero_features_give_the_neural_spline_kernel():
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.5, 0.5, size=(40, 3))
    z = rng.uniform(-0.5, 0.5, size=(30, 3))
    plain = ns_kernel(homogeneous(x), homogeneous(z))
    zero = ns_kernel(homogeneous(x, np.zeros((40, 8))), homogeneous(z, np.zeros((30, 8))))
    np.testing.assert_allclose(zero, plain, rtol=1e-14, atol=1e-14)
    # ... and through the fused 12-D loops of the engine, against its 4-D loops.
    e = cpu_engine()
    zx, zz = homogeneous(x, np.zeros((40, 8))), homogeneous(z, np.zeros((30, 8)))
    k12 = e.kernel_matrix(*split_unit(zx), *split_unit(zz))
    k4 = e.kernel_matrix(*split_unit(homogeneous(x)), *split_unit(homogeneous(z)))
    np.testing.assert_allclose(k12, k4, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("acute", [False, True])
def test_fused_12d_loops_match_the_generic_loops(acute):
    a = _homog(300, 8, 1)
    b = _homog(257, 8, 2)
    au, _ = split_unit(a)
    bu, _ = split_unit(b)
    assert float(au[:, -1].min()) >= nk.ACUTE_MIN_LAST  # small features: the fast angle term is valid
    bt = np.ascontiguousarray(bu.T)
    beta = np.random.default_rng(3).normal(size=len(bu))
    ref = nk.gsum(au, bt, beta)
    np.testing.assert_allclose(nk.gsum12(au, bt, beta, acute), ref, rtol=1e-12, atol=1e-12)
    g_ref = ns_kernel(au, bu) * np.pi  # unit vectors: K = g / pi
    np.testing.assert_allclose(nk.gmatrix(au, bt, acute), g_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("acute", [False, True])
def test_fused_12d_sum_at_the_centres_themselves(acute):
    """gsum12 computes |q - c|^2 as 2 - 2 q.c: at a query that is a centre (d2 = 0, the worst case)
    it may differ from the difference form by the bound its docstring gives, no more."""
    b = _homog(400, 8, 5)
    bu, _ = split_unit(b)
    bt = np.ascontiguousarray(bu.T)
    beta = np.random.default_rng(6).normal(size=len(bu))
    ref = nk.gsum(bu, bt, beta)
    err = np.abs(nk.gsum12(bu, bt, beta, acute) - ref).max()
    assert err <= 3e-8 * np.abs(beta).sum()
    # ... and a query a little off each centre is as accurate as anywhere
    q = bu + 1e-3 * np.random.default_rng(7).normal(size=bu.shape)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(nk.gsum12(q, bt, beta, acute), nk.gsum(q, bt, beta), rtol=1e-11,
                               atol=1e-11 * np.abs(beta).sum())


def test_kernel_matrix_and_its_gradient_match_autograd():
    a = torch.tensor(_homog(25, 8, 4, scale=0.3), requires_grad=True)
    b = torch.tensor(_homog(18, 8, 5, scale=0.3), requires_grad=True)
    w = torch.randn(25, 18, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    k1, k2 = kernel_matrix(a, b), ns_kernel_torch(a, b)
    torch.testing.assert_close(k1, k2, rtol=1e-13, atol=1e-13)
    g1 = torch.autograd.grad((k1 * w).sum(), (a, b))
    g2 = torch.autograd.grad((k2 * w).sum(), (a, b))
    for x, y in zip(g1, g2):
        torch.testing.assert_close(x, y, rtol=1e-11, atol=1e-11)
    # The Gram matrix: a appears on both sides, and its diagonal pairs a point with itself.
    wg = torch.randn(25, 25, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    g1 = torch.autograd.grad((kernel_matrix(a, a) * wg).sum(), a)[0]
    g2 = torch.autograd.grad((ns_kernel_torch(a, a) * wg).sum(), a)[0]
    torch.testing.assert_close(g1, g2, rtol=1e-11, atol=1e-11)


def test_gradients_through_the_solve_match_finite_differences():
    a = torch.tensor(_homog(12, 3, 6, scale=0.3), requires_grad=True)
    q = torch.tensor(_homog(7, 3, 7, scale=0.3), requires_grad=True)
    y = torch.tensor(np.r_[np.ones(6), -np.ones(6)])
    assert torch.autograd.gradcheck(lambda a, q: fit_and_evaluate(a, y, 1e-4, q), (a, q), eps=1e-6, atol=1e-6)


def test_spd_solve_solves_and_adds_jitter_when_singular():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(6, 6))
    A = torch.tensor(m @ m.T + 6 * np.eye(6))
    y = torch.tensor(rng.normal(size=6))
    torch.testing.assert_close(A @ spd_solve(A, y), y, rtol=1e-12, atol=1e-12)
    v = torch.tensor(rng.normal(size=(6, 1)))
    singular = v @ v.T  # rank one: not positive definite
    out = spd_solve(singular, y)
    assert bool(torch.isfinite(out).all())
