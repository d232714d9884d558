"""A seeded random subset of at most ``max_points`` points (the ``max_points`` setting)."""

from __future__ import annotations

import numpy as np


def random_subset(points, normals, colors, max_points: int | None, seed: int = 0):
    """At most ``max_points`` rows of ``points`` (N, 3), chosen at random with ``seed`` and kept in
    their input order; ``normals`` and ``colors`` (either may be ``None``) are indexed alike.

    Returns ``(points, normals, colors)``, the inputs themselves when ``max_points`` is ``None``,
    0 or not below N.
    """
    n = len(points)
    if not max_points or n <= max_points:
        return points, normals, colors
    points = np.asarray(points)
    normals = None if normals is None else np.asarray(normals)
    colors = None if colors is None else np.asarray(colors)
    keep = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
    return points[keep], None if normals is None else normals[keep], None if colors is None else colors[keep]
