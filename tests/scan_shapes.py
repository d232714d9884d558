"""Shapes with exact oriented samples for the scan tests (boxes, plates, open hemispheres)."""

from __future__ import annotations

import numpy as np


def box_points(n: int, size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), seed: int = 0):
    """``n`` points uniform by area on the surface of an axis-aligned box, outward unit normals."""
    rng = np.random.default_rng(seed)
    sx, sy, sz = size
    areas = np.array([sy * sz, sy * sz, sx * sz, sx * sz, sx * sy, sx * sy])
    face = rng.choice(6, size=n, p=areas / areas.sum())
    u = rng.uniform(-0.5, 0.5, size=(n, 3)) * np.array(size)
    axis = face // 2
    sign = np.where(face % 2 == 0, 1.0, -1.0)
    half = np.array(size) / 2
    u[np.arange(n), axis] = sign * half[axis]
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = sign
    return u + np.asarray(center), nrm


def hemisphere_points(n: int, seed: int = 0):
    """``n`` points on the upper unit hemisphere (z >= 0), outward normals: an open surface."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.copy(), d


def open_box_points(n: int, wall: float, seed: int = 0):
    """``n`` points on a unit box without a lid whose five walls are slabs ``wall`` thick (a cup
    with thin walls: each wall's inner face looks into the box), outward unit normals. Faces that
    lie inside another wall (where walls meet) are sampled too, as in a mesh made of five boxes."""
    t = wall
    parts = [((1.0, 1.0, t), (0.0, 0.0, -0.5 + t / 2)),
             ((t, 1.0, 1.0), (-0.5 + t / 2, 0.0, 0.0)), ((t, 1.0, 1.0), (0.5 - t / 2, 0.0, 0.0)),
             ((1.0 - 2 * t, t, 1.0), (0.0, -0.5 + t / 2, 0.0)), ((1.0 - 2 * t, t, 1.0), (0.0, 0.5 - t / 2, 0.0))]
    areas = np.array([2 * (sx * sy + sy * sz + sx * sz) for (sx, sy, sz), _ in parts])
    counts = np.round(n * areas / areas.sum()).astype(int)
    ps, ns = [], []
    for k, ((size, centre), m) in enumerate(zip(parts, counts)):
        p, q = box_points(int(m), size=size, center=centre, seed=seed + k)
        ps.append(p)
        ns.append(q)
    return np.concatenate(ps), np.concatenate(ns)


def cube_mesh(half: float = 0.4):
    """Vertices (8, 3) and outward-wound triangles (12, 3) of the cube [-half, half]^3."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    # Outward-facing triangles of the cube with corners v[4x + 2y + z].
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    return v, np.array(f)
