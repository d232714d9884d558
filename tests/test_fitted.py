"""A fit you can keep (nkf_model.fit, nkf_model.pipeline.fitted): re-mesh and re-solve give what a fresh run gives."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from shapes import torus_points

import nkf_model
from nkf_model.errors import Cancelled, InvalidParameterError

# splines on the dense solver and on the partition of unity (forced, so that it stays small)
CASES = [
    pytest.param(dict(method="splines"), 500, id="dense"),
    pytest.param(dict(method="splines", solver="pou"), 1200, id="pou"),
]


def torus(n):
    p, nrm = torus_points(n, seed=3)
    return p * 2.5 + np.array([10.0, -3.0, 1.0]), nrm


def same(m1, m2):
    return np.array_equal(m1.faces, m2.faces) and np.array_equal(m1.vertices, m2.vertices)


def close_to(m1, m2, tol=1e-6):
    """Same triangles, vertices within ``tol`` of the box's longest side."""
    if m1.faces.shape != m2.faces.shape or not np.array_equal(m1.faces, m2.faces):
        return False
    d = np.abs(m1.local_vertices.astype(np.float64) - m2.local_vertices.astype(np.float64)).max()
    return d <= tol * m1.scale


@pytest.mark.parametrize("settings,n", CASES)
def test_fit_then_mesh_is_reconstruct_and_resolution_is_only_a_remesh(settings, n):
    p, nrm = torus(n)
    f = nkf_model.fit(p, nrm, resolution=40, **settings)
    assert isinstance(f, nkf_model.Fit) and f.points_used == n and not f.resolution_dependent
    assert same(f.mesh(), nkf_model.reconstruct(p, nrm, resolution=40, **settings))
    seen = []
    m48 = f.mesh(resolution=48, progress=lambda fr, st: seen.append(st))
    assert same(m48, nkf_model.reconstruct(p, nrm, resolution=48, **settings))
    # only the evaluation and the meshing ran
    assert set(seen) == {"evaluate", "mesh", "done"}
    assert set(m48.stats["timings"]) == {"evaluate", "mesh"}
    assert "solve" in m48.stats["fit_timings"]


@pytest.mark.parametrize("settings,n", CASES)
def test_new_lambda_is_a_fresh_run(settings, n):
    p, nrm = torus(n)
    f = nkf_model.fit(p, nrm, resolution=40, lam=1e-10, **settings)
    fresh = nkf_model.reconstruct(p, nrm, resolution=40, lam=3e-6, **settings)
    # Cholesky from the kept constraints: the same to the bit
    g = f.with_lam(3e-6)
    assert g.lam == 3e-6 and g.options.lam == 3e-6 and f.lam == 1e-10
    assert same(g.mesh(), fresh)
    # from the eigendecomposition: within 1e-6 of the box
    assert f.can_factorize and not f.factorized
    assert f.factorize() and f.factorized and g.factorized  # shared by every fit of one call
    h = f.with_lam(3e-6)
    assert close_to(h.mesh(), fresh)
    assert close_to(f.with_lam(1e-10).mesh(), f.mesh())
    # a much smoother lambda changes the surface (the test can fail)
    smooth = f.with_lam(1e-2).mesh()
    assert smooth.faces.shape != fresh.faces.shape or not np.array_equal(smooth.faces, fresh.faces)


def test_nkf_fit_matches_reconstruct_after_a_new_lambda():
    p, nrm = torus(400)
    f = nkf_model.fit(p, nrm, method="nkf", resolution=32)
    assert same(f.mesh(), nkf_model.reconstruct(p, nrm, method="nkf", resolution=32))
    f.factorize()
    assert close_to(f.with_lam(1e-7).mesh(), nkf_model.reconstruct(p, nrm, method="nkf", resolution=32, lam=1e-7))


def test_mesh_settings_trim_and_bad_values():
    p, nrm = torus(500)
    f = nkf_model.fit(p, nrm, method="splines", resolution=32, trim=4.0)
    assert same(f.mesh(trim=2.0, min_piece=0.01), nkf_model.reconstruct(p, nrm, method="splines", resolution=32,
                                                                        trim=2.0, min_piece=0.01))
    with pytest.raises(InvalidParameterError, match="changes the fit"):
        f.mesh(trim=None)
    with pytest.raises(InvalidParameterError):
        f.mesh(resolution=5)
    with pytest.raises(InvalidParameterError):
        f.with_lam(-1.0)


def test_keep_factors_off_keeps_no_gram_matrix():
    p, nrm = torus(500)
    kept = nkf_model.fit(p, nrm, method="splines", resolution=32)
    light = nkf_model.fit(p, nrm, method="splines", resolution=32, keep_factors=False)
    assert not light.can_factorize and not light.factorize()
    assert kept.nbytes - light.nbytes >= 8 * 1000 * 1000  # the (2N)^2 Gram matrix
    assert same(light.with_lam(1e-6).mesh(), kept.with_lam(1e-6).mesh())


def test_cancel_a_remesh_and_a_new_lambda():
    p, nrm = torus(500)
    f = nkf_model.fit(p, nrm, method="splines", resolution=32)
    stop = threading.Event()
    stop.set()
    with pytest.raises(Cancelled):
        f.mesh(resolution=64, cancel=stop)
    with pytest.raises(Cancelled):
        f.with_lam(1e-6, cancel=stop)
    assert same(f.mesh(), nkf_model.reconstruct(p, nrm, method="splines", resolution=32))


def test_pou_new_lambda_keeps_the_coarse_fit_and_solves_only_the_patches():
    # The coarse fit's lambda is COARSE_LAM whatever the fit's: its 48^3 grid is made once per fit.
    p, nrm = torus(1200)
    settings = dict(method="splines", solver="pou", resolution=40)
    f = nkf_model.fit(p, nrm, lam=1e-10, **settings)
    floor = f.stats["pou"]["patch_lam"]  # the patches' lambda: the noise floor (about 1e-4 here)
    lam = 3 * floor
    fresh = nkf_model.fit(p, nrm, lam=lam, **settings)
    g = f.with_lam(lam)
    assert g.stats["pou"]["patch_lam"] == fresh.stats["pou"]["patch_lam"] == lam
    assert g._sol.fn.f0_grid is f._sol.fn.f0_grid
    assert np.array_equal(fresh._sol.fn.f0_grid, f._sol.fn.f0_grid)
    assert np.array_equal(g._sol.fn.beta, fresh._sol.fn.beta)
    assert not np.array_equal(g._sol.fn.beta, f._sol.fn.beta)  # the patches were solved again
    fresh_mesh = fresh.mesh()
    assert same(g.mesh(), fresh_mesh)
    f.factorize()
    assert close_to(f.with_lam(lam).mesh(), fresh_mesh)
    # under the noise floor a new lambda leaves the function as it is
    under = f.with_lam(floor / 2)
    assert under._sol.fn is f._sol.fn and under.stats["pou"]["patch_lam"] == floor
    assert same(under.mesh(), nkf_model.reconstruct(p, nrm, lam=floor / 2, **settings))


def test_coarse_lambda_is_the_default_lambda():
    # docs/adjust.md: runs at the default lambda kept their coarse fit when it stopped following lambda
    from nkf_model.fit.partition_of_unity import COARSE_LAM
    from nkf_model.options import SETTING

    assert COARSE_LAM == SETTING["lam"].default
