"""The reused BLAS thread limit of the solves (nkf_model.pipeline.blas_threads)."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info

from nkf_model.fit.refit import GramEigen
from nkf_model.pipeline.blas_threads import blas_threads


def _blas_threads():
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_limit_applies_inside_and_is_restored_after():
    before = _blas_threads()
    assert before, "numpy's BLAS is visible to threadpoolctl"
    for _ in range(2):  # the second call reuses the controller
        with blas_threads(1):
            assert all(n == 1 for n in _blas_threads())
        assert _blas_threads() == before


def test_projected_solve_is_the_solve_to_the_bit():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(60, 60))
    gram = a @ a.T
    y = rng.normal(size=60)
    eig = GramEigen.of(gram.copy())
    b = eig.project(y)
    for shift in (1e-9, 1e-3, 1.0):
        x = eig.solve_projected(b, shift)
        assert np.array_equal(x, eig.solve(y, shift))
        np.testing.assert_allclose((gram + shift * np.eye(60)) @ x, y, rtol=1e-6, atol=1e-6)
