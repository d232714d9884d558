"""The Neural Spline kernel: every implementation against a direct transcription of the formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nkf_model.kernel.engines import NumbaEngine, TorchEngine
from nkf_model.kernel.neural_spline import angle_term, homogeneous, ns_kernel, ns_kernel_torch, split_unit


def textbook(a, b):
    """K(a, b) = |a||b|/pi (sin t + 2 (pi - t) cos t), t = arccos of the cosine (float64, loops)."""
    out = np.empty((len(a), len(b)))
    for i, ai in enumerate(a):
        for j, bj in enumerate(b):
            na, nb = np.linalg.norm(ai), np.linalg.norm(bj)
            c = np.clip(ai @ bj / (na * nb), -1.0, 1.0)
            t = math.acos(c)
            out[i, j] = na * nb / math.pi * (math.sin(t) + 2 * (math.pi - t) * math.cos(t))
    return out


def kahan_angle(a, b):
    """Kahan's formula with 40-digit arithmetic, as the reference for nearly parallel vectors."""
    import mpmath

    mpmath.mp.dps = 40
    a = [mpmath.mpf(float(x)) for x in a]
    b = [mpmath.mpf(float(x)) for x in b]
    na = mpmath.sqrt(sum(x * x for x in a))
    nb = mpmath.sqrt(sum(x * x for x in b))
    d = mpmath.sqrt(sum((nb * x - na * y) ** 2 for x, y in zip(a, b)))
    s = mpmath.sqrt(sum((nb * x + na * y) ** 2 for x, y in zip(a, b)))
    return 2 * mpmath.atan2(d, s), na, nb


@pytest.fixture(scope="module")
def pairs():
    rng = np.random.default_rng(0)
    a = homogeneous(rng.uniform(-0.5, 0.5, size=(40, 3)))
    b = homogeneous(rng.uniform(-0.5, 0.5, size=(30, 3)))
    return a, b


def test_reference_matches_textbook(pairs):
    a, b = pairs
    np.testing.assert_allclose(ns_kernel(a, b), textbook(a, b), rtol=1e-12, atol=1e-12)


def test_kernel_is_symmetric_and_positive_definite(pairs):
    a, _ = pairs
    G = ns_kernel(a, a)
    np.testing.assert_allclose(G, G.T, rtol=0, atol=1e-14)
    assert np.linalg.eigvalsh(G).min() > 0
    # On the diagonal t = 0, so K(a, a) = |a|^2 / pi * 2 pi = 2 |a|^2.
    np.testing.assert_allclose(np.diag(G), 2 * np.sum(a * a, axis=1), rtol=1e-14)


@pytest.mark.parametrize("engine", [NumbaEngine(), TorchEngine("cpu")], ids=["numba", "torch"])
def test_engines_match_reference(pairs, engine):
    a, b = pairs
    au, ar = split_unit(a)
    bu, br = split_unit(b)
    K = ns_kernel(a, b)
    np.testing.assert_allclose(engine.kernel_matrix(au, ar, bu, br), K, rtol=1e-12, atol=1e-12)
    w = np.random.default_rng(1).normal(size=len(b))
    np.testing.assert_allclose(engine.kernel_sum(au, ar, bu, br, w), K @ w, rtol=1e-11, atol=1e-11)
    u = np.random.default_rng(2).normal(size=len(b))
    v = np.random.default_rng(3).normal(size=len(a))
    np.testing.assert_allclose(engine.normal_product(au, ar, bu, br, u, v), K.T @ (K @ u + v), rtol=1e-10)


@pytest.mark.parametrize("engine", [NumbaEngine(), TorchEngine("cpu")], ids=["numba", "torch"])
def test_any_dimension(engine):
    """Inputs [x : phi : 1] with features (D = 3 + 5 + 1) go through the generic path."""
    rng = np.random.default_rng(4)
    a = homogeneous(rng.uniform(-0.5, 0.5, (25, 3)), rng.normal(size=(25, 5)))
    b = homogeneous(rng.uniform(-0.5, 0.5, (2100, 3)), rng.normal(size=(2100, 5)))  # > one block
    au, ar = split_unit(a)
    bu, br = split_unit(b)
    K = ns_kernel(a, b)
    np.testing.assert_allclose(engine.kernel_matrix(au, ar, bu, br), K, rtol=1e-11, atol=1e-11)
    w = rng.normal(size=len(b))
    np.testing.assert_allclose(engine.kernel_sum(au, ar, bu, br, w), K @ w, rtol=1e-10, atol=1e-10)


def test_nearly_parallel_inputs_keep_their_accuracy():
    """Neighbouring points give nearly parallel homogeneous vectors; arccos of a dot product loses
    half the digits there, Kahan's formula does not."""
    base = np.array([0.3, -0.2, 0.1, 1.0])
    engine = NumbaEngine()
    for delta in (1e-3, 1e-5, 1e-7, 1e-9):
        a = base[None]
        b = (base + np.array([delta, -0.5 * delta, 0.25 * delta, 0.0]))[None]
        t, na, nb = kahan_angle(a[0], b[0])
        import mpmath

        exact = float(na * nb / mpmath.pi * (mpmath.sin(t) + 2 * (mpmath.pi - t) * mpmath.cos(t)))
        ref = ns_kernel(a, b)[0, 0]
        au, ar = split_unit(a)
        bu, br = split_unit(b)
        fast = engine.kernel_matrix(au, ar, bu, br)[0, 0]
        tor = ns_kernel_torch(torch.tensor(a), torch.tensor(b)).item()
        for got in (ref, fast, tor):
            assert abs(got - exact) <= 1e-14 * abs(exact), (delta, got, exact)


def test_angle_term_limits():
    assert angle_term(np.array([0.0]))[0] == pytest.approx(2 * math.pi)  # t = 0
    assert angle_term(np.array([2.0]))[0] == pytest.approx(1.0)  # t = pi/2: sin = 1, cos = 0
    assert angle_term(np.array([4.0]))[0] == pytest.approx(0.0, abs=1e-12)  # t = pi


def test_torch_kernel_gradient_is_finite_on_the_diagonal():
    a = torch.tensor(homogeneous(np.random.default_rng(5).uniform(-0.5, 0.5, (6, 3))), requires_grad=True)
    K = ns_kernel_torch(a, a)
    K.sum().backward()
    assert torch.isfinite(a.grad).all()
    b = a.detach().clone() + 0.1
    assert torch.autograd.gradcheck(lambda x: ns_kernel_torch(x, b), (a,), atol=1e-6)


@pytest.mark.parametrize("spread", [0.5, 0.99, 3.0])
def test_fast_and_general_angle_terms_agree(spread):
    """The 4-D engine picks a one-square-root angle term when all pairs are within 90 degrees
    (|x| < 1) and the general one otherwise; both match the reference."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=(300, 3))
    x *= (spread * rng.uniform(0.0, 1.0, 300) / np.linalg.norm(x, axis=1))[:, None]
    a = homogeneous(x)
    u, r = split_unit(a)
    eng = NumbaEngine()
    assert eng._acute(u) == (spread < 1)
    w = rng.normal(size=len(a))
    K = ns_kernel(a, a)
    np.testing.assert_allclose(eng.kernel_matrix(u, r, u, r), K, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(eng.kernel_sum(u, r, u, r, w), K @ w, rtol=1e-11, atol=1e-11)
