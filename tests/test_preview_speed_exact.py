"""The learned features at grid nodes kept for later lambdas (nkf_model.pipeline.query_cache.QueryCache):
a re-mesh that reuses them gives what a fresh run gives, to the bit."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import torus_points

import nkf_model
from nkf_model.pipeline import fitted


def torus(n):
    p, nrm = torus_points(n, seed=3)
    return p * 2.5 + np.array([10.0, -3.0, 1.0]), nrm


def same(m1, m2):
    return np.array_equal(m1.faces, m2.faces) and np.array_equal(m1.vertices, m2.vertices)


# nkf on the dense solver with the far field (a BlendedField around the kernel sum) and trimmed
# (the kernel sum alone), and on the partition of unity (forced, so that it stays small)
CASES = [
    pytest.param(dict(method="nkf"), 500, id="dense-far-field"),
    pytest.param(dict(method="nkf", trim=2.0), 500, id="dense-trim"),
    pytest.param(dict(method="nkf", solver="pou"), 1200, id="pou"),
]


@pytest.mark.parametrize("settings,n", CASES)
def test_a_new_lambda_reuses_the_features_at_the_nodes_and_is_a_fresh_run(settings, n):
    p, nrm = torus(n)
    f = nkf_model.fit(p, nrm, resolution=48, lam=1e-10, **settings)
    cache = f._shared.queries
    assert cache is not None and cache.nbytes == 0
    f.mesh(resolution=64)  # levels 16, 32, 64
    kept, misses = cache.nbytes, cache.misses
    assert kept > 0 and misses > 0 and cache.hits == 0
    assert f.nbytes >= kept
    g = f.with_lam(3e-6)
    hits = cache.hits
    preview = g.mesh(resolution=64)
    assert cache.hits - hits > 0.8 * (cache.hits - hits + cache.misses - misses)  # most nodes seen before
    assert same(preview, nkf_model.reconstruct(p, nrm, resolution=64, lam=3e-6, **settings))
    # resolution 32 evaluates levels 16 and 32 only: all of them seen before, no features computed
    misses = cache.misses
    assert same(g.mesh(resolution=32), nkf_model.reconstruct(p, nrm, resolution=32, lam=3e-6, **settings))
    assert cache.misses == misses
    # resolution 48 (levels 24 and 48): new nodes, kept too
    assert same(g.mesh(resolution=48), nkf_model.reconstruct(p, nrm, resolution=48, lam=3e-6, **settings))
    assert cache.misses > misses and cache.nbytes > kept


def test_the_kept_rows_are_the_nodes_rows():
    # A row kept for the wrong node would move the surface: swap two kept levels' rows and the
    # re-mesh must differ (this is what the equality above rests on).
    p, nrm = torus(500)
    f = nkf_model.fit(p, nrm, method="nkf", resolution=32, lam=1e-10, trim=2.0)
    first = f.mesh(resolution=32)
    cache = f._shared.queries
    level = max(cache._levels, key=lambda lv: lv[0])  # the finest level (32 cells)
    e = cache._levels[level]
    used = e[4]
    e[2][:used] = e[2][:used][np.random.default_rng(0).permutation(used)]
    assert not same(f.mesh(resolution=32), first)


def test_a_small_budget_keeps_less_and_stays_exact(monkeypatch):
    monkeypatch.setattr(fitted, "QUERY_CACHE_BYTES", 2_000_000)  # one coarse level (8,192 rows), not two
    p, nrm = torus(500)
    settings = dict(method="nkf", trim=2.0)
    f = nkf_model.fit(p, nrm, resolution=48, lam=1e-10, **settings)
    cache = f._shared.queries
    assert cache.max_bytes == 2_000_000
    f.mesh(resolution=64)
    assert 0 < cache.nbytes <= 2_000_000 and len(cache._levels) == 1
    g = f.with_lam(3e-6)
    assert same(g.mesh(resolution=64), nkf_model.reconstruct(p, nrm, resolution=64, lam=3e-6, **settings))
    assert cache.nbytes <= 2_000_000


def test_no_cache_without_learned_features_or_kept_factors():
    p, nrm = torus(500)
    assert nkf_model.fit(p, nrm, method="nkf", resolution=32, keep_factors=False)._shared.queries is None
    splines = nkf_model.fit(p, nrm, method="splines", resolution=32)
    splines.mesh()
    assert splines._shared.queries is None or splines._shared.queries.nbytes == 0
