"""The feature network phi of Neural Kernel Fields (Williams et al., CVPR 2022, section 3.2).

The grid box ``[-GRID_HALF, GRID_HALF]^3`` of the unit box (the same box the evaluation grid spans)
is cut into ``M^3`` cells. A PointNet in every cell that holds constraint points sees each point's
position inside its cell and its label (+1 outside, -1 inside) and max-pools them to a cell feature
(empty cells: zero). A small 3-D U-Net turns that grid into an ``M^3 x d`` feature grid, and phi at
any point is the trilinear interpolation of that grid.

The kernel sees ``phi(x) = gate * tanh(raw(x))`` with a learnable per-channel ``gate``. At the
start of training the gate is small, so ``[x : phi(x) : 1]`` is almost ``[x : 0 : 1]`` and the
learned kernel starts as the data-free Neural Splines kernel. With ``point_weights`` the network
has one more output channel, ``rho``, and each constraint gets the weight
``w = exp(-softplus(rho))`` in ``(0, 1]`` (see :mod:`nkf_model.kernel.learned_kernel`).

Shapes: the network runs in float32 on one shape at a time; :func:`sample_grid_numpy` gives the
same trilinear interpolation in NumPy float64 for the evaluation of large grids.
:class:`FeatureConfig` lives in :mod:`~nkf_model.kernel.feature_config` and the inference-only
NumPy twin of this network (no PyTorch) in :mod:`~nkf_model.kernel.feature_net_numpy`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..points.normalise import GRID_HALF
from .feature_config import FeatureConfig
from .feature_net_numpy import sample_grid_numpy

__all__ = ["FeatureConfig", "FeatureNet", "UNet3D", "cell_coordinates", "sample_grid_numpy",
           "sample_grid_torch"]


def cell_coordinates(x: torch.Tensor, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell index and position in the cell of unit-box points.

    Parameters
    ----------
    x : (N, 3) tensor
        Unit-box positions; points outside the grid box go to the nearest border cell.
    grid : int
        Cells per side.

    Returns
    -------
    flat : (N,) int64
        ``(i * M + j) * M + k`` of the cell ``(i, j, k)`` holding each point.
    local : (N, 3) float
        Position inside the cell, from -0.5 to 0.5 (further for points outside the box).
    """
    s = (x + GRID_HALF) * (grid / (2.0 * GRID_HALF))
    ijk = torch.clamp(torch.floor(s), 0, grid - 1)
    local = s - ijk - 0.5
    ijk = ijk.long()
    flat = (ijk[:, 0] * grid + ijk[:, 1]) * grid + ijk[:, 2]
    return flat, local


def _block(cin: int, cout: int) -> nn.Sequential:
    groups = 4 if cout % 4 == 0 else 1
    return nn.Sequential(
        nn.Conv3d(cin, cout, 3, padding=1),
        nn.GroupNorm(groups, cout),
        nn.ReLU(inplace=True),
        nn.Conv3d(cout, cout, 3, padding=1),
        nn.GroupNorm(groups, cout),
        nn.ReLU(inplace=True),
    )


class UNet3D(nn.Module):
    """Fully convolutional 3-D U-Net: (1, C_in, M, M, M) -> (1, C_out, M, M, M)."""

    def __init__(self, cin: int, cout: int, width: int, levels: int):
        super().__init__()
        widths = [width * 2**i for i in range(levels)]
        self.down = nn.ModuleList()
        prev = cin
        for w in widths:
            self.down.append(_block(prev, w))
            prev = w
        self.up = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.up.append(_block(prev + w, w))
            prev = w
        self.head = nn.Conv3d(prev, cout, 1)

    def forward(self, x):
        skips = []
        for i, blk in enumerate(self.down):
            if i > 0:
                x = F.max_pool3d(x, 2)
            x = blk(x)
            skips.append(x)
        for blk, skip in zip(self.up, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[-3:], mode="trilinear", align_corners=False)
            x = blk(torch.cat([x, skip], dim=1))
        return self.head(x)


