"""The feature network of the learned kernel: shapes, determinism, pooling and trilinear sampling."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nkf_helpers import TINY, tiny_net

from nkf_model.kernel.feature_net import (
    FeatureConfig,
    FeatureNet,
    cell_coordinates,
    sample_grid_numpy,
    sample_grid_torch,
)
from nkf_model.kernel.learned_kernel import _gated_trilinear
from nkf_model.points.normalise import GRID_HALF


def _cloud(n=300, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, size=(n, 3))
    y = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    return torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32)


@pytest.mark.parametrize("config", [
    TINY,
    FeatureConfig(grid=16, unet_levels=3, point_weights=True),
    FeatureConfig(grid=8, unet_levels=2, unet_width=4, point_weights=True, const_channel=True, const_init=1.0),
])
def test_shapes(config):
    net = FeatureNet(config)
    x, y = _cloud()
    g = net.grid_features(x, y)
    c = config.feature_dim - config.const_channel + config.point_weights
    assert g.shape == (c, config.grid, config.grid, config.grid)
    phi, w = net.point_features(g, x[:50])
    assert phi.shape == (50, config.feature_dim)
    if config.const_channel:  # a learned constant first feature: c^2 = exp(const_init)
        assert torch.allclose(phi[:, 0], torch.full((50,), float(np.exp(0.5))))
        phi = phi[:, 1:]
    if config.point_weights:
        assert w.shape == (50,) and bool(((w > 0) & (w <= 1)).all())
    else:
        assert w is None
    # tanh and the gate bound every feature.
    assert float(phi.detach().abs().max()) <= float(net.gate.detach().abs().max()) + 1e-7


def test_deterministic_and_seeded():
    x, y = _cloud()
    a, b = tiny_net(seed=3), tiny_net(seed=3)
    ga = a.grid_features(x, y)
    assert torch.equal(ga, a.grid_features(x, y))
    assert torch.equal(ga, b.grid_features(x, y))
    assert not torch.equal(ga, tiny_net(seed=4).grid_features(x, y))


def test_pointnet_pools_per_cell_and_leaves_empty_cells_zero():
    net = tiny_net()
    x, y = _cloud(200)
    cells = net.cell_grid(x, y)
    perm = torch.randperm(len(x), generator=torch.Generator().manual_seed(0))
    assert torch.equal(cells, net.cell_grid(x[perm], y[perm]))  # order does not matter (max pooling)
    flat, _ = cell_coordinates(x, TINY.grid)
    occupied = torch.zeros(TINY.grid**3, dtype=torch.bool)
    occupied[flat] = True
    assert 0 < int(occupied.sum()) < TINY.grid**3
    flat_cells = cells.detach().reshape(cells.shape[0], -1)
    assert bool((flat_cells[:, ~occupied] == 0).all())
    assert bool((flat_cells[:, occupied] != 0).any(dim=0).all())


def test_cell_coordinates():
    m = 8
    h = 2 * GRID_HALF / m
    x = torch.tensor([[-GRID_HALF + 0.5 * h, -GRID_HALF + 0.25 * h, GRID_HALF - 0.5 * h], [2.0, -2.0, 0.0]])
    flat, local = cell_coordinates(x, m)
    assert flat[0] == (0 * m + 0) * m + (m - 1)
    assert torch.allclose(local[0], torch.tensor([0.0, -0.25, 0.0]), atol=1e-6)
    assert flat[1] == ((m - 1) * m + 0) * m + m // 2  # outside the box: the border cell


def _direct_trilinear(grid, p):
    """Trilinear interpolation of cell-centred values, written out point by point."""
    m = grid.shape[0]
    h = 2 * GRID_HALF / m
    centres = -GRID_HALF + (np.arange(m) + 0.5) * h
    out = np.zeros(grid.shape[-1])
    idx, wts = [], []
    for a in range(3):
        c = min(max(p[a], centres[0]), centres[-1])  # border values extend outward
        i = min(int(np.searchsorted(centres, c, side="right")) - 1, m - 2)
        t = (c - centres[i]) / h
        idx.append(i)
        wts.append(t)
    for da in (0, 1):
        for db in (0, 1):
            for dc in (0, 1):
                w = ((wts[0] if da else 1 - wts[0]) * (wts[1] if db else 1 - wts[1])
                     * (wts[2] if dc else 1 - wts[2]))
                out += w * grid[idx[0] + da, idx[1] + db, idx[2] + dc]
    return out


def test_trilinear_sampling_matches_a_direct_computation():
    rng = np.random.default_rng(0)
    grid = rng.normal(size=(6, 6, 6, 3))
    pts = rng.uniform(-0.62, 0.62, size=(200, 3))  # also outside the box
    pts[:4] = [[0, 0, 0], [GRID_HALF, -GRID_HALF, 0.1], [-0.6, 0.6, 0.6], [0.01, 0.02, -0.03]]
    direct = np.array([_direct_trilinear(grid, p) for p in pts])
    np.testing.assert_allclose(sample_grid_numpy(grid, pts), direct, atol=1e-12)
    g_t = torch.tensor(np.moveaxis(grid, -1, 0))
    np.testing.assert_allclose(sample_grid_torch(g_t, torch.tensor(pts)).numpy(), direct, atol=1e-12)
    gate = np.array([0.5, -1.0, 2.0])
    fused = _gated_trilinear(np.ascontiguousarray(grid), gate, pts, GRID_HALF)
    np.testing.assert_allclose(fused, gate * np.tanh(direct), atol=1e-12)


def test_trilinear_reproduces_linear_functions():
    m = 8
    h = 2 * GRID_HALF / m
    c = -GRID_HALF + (np.arange(m) + 0.5) * h
    cx, cy, cz = np.meshgrid(c, c, c, indexing="ij")
    grid = np.stack([1 + 2 * cx - cy + 0.5 * cz], axis=-1)
    pts = np.random.default_rng(1).uniform(c[0], c[-1], size=(100, 3))
    want = 1 + 2 * pts[:, 0] - pts[:, 1] + 0.5 * pts[:, 2]
    np.testing.assert_allclose(sample_grid_numpy(grid, pts)[:, 0], want, atol=1e-12)
