"""The real-scan benchmark's reference-free scores (benchmarks/bench_real_scan.py)."""

import numpy as np
from nkf_helpers import icosphere

from benchmarks.bench_real_scan import judge


def _sphere_points(radius, n=50_000, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_a_surface_through_the_points_lies_near_them():
    v, f = icosphere(5, radius=0.02)  # a sphere of 20 mm radius in metres, points 0.3 mm apart
    r = judge(v, f, _sphere_points(0.02), mm=0.001)
    assert r["pieces"] == 1 and r["largest"] == 1.0
    assert r["near"] > 0.99 and r["far"] == 0.0
    assert r["in_p50"] < 0.5


def test_a_second_sheet_and_a_floater_are_seen():
    v, f = icosphere(5, radius=0.02)
    inner = v * 0.9  # 2 mm inside: a second wall beside the first
    blob_v, blob_f = icosphere(2, radius=0.002)
    blob_v = blob_v + [0.04, 0.0, 0.0]
    vv = np.concatenate([v, inner, blob_v])
    ff = np.concatenate([f, f + len(v), blob_f + 2 * len(v)])
    r = judge(vv, ff, _sphere_points(0.02), mm=0.001)
    assert r["pieces"] == 3 and 0.5 < r["largest"] < 0.6  # the outer wall: 1 / (1 + 0.81 + 0.01)
    assert 0.4 < r["far"] < 0.5  # the inner wall and the floater
    assert r["in_p50"] < 0.5  # the input still lies on the outer wall


def test_point_triangle_distance_is_the_closest_point_of_the_triangle():
    from benchmarks.bench_real_scan import point_triangle_distance

    rng = np.random.default_rng(3)
    a, b, c = (rng.normal(size=(300, 3)) for _ in range(3))
    p = 2 * rng.normal(size=(300, 3))
    # brute force: the nearest of a fine barycentric lattice on each triangle
    t = np.linspace(0, 1, 201)
    u, w = np.meshgrid(t, t)
    inside = u + w <= 1
    u, w = u[inside], w[inside]
    grid = a[:, None] + u[None, :, None] * (b - a)[:, None] + w[None, :, None] * (c - a)[:, None]
    brute = np.linalg.norm(grid - p[:, None], axis=2).min(axis=1)
    got = point_triangle_distance(p, a, b, c)
    assert np.all(got <= brute + 1e-12)
    edge = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - a, axis=1)], axis=0)
    assert np.all(brute - got <= edge / 200 + 1e-12)  # within the lattice's step
