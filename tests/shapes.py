"""Analytic shapes with exact oriented samples, for tests."""

from __future__ import annotations

import numpy as np


def sphere_points(n: int, radius: float = 1.0, center=(0.0, 0.0, 0.0), seed: int = 0):
    """``n`` points on a sphere with outward unit normals: (n, 3), (n, 3) float64."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center) + radius * d, d


def torus_points(n: int, R: float = 1.0, r: float = 0.35, seed: int = 0):
    """``n`` points on a torus around the z axis (major radius R, minor r), outward normals."""
    rng = np.random.default_rng(seed)
    # Rejection sampling for a uniform density by area (area element ~ R + r cos v).
    u = rng.uniform(0, 2 * np.pi, 4 * n)
    v = rng.uniform(0, 2 * np.pi, 4 * n)
    keep = rng.uniform(0, R + r, 4 * n) < R + r * np.cos(v)
    u, v = u[keep][:n], v[keep][:n]
    c = np.stack([np.cos(u), np.sin(u), np.zeros_like(u)], axis=1)
    nrm = np.cos(v)[:, None] * c + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
    return R * c + r * nrm, nrm


def torus_distance(p, R: float = 1.0, r: float = 0.35):
    """Unsigned distance of points (N, 3) to the torus surface."""
    q = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2) - R
    return np.abs(np.sqrt(q**2 + p[:, 2] ** 2) - r)
