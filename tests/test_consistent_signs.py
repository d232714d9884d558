"""Hoppe's tangent-plane sign propagation (nkf_model.normals.consistent)."""

import numpy as np

from nkf_model.normals.consistent import consistent_signs


def test_random_signs_on_a_sphere_become_outward_from_a_mostly_right_reference():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    flips = np.where(rng.random(3000) < 0.5, -1.0, 1.0)
    n = p * flips[:, None]
    ref = flips.copy()
    ref[:600] *= -1  # a reference wrong on 20 % of the points
    s, pieces = consistent_signs(p, n, reference=ref)
    assert pieces == 1
    assert np.all(np.einsum("ij,ij->i", n * s[:, None], p) > 0)
