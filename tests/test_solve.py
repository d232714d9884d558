"""Stage 4: the exact and the Falkon solves."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import sphere_points

from nkf_model.errors import Cancelled
from nkf_model.fit.augment import augment
from nkf_model.fit.solve import KernelFunction, solve_dense, solve_falkon
from nkf_model.kernel.engines import cpu_engine
from nkf_model.kernel.neural_spline import homogeneous, ns_kernel
from nkf_model.points.normalise import Normalisation


def constraints(n=300, eps=0.01, seed=0):
    p, nrm = sphere_points(n, seed=seed)
    x = Normalisation.fit(p).to_unit(p)
    xa, y = augment(x, nrm, eps)
    return x, nrm, homogeneous(xa), y


def test_dense_solve_reproduces_its_constraints():
    _, _, a, y = constraints()
    alpha, info = solve_dense(a, y, 1e-12, cpu_engine())
    assert info.method == "dense" and info.centres == len(a)
    f = KernelFunction(a, alpha, cpu_engine())(a[:, :3])
    np.testing.assert_allclose(f, y, atol=1e-5)
    # And it is the solution of (G + N lam I) alpha = y.
    G = ns_kernel(a, a)
    np.testing.assert_allclose((G + len(a) * 1e-12 * np.eye(len(a))) @ alpha, y, atol=1e-6)


def test_larger_lambda_smooths():
    """Larger lambda fits the constraints less tightly and gives a smaller RKHS norm."""
    _, _, a, y = constraints()
    G = ns_kernel(a, a)
    res, norms = [], []
    for lam in (1e-12, 1e-6, 1e-3):
        alpha, _ = solve_dense(a, y, lam, cpu_engine())
        res.append(np.abs(G @ alpha - y).mean())
        norms.append(alpha @ G @ alpha)
    assert res[0] < res[1] < res[2]
    assert norms[0] > norms[1] > norms[2]
    assert res[0] < 1e-5 and res[2] > 0.05


def test_dense_solve_survives_repeated_constraints_and_zero_lambda():
    _, _, a, y = constraints(100)
    a2 = np.concatenate([a, a[:10]])
    y2 = np.concatenate([y, y[:10]])
    alpha, info = solve_dense(a2, y2, 0.0, cpu_engine())
    assert np.isfinite(alpha).all() and info.jitter > 0
    f = KernelFunction(a2, alpha, cpu_engine())(a2[:, :3])
    np.testing.assert_allclose(f, y2, atol=1e-3)


def test_falkon_matches_dense_when_all_points_are_centres():
    _, _, a, y = constraints(200)
    lam = 1e-9
    dense, _ = solve_dense(a, y, lam, cpu_engine())
    # Nystrom KRR with every point as a centre solves (G G + N lam G) alpha = G y, the same alpha.
    falk, info = solve_falkon(a, y, np.arange(len(a)), lam, cpu_engine(), tol=1e-12, max_iter=500)
    assert info.method == "falkon"
    xs = np.random.default_rng(0).uniform(-0.5, 0.5, (500, 3))
    fd = KernelFunction(a, dense, cpu_engine())(xs)
    ff = KernelFunction(a, falk, cpu_engine())(xs)
    np.testing.assert_allclose(ff, fd, atol=2e-3 * np.abs(fd).max())


def test_falkon_with_fewer_centres_fits_the_constraints():
    x, _, a, y = constraints(1500)
    idx = np.random.default_rng(0).choice(len(a), 800, replace=False)
    alpha, info = solve_falkon(a, y, idx, 1e-10, cpu_engine())
    assert info.centres == 800 and info.iterations > 0
    f = KernelFunction(a[idx], alpha, cpu_engine())(a[:, :3])
    assert (np.sign(f) == y).mean() > 0.99
    assert np.abs(f - y).mean() < 0.1


def test_solves_stop_when_cancelled():
    _, _, a, y = constraints(200)

    def stop():
        raise Cancelled("stop")

    with pytest.raises(Cancelled):
        solve_dense(a, y, 1e-10, cpu_engine(), cancel_poll=stop)
    with pytest.raises(Cancelled):
        solve_falkon(a, y, np.arange(100), 1e-10, cpu_engine(), cancel_poll=stop)


@pytest.mark.parametrize("features", [0, 8, 2])  # 4-D, 12-D and generic rows
def test_fused_gram_lower_triangle_matches_the_kernel_matrix(features):
    from nkf_model.kernel.engines import TorchEngine
    from nkf_model.kernel.neural_spline import split_unit

    rng = np.random.default_rng(features)
    x = rng.uniform(-0.5, 0.5, size=(301, 3))
    phi = None if features == 0 else rng.normal(scale=0.3, size=(301, features))
    u, r = split_unit(homogeneous(x, phi))
    low = np.tril_indices(len(u))
    want = ns_kernel(homogeneous(x, phi), homogeneous(x, phi))
    want[np.diag_indices(len(u))] += 0.25
    for engine in (cpu_engine(), TorchEngine("cpu")):
        got = engine.gram(u, r, 0.25)
        np.testing.assert_allclose(got[low], want[low], rtol=1e-11, atol=1e-11)
