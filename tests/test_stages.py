"""Stages 1, 2, 5 and 6 on their own: normalise, augment, sparse evaluation, meshing; and sampling."""

from __future__ import annotations

import numpy as np
import pytest

from nkf_model.errors import Cancelled
from nkf_model.fit.augment import augment, default_eps
from nkf_model.points.farthest_point import farthest_point_sample
from nkf_model.points.normalise import Normalisation
from nkf_model.surface.evaluate import evaluate_dense, evaluate_sparse, levels, node_positions
from nkf_model.surface.mesh import triangulate, vertex_normals


def test_normalisation_round_trip_far_from_the_origin():
    rng = np.random.default_rng(0)
    p = 1e6 + rng.uniform(-3, 3, (100, 3))
    nm = Normalisation.fit(p)
    u = nm.to_unit(p)
    assert np.abs(u).max() <= 0.5 + 1e-12
    assert np.isclose(np.ptp(u, axis=0).max(), 1.0)
    np.testing.assert_allclose(nm.to_world(u), p, rtol=0, atol=1e-9)


def test_normalisation_of_a_tiny_object():
    rng = np.random.default_rng(1)
    p = 1e-6 * rng.uniform(-1, 1, (100, 3))
    u = Normalisation.fit(p).to_unit(p)
    assert np.isclose(np.ptp(u, axis=0).max(), 1.0)


def test_augment_doubles_points_with_signed_labels():
    x = np.zeros((3, 3))
    n = np.eye(3)
    xa, y = augment(x, n, 0.01)
    np.testing.assert_allclose(xa[:3], 0.01 * np.eye(3))
    np.testing.assert_allclose(xa[3:], -0.01 * np.eye(3))
    np.testing.assert_array_equal(y, [1, 1, 1, -1, -1, -1])
    assert default_eps(1000) == 0.01 and default_eps(12000) == pytest.approx(0.005)


def sphere_sdf(p, r=0.3):
    return np.linalg.norm(p, axis=1) - r


def test_sparse_evaluation_matches_dense_near_the_surface():
    res = 128
    sp = evaluate_sparse(sphere_sdf, res)
    dense = evaluate_dense(sphere_sdf, res)
    g = np.arange(res + 1)
    ijk = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    vals = sp.lookup(ijk)
    known = ~np.isnan(vals)
    np.testing.assert_allclose(vals[known], dense.reshape(-1)[known])
    # Every cell of the dense grid that crosses zero is in the band.
    neg = dense < 0
    crossing = set()
    for i, j, k in np.argwhere(neg[:-1, :-1, :-1] != neg[1:, 1:, 1:]):
        crossing.add((i, j, k))
    band = {tuple(c) for c in sp.band}
    assert crossing <= band
    assert sp.evaluations < 0.25 * (res + 1) ** 3


def test_evaluations_grow_as_the_square_of_the_resolution():
    # The finest level's evaluations: the coarse 24-48 grid is a fixed cost.
    counts = [evaluate_sparse(sphere_sdf, r).level_evaluations[-1][1] for r in (128, 256, 512)]
    assert 3.0 < counts[1] / counts[0] < 5.0
    assert 3.0 < counts[2] / counts[1] < 5.0


def test_levels():
    assert levels(128) == [16, 32, 64, 128]
    assert levels(100) == [25, 50, 100]
    assert levels(37) == [19, 38]
    assert levels(1023) == [32, 64, 128, 256, 512, 1024]
    assert levels(16) == [16]


@pytest.mark.parametrize("res", [37, 99, 129])
def test_odd_resolutions_stay_sparse_and_match_dense(res):
    sp = evaluate_sparse(sphere_sdf, res)
    assert sp.evaluations < 0.3 * (res + 1) ** 3
    v, f = triangulate(sp)
    assert len(f) > 0 and np.abs(np.linalg.norm(v, axis=1) - 0.3).max() < 1.1 / res
    assert v.max() < 0.55 and v.min() > -0.55


def test_seeds_find_a_part_the_coarse_grid_misses():
    """A small ball between the coarse grid's nodes is found through a seed point on it."""
    c = np.array([0.013, -0.021, 0.017])

    def blobs(p):
        return np.minimum(np.linalg.norm(p - 0.3, axis=1) - 0.1, np.linalg.norm(p - c, axis=1) - 0.012)

    without = triangulate(evaluate_sparse(blobs, 128))[0]
    seeded = triangulate(evaluate_sparse(blobs, 128, seeds=(c + [0.012, 0, 0])[None]))[0]
    near = lambda v: (np.linalg.norm(v - c, axis=1) < 0.02).sum()  # noqa: E731
    assert near(without) == 0
    assert near(seeded) > 20


def test_sparse_evaluation_cancels():
    def stop():
        raise Cancelled("stop")

    with pytest.raises(Cancelled):
        evaluate_sparse(sphere_sdf, 64, cancel_poll=stop)


def two_spheres(p):
    return np.minimum(np.linalg.norm(p - [0.2, 0, 0], axis=1), np.linalg.norm(p + [0.2, 0, 0], axis=1)) - 0.15


def test_block_marching_cubes_is_watertight_across_blocks():
    sp = evaluate_sparse(two_spheres, 96)  # 3 blocks per side
    v, f = triangulate(sp)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()
    d = np.abs(two_spheres(v))
    assert d.max() < 2 * 1.1 / 96
    # Outward: vertex normals agree with the gradient of the distance.
    n = vertex_normals(v, f)
    grad = np.where((v[:, :1] > 0), v - [0.2, 0, 0], v + [0.2, 0, 0])
    assert (np.sum(n * grad, axis=1) > 0).mean() > 0.999


def test_grid_covers_the_unit_box_with_a_margin():
    corners = node_positions(np.array([[0, 0, 0], [64, 64, 64]]), 64)
    assert corners[0, 0] < -0.5 and corners[1, 0] > 0.5


def test_farthest_point_sampling_spreads_points():
    rng = np.random.default_rng(0)
    p = rng.uniform(size=(5000, 3))
    idx = farthest_point_sample(p, 100, seed=1)
    assert len(np.unique(idx)) == 100
    from scipy.spatial import cKDTree

    d, _ = cKDTree(p[idx]).query(p)
    r, _ = cKDTree(p[rng.choice(5000, 100, replace=False)]).query(p)
    assert d.max() < r.max()