class FeatureNet(nn.Module):
    """Constraint points and labels -> feature grid (C, M, M, M); see the module docstring."""

    def __init__(self, config: FeatureConfig):
        super().__init__()
        c = config
        if c.grid % (2 ** (c.unet_levels - 1)) != 0:
            raise ValueError(f"grid {c.grid} is not divisible by 2^{c.unet_levels - 1}")
        self.config = c
        w = c.pointnet_width
        self.pointnet = nn.Sequential(
            nn.Linear(4, w), nn.ReLU(inplace=True), nn.Linear(w, w), nn.ReLU(inplace=True), nn.Linear(w, w)
        )
        self.learned_dim = c.feature_dim - (1 if c.const_channel else 0)
        if self.learned_dim < 0:
            raise ValueError("feature_dim must be at least 1 with const_channel")
        self.out_channels = self.learned_dim + (1 if c.point_weights else 0)
        self.unet = UNet3D(w, self.out_channels, c.unet_width, c.unet_levels)
        # Small raw features at the start: tanh stays linear and phi stays close to zero.
        nn.init.normal_(self.unet.head.weight, std=0.01)
        nn.init.zeros_(self.unet.head.bias)
        if c.point_weights:
            with torch.no_grad():
                self.unet.head.bias[self.learned_dim] = -4.0  # w = exp(-softplus(-4)) = 0.982
        self.gate = nn.Parameter(torch.full((self.learned_dim,), float(c.gate_init)))
        if c.const_channel:
            self.log_c2 = nn.Parameter(torch.tensor(float(c.const_init)))

    def grid_features(self, x: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """Feature grid of one shape.

        Parameters
        ----------
        x : (N, 3) float32 tensor
            Unit-box constraint positions (points moved by +-eps along their normals).
        labels : (N,) float32 tensor
            +1 for outside constraints, -1 for inside ones.

        Returns
        -------
        (C, M, M, M) float32 tensor
            Raw U-Net outputs: the learned feature channels (``d``, or ``d - 1`` with
        ``const_channel``), then the weight channel if any; indexed
            ``[c, i, j, k]`` for the cell ``(i, j, k)`` along (x, y, z).
        """
        return self.unet(self.cell_grid(x, labels)[None])[0]

    def cell_grid(self, x: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """PointNet features of the cells, (pointnet_width, M, M, M); zero in empty cells."""
        m = self.config.grid
        flat, local = cell_coordinates(x, m)
        h = self.pointnet(torch.cat([local, labels[:, None]], dim=1))
        cells = torch.zeros(m**3, h.shape[1], dtype=h.dtype, device=h.device)
        cells = cells.scatter_reduce(0, flat[:, None].expand_as(h), h, reduce="amax", include_self=False)
        return cells.T.reshape(h.shape[1], m, m, m)

    def point_features(self, grid: torch.Tensor, x: torch.Tensor):
        """``phi`` (N, d) and weights (N,) or None at unit-box points ``x`` (N, 3), float32 tensors.

        With ``const_channel`` the first column of ``phi`` is the learned constant ``c``."""
        raw = sample_grid_torch(grid, x)
        d = self.learned_dim
        phi = self.gate * torch.tanh(raw[:, :d])
        if self.config.const_channel:
            c = torch.exp(0.5 * self.log_c2).to(phi.dtype)
            phi = torch.cat([c.expand(len(x), 1), phi], dim=1)
        w = torch.exp(-F.softplus(raw[:, d])) if self.config.point_weights else None
        return phi, w

    def constant_feature(self) -> float:
        """The learned constant feature ``c`` (0 without ``const_channel``)."""
        return float(torch.exp(0.5 * self.log_c2.detach())) if self.config.const_channel else 0.0


def sample_grid_torch(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a cell-centred grid (C, M, M, M) at points ``x`` (N, 3): (N, C).

    Values sit at the cell centres of the grid box; outside the outermost centres the value of the
    border is extended (``grid_sample`` with ``padding_mode="border"``).
    """
    g = (x / GRID_HALF)[:, [2, 1, 0]].reshape(1, 1, 1, -1, 3).to(grid.dtype)
    out = F.grid_sample(grid[None], g, mode="bilinear", padding_mode="border", align_corners=False)
    return out.reshape(grid.shape[0], -1).T
