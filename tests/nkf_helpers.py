"""Small learned-kernel models and meshes for the nkf tests."""

from __future__ import annotations

import numpy as np
import torch

from nkf_model.kernel.feature_net import FeatureConfig, FeatureNet
from nkf_model.kernel.weights import save_weights

TINY = FeatureConfig(grid=8, pointnet_width=8, unet_width=4, unet_levels=2, feature_dim=8, point_weights=False)


def tiny_net(seed: int = 0, config: FeatureConfig = TINY, gate: float | None = None) -> FeatureNet:
    torch.manual_seed(seed)
    net = FeatureNet(config)
    if gate is not None:
        with torch.no_grad():
            net.gate.fill_(gate)
    return net


def tiny_weights(path, seed: int = 0, config: FeatureConfig = TINY, gate: float | None = None, lam: float = 1e-10):
    return save_weights(path, tiny_net(seed, config, gate), lam=lam, training={"test": True})


def icosphere(subdivisions: int = 2, radius: float = 0.45):
    """A closed triangle mesh of a sphere (outward faces) in the unit box."""
    t = (1.0 + 5**0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    v = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        cache = {}
        nf = []

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = v[a] + v[b]
                v.append(m / np.linalg.norm(m))
                cache[key] = len(v) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = nf
    return np.array(v) * radius, np.array(f, dtype=np.int64)


def box_mesh(size=(0.8, 0.5, 0.3)):
    """A closed box (outward faces) centred at the origin."""
    sx, sy, sz = (np.asarray(size) / 2)
    v = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = []
    for a, b, c, d in quads:
        f += [[a, b, c], [a, c, d]]
    return v, np.array(f, dtype=np.int64)
