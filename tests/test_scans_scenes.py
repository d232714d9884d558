"""The synthetic scene scanner: only visible, front-facing surfaces are sampled (issue 5)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import scenes


@pytest.fixture(scope="module")
def room():
    scene = scenes.make_scene(seed=5, n_objects=3)
    return scene, scenes.scan(scene, 20_000, noise=0.002, seed=5, reference=20_000)


def test_scene_layout(room):
    scene, _ = room
    w, d, h = scenes.ROOM
    assert len(scene.objects) == 3 and len(scene.viewpoints) == 3
    assert scene.vertices[:, 2].min() >= -1e-9 and scene.vertices[:, 0].min() >= -1e-9
    assert scene.vertices[:, 0].max() <= w + 1e-9 and scene.vertices[:, 1].max() <= d + 1e-9
    assert len(scene.face_colors) == len(scene.faces) == len(scene.part)
    assert set(np.unique(scene.part)) == {0, 1, 2, 3, 4}


def occluded(scene, origin, target):
    """Whether any triangle cuts the segment origin -> target (Moller-Trumbore, excluding the ends)."""
    tri = scene.vertices[scene.faces]
    d = target - origin
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    pv = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = origin - tri[:, 0]
    u = np.einsum("ij,ij->i", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = (qv @ d) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-3)
    return bool(hit.any())


def test_scan_sees_only_front_facing_visible_surfaces(room):
    scene, s = room
    assert s.points.shape == (20_000, 3) and s.colors.dtype == np.uint8
    # Every reference sample faces a scanner, and the segment to the scanner that saw it is free.
    rng = np.random.default_rng(0)
    pick = rng.choice(len(s.points), 60, replace=False)
    clean = scenes.scan(scene, 20_000, noise=0.0, seed=5, reference=20_000)  # same draw, no noise
    towards = scene.viewpoints[clean.seen_by] - clean.points
    assert (np.sum(clean.normals * towards, axis=1) > 0).all()
    blocked = [occluded(scene, scene.viewpoints[clean.seen_by[i]], clean.points[i]) for i in pick]
    assert sum(blocked) <= 1  # the depth buffer's tolerance may let a grazing sample through
    # And samples the scanner rejects are really hidden from it (or face away).
    pts, nrm, _ = scenes._sample(scene.vertices, scene.faces, 3000, rng)
    vp = scene.viewpoints[0]
    seen = scenes.visible_from(scene, pts, nrm, vp)
    hidden = np.flatnonzero(~seen & (np.sum(nrm * (vp - pts), axis=1) > 0.2 * np.linalg.norm(vp - pts, axis=1)))
    assert len(hidden) > 20
    checks = [occluded(scene, vp, pts[i]) for i in hidden[:40]]
    assert np.mean(checks) > 0.95


def test_noise_is_along_the_line_of_sight():
    scene = scenes.make_scene(seed=6, n_objects=1)
    a = scenes.scan(scene, 2000, noise=0.0, seed=1, reference=1000)
    b = scenes.scan(scene, 2000, noise=0.01, seed=1, reference=1000)
    diff = b.points - a.points
    ray = a.points - scene.viewpoints[a.seen_by]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.sum(diff * ray, axis=1)
    assert np.allclose(diff, along[:, None] * ray, atol=1e-9)
    assert 0.007 < along.std() < 0.013


def test_scenes_are_reproducible():
    a = scenes.scan(scenes.make_scene(seed=2, n_objects=2), 1000, seed=3, reference=1000)
    b = scenes.scan(scenes.make_scene(seed=2, n_objects=2), 1000, seed=3, reference=1000)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.colors, b.colors)
