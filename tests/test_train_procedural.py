"""Procedural training shapes (nkf_model.train.procedural) and the batches made from them."""

from __future__ import annotations

import numpy as np
import pytest

from nkf_model.train import procedural as P
from nkf_model.train.data_worker import DataSource
from nkf_model.train.examples import AugmentSpec, make_example, partial_mask

SMALL = P.ProceduralSpec(n_surface=1500, n_volume=1024, n_near=1024, grid=48)


@pytest.fixture(scope="module")
def one_of_each():
    return {fam: P.shape_samples(11, SMALL, family=fam) for fam in P.FAMILIES}


def test_primitives_have_the_right_sign_and_distance():
    p = np.array([[0.0, 0, 0], [0.5, 0, 0], [0.0, 0, 0.95]])
    assert np.allclose(P.sphere([0, 0, 0], 0.4)(p), [-0.4, 0.1, 0.55])
    assert np.allclose(P.box([0, 0, 0], [0.3, 0.3, 0.3])(p), [-0.3, 0.2, 0.65])
    assert np.allclose(P.capsule([0, 0, -0.5], [0, 0, 0.5], 0.1)(p), [-0.1, 0.4, 0.35])
    assert np.allclose(P.cylinder([0, 0, 0], 0.2, 0.5)(p), [-0.2, 0.3, 0.45])
    assert np.allclose(P.torus([0, 0, 0], 0.5, 0.1)(p), [0.4, -0.1, np.hypot(0.5, 0.95) - 0.1])
    # A tube is the union of its capsules (the compiled loop agrees with the NumPy one).
    rng = np.random.default_rng(0)
    curve, radii = rng.uniform(-0.5, 0.5, size=(7, 3)), rng.uniform(0.05, 0.1, size=7)
    q = rng.uniform(-1, 1, size=(500, 3))
    assert np.allclose(P.tube(curve, radii)(q), P._capsule_chain_py(q, curve, radii))
    # Subtraction and shells
    hollow = P.subtract(P.sphere([0, 0, 0], 0.5), P.sphere([0, 0, 0], 0.3))
    assert list(hollow(p) < 0) == [False, False, False] and hollow(np.array([[0.4, 0, 0]]))[0] < 0
    assert P.shell(P.sphere([0, 0, 0], 0.5), 0.1)(np.array([[0.5, 0, 0], [0.3, 0, 0]])).tolist() == \
        pytest.approx([-0.05, 0.15])


def test_shapes_are_seeded_and_varied():
    a = P.shape_samples(5, SMALL)
    b = P.shape_samples(5, SMALL)
    c = P.shape_samples(6, SMALL)
    for k in ("surf_pts", "surf_nrm", "vol_pts", "vol_occ", "near_pts", "near_occ"):
        assert np.array_equal(a[k], b[k])
    assert not np.array_equal(a["vol_occ"], c["vol_occ"])
    fams = {P.make_shape(s)[0] for s in range(40)}
    assert fams == set(P.FAMILIES)


@pytest.mark.parametrize("family", P.FAMILIES)
def test_samples_lie_on_the_exact_surface_with_outward_normals(one_of_each, family):
    d = one_of_each[family]
    assert d["family"] == family
    # the corpus's unit box: centred, longest side 1
    sp = d["surf_pts"].astype(np.float64)
    ext = sp.max(axis=0) - sp.min(axis=0)
    assert abs(ext.max() - 1.0) < 0.03 and np.abs(0.5 * (sp.max(axis=0) + sp.min(axis=0))).max() < 0.02
    _, f = P.make_shape(11, SMALL, family=family)
    v, _ = P.surface_mesh(f, SMALL.grid)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre, scale = 0.5 * (lo + hi), float((hi - lo).max())

    def field(u):
        return f(np.asarray(u, np.float64) * scale + centre)

    assert np.abs(field(sp)).max() < 1e-5  # on f = 0 (float32 storage)
    n = d["surf_nrm"].astype(np.float64)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    eps = 2e-3
    outward = (field(sp + eps * n) > 0) & (field(sp - eps * n) < 0)
    assert outward.mean() > 0.97  # thin walls and sharp edges can put both sides within eps
    # occupancy is the sign of f, at every stored query
    assert np.array_equal(d["vol_occ"], field(d["vol_pts"]) < 0)
    assert 0.0 < d["vol_occ"].mean() < 0.7
    assert 0.2 < d["near_occ"].mean() < 0.8  # near points straddle the surface


@pytest.mark.parametrize("family", P.FAMILIES)
def test_the_surface_is_closed(family):
    """Marching cubes on the bounded implicit gives a closed mesh: every edge has exactly two faces."""
    _, f = P.make_shape(3, SMALL, family=family)
    _, faces = P.surface_mesh(f, SMALL.grid)
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_examples_from_procedural_shapes(one_of_each):
    spec = AugmentSpec(n_min=200, n_max=1200, n_mode=600, noise_max=0.01, p_half=0.3, p_partial=0.5,
                       scale_min=0.6, scale_max=1.5, n_volume=256, n_near=256, n_surface=128)
    rng = np.random.default_rng(1)
    halves = 0
    for d in one_of_each.values():
        for _ in range(4):
            ex = make_example(d, rng, spec)
            halves += ex.half
            assert 200 <= len(ex.points) <= 1200 or ex.half
            assert abs((ex.points.max(axis=0) - ex.points.min(axis=0)).max() - 1.0) < 1e-9
            assert np.all(np.abs(ex.queries) <= 0.55 + 1e-12)
            assert 0 < ex.occupancy.mean() < 1
    assert halves > 0


def test_partial_surfaces_leave_holes():
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, size=(4000, 3))
    centres = np.array([[0.0, 0.0, 0.0], [0.4, 0.4, 0.4]])
    keep = partial_mask(pts, centres, np.array([0.2, 0.1]))
    d = np.linalg.norm(pts[:, None] - centres[None], axis=2)
    assert np.array_equal(keep, (d[:, 0] > 0.2) & (d[:, 1] > 0.1))
    assert 0 < (~keep).sum() < 4000


def test_batches_depend_only_on_the_step(tmp_path):
    """The examples of a step are the same from a fresh source, in any order (exact resume)."""
    def source():
        return DataSource([], tmp_path, None, AugmentSpec(n_min=100, n_max=200, n_mode=150, n_volume=64, n_near=64,
                                                          n_surface=32, p_partial=0.5),
                          seed=3, batch=2, p_procedural=1.0, procedural=SMALL)

    a = source()
    first = [a.batch_at(s) for s in (0, 1, 2)]
    b = source()
    again = [b.batch_at(s) for s in (2, 0, 1)]
    for x, y in zip(first, [again[1], again[2], again[0]]):
        for ex, ey in zip(x, y):
            assert np.array_equal(ex.points, ey.points) and np.array_equal(ex.occupancy, ey.occupancy)
    assert not np.array_equal(first[0][0].points[:50], first[1][0].points[:50])
