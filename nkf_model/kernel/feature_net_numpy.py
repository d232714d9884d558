"""The feature network's forward pass in NumPy: NKF inference without PyTorch.

:class:`NumpyFeatureNet` reads the same tensors (by name, from the same safetensors file) as
:class:`nkf_model.kernel.feature_net.FeatureNet` and computes the same feature grid, layer by layer:

* cell assignment and position in the cell in float32, exactly as PyTorch does it on the float32
  inputs (so every constraint lands in the same cell);
* the per-cell PointNet (three linear layers, ReLU) and the max-pool per cell (empty cells: 0);
* the U-Net: 3x3x3 convolutions with zero padding (one matrix product per layer), GroupNorm
  (4 groups, or 1 when the width is not divisible by 4; eps 1e-5), ReLU, 2x max-pooling, and
  trilinear upsampling with ``align_corners=False``, then the 1x1x1 head.

Everything after the cell assignment runs in float64, so the result differs from PyTorch's float32
network only by PyTorch's own rounding (``tests/test_feature_net_numpy.py`` holds it to 1e-5 of the
features' scale). :func:`sample_grid_numpy` is the trilinear interpolation of the finished grid at
arbitrary points (also used with PyTorch). No PyTorch, SciPy or numba import here.
"""

from __future__ import annotations

import numpy as np

from ..points.normalise import GRID_HALF
from .feature_config import FeatureConfig

GROUP_NORM_EPS = 1e-5


def sample_grid_numpy(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """NumPy float64 twin of :func:`nkf_model.kernel.feature_net.sample_grid_torch`.

    Parameters
    ----------
    grid : (M, M, M, C) float array
        Channels last (C-contiguous for fast gathers).
    x : (N, 3) float
        Unit-box positions.

    Returns
    -------
    (N, C) float64
    """
    m = grid.shape[0]
    s = (np.asarray(x, dtype=np.float64) + GRID_HALF) * (m / (2.0 * GRID_HALF)) - 0.5
    s = np.clip(s, 0.0, m - 1)
    i0 = np.minimum(np.floor(s).astype(np.int64), m - 2) if m > 1 else np.zeros(s.shape, np.int64)
    f = s - i0
    flat = grid.reshape(m * m * m, -1)
    out = np.zeros((len(s), flat.shape[1]))
    for a in (0, 1):
        wa = f[:, 0] if a else 1.0 - f[:, 0]
        for b in (0, 1):
            wb = wa * (f[:, 1] if b else 1.0 - f[:, 1])
            for c in (0, 1):
                w = wb * (f[:, 2] if c else 1.0 - f[:, 2])
                idx = ((i0[:, 0] + a) * m + (i0[:, 1] + b)) * m + (i0[:, 2] + c)
                out += w[:, None] * flat[idx]
    return out


def cell_coordinates_numpy(x: np.ndarray, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Twin of :func:`nkf_model.kernel.feature_net.cell_coordinates` on float32 inputs, in float32.

    Returns ``flat`` (N,) int64 cell numbers and ``local`` (N, 3) float32 positions in the cell.
    """
    x = np.asarray(x, dtype=np.float32)
    s = (x + np.float32(GRID_HALF)) * np.float32(grid / (2.0 * GRID_HALF))
    ijk = np.clip(np.floor(s), 0, grid - 1)
    local = s - ijk - np.float32(0.5)
    ijk = ijk.astype(np.int64)
    flat = (ijk[:, 0] * grid + ijk[:, 1]) * grid + ijk[:, 2]
    return flat, local


def conv3d(x: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``torch.nn.Conv3d`` (stride 1, zero padding ``k // 2``) of ``x`` (C_in, A, B, C)."""
    cout, cin, k = weight.shape[0], weight.shape[1], weight.shape[2]
    shape = x.shape[1:]
    n = int(np.prod(shape))
    if k == 1:
        out = weight[:, :, 0, 0, 0] @ x.reshape(cin, n)
    else:
        # im2col: one (C_out, k^3 C_in) x (k^3 C_in, n) product (27 small ones were 15 times slower).
        p = k // 2
        xp = np.pad(x, ((0, 0), (p, p), (p, p), (p, p)))
        cols = np.empty((k, k, k, cin) + shape)
        for dz in range(k):
            for dy in range(k):
                for dx in range(k):
                    cols[dz, dy, dx] = xp[:, dz : dz + shape[0], dy : dy + shape[1], dx : dx + shape[2]]
        w2 = np.ascontiguousarray(weight.transpose(0, 2, 3, 4, 1)).reshape(cout, k * k * k * cin)
        out = w2 @ cols.reshape(k * k * k * cin, n)
    out += bias[:, None]
    return out.reshape((cout, *shape))


def group_norm(x: np.ndarray, groups: int, gamma: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """``torch.nn.GroupNorm(groups, C)`` of ``x`` (C, ...): biased variance, eps 1e-5, then affine."""
    c = x.shape[0]
    g = x.reshape(groups, -1)
    mean = g.mean(axis=1, keepdims=True)
    var = ((g - mean) ** 2).mean(axis=1, keepdims=True)
    g = (g - mean) / np.sqrt(var + GROUP_NORM_EPS)
    y = g.reshape(x.shape)
    shape = (c,) + (1,) * (x.ndim - 1)
    return y * gamma.reshape(shape) + beta.reshape(shape)


def max_pool2(x: np.ndarray) -> np.ndarray:
    """``F.max_pool3d(x, 2)`` of ``x`` (C, A, B, C') with even sides."""
    c, a, b, d = x.shape
    return x.reshape(c, a // 2, 2, b // 2, 2, d // 2, 2).max(axis=(2, 4, 6))


def _resize_axis(x: np.ndarray, axis: int, size: int) -> np.ndarray:
    """Linear resampling of one axis as ``F.interpolate(..., align_corners=False)`` does it."""
    n = x.shape[axis]
    scale = n / size
    src = np.maximum(scale * (np.arange(size) + 0.5) - 0.5, 0.0)
    i0 = np.minimum(src.astype(np.int64), n - 1)
    i1 = np.where(i0 < n - 1, i0 + 1, i0)
    lam = np.clip(src - i0, 0.0, 1.0)
    shape = [1] * x.ndim
    shape[axis] = size
    lam = lam.reshape(shape)
    return np.take(x, i0, axis=axis) * (1.0 - lam) + np.take(x, i1, axis=axis) * lam


def upsample_trilinear(x: np.ndarray, size) -> np.ndarray:
    """``F.interpolate(x[None], size=size, mode="trilinear", align_corners=False)[0]``."""
    for axis, s in zip((1, 2, 3), size):
        x = _resize_axis(x, axis, int(s))
    return x


def expected_shapes(config: FeatureConfig) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every tensor that :class:`~nkf_model.kernel.feature_net.FeatureNet` (and so
    a weights file) holds for ``config``; names as in its ``state_dict``."""
    c = config
    if c.grid % (2 ** (c.unet_levels - 1)) != 0:
        raise ValueError(f"grid {c.grid} is not divisible by 2^{c.unet_levels - 1}")
    learned = c.feature_dim - (1 if c.const_channel else 0)
    if learned < 0:
        raise ValueError("feature_dim must be at least 1 with const_channel")
    out_ch = learned + (1 if c.point_weights else 0)
    w = c.pointnet_width
    shapes: dict[str, tuple[int, ...]] = {"gate": (learned,)}
    if c.const_channel:
        shapes["log_c2"] = ()
    for i, (cin, cout) in enumerate([(4, w), (w, w), (w, w)]):
        shapes[f"pointnet.{2 * i}.weight"] = (cout, cin)
        shapes[f"pointnet.{2 * i}.bias"] = (cout,)

    def block(prefix, cin, cout):
        shapes[f"{prefix}.0.weight"] = (cout, cin, 3, 3, 3)
        shapes[f"{prefix}.3.weight"] = (cout, cout, 3, 3, 3)
        for j in (0, 1, 3, 4):
            shapes[f"{prefix}.{j}.bias"] = (cout,)
        for j in (1, 4):
            shapes[f"{prefix}.{j}.weight"] = (cout,)

    widths = [c.unet_width * 2**i for i in range(c.unet_levels)]
    prev = w
    for i, width in enumerate(widths):
        block(f"unet.down.{i}", prev, width)
        prev = width
    for i, width in enumerate(reversed(widths[:-1])):
        block(f"unet.up.{i}", prev + width, width)
        prev = width
    shapes["unet.head.weight"] = (out_ch, prev, 1, 1, 1)
    shapes["unet.head.bias"] = (out_ch,)
    return shapes


class NumpyFeatureNet:
    """Inference-only twin of :class:`~nkf_model.kernel.feature_net.FeatureNet` (see the module).

    Parameters
    ----------
    config : FeatureConfig
    tensors : dict[str, array]
        The network's tensors by ``state_dict`` name (as read from a weights file); checked
        against :func:`expected_shapes` by :func:`nkf_model.kernel.weights.load_weights`.
    """

    backend = "numpy"

    def __init__(self, config: FeatureConfig, tensors: dict):
        self.config = config
        expected = expected_shapes(config)
        self.learned_dim = expected["gate"][0]
        self.out_channels = expected["unet.head.bias"][0]
        self._t = {k: np.asarray(tensors[k], dtype=np.float64) for k in expected}
        self.gate = self._t["gate"].copy()
        self._log_c2 = np.float32(tensors["log_c2"]) if config.const_channel else None

    def eval(self) -> NumpyFeatureNet:
        """For symmetry with ``torch.nn.Module.eval``: inference is all this network does."""
        return self

    def constant_feature(self) -> float:
        """The learned constant feature ``c`` (0 without ``const_channel``), in float64 (PyTorch's
        float32 value is within 1e-7 of it)."""
        if self._log_c2 is None:
            return 0.0
        return float(np.exp(0.5 * float(self._log_c2)))

    def cell_grid(self, x: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """PointNet features of the cells, (pointnet_width, M, M, M) float64; zero in empty cells."""
        m = self.config.grid
        t = self._t
        flat, local = cell_coordinates_numpy(x, m)
        h = np.concatenate([local.astype(np.float64), np.asarray(labels, np.float32).astype(np.float64)[:, None]], 1)
        h = np.maximum(h @ t["pointnet.0.weight"].T + t["pointnet.0.bias"], 0.0)
        h = np.maximum(h @ t["pointnet.2.weight"].T + t["pointnet.2.bias"], 0.0)
        h = h @ t["pointnet.4.weight"].T + t["pointnet.4.bias"]
        cells = np.zeros((m**3, h.shape[1]))
        if len(flat):
            order = np.argsort(flat, kind="stable")
            fs = flat[order]
            starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
            cells[fs[starts]] = np.maximum.reduceat(h[order], starts, axis=0)
        return np.ascontiguousarray(cells.T).reshape(h.shape[1], m, m, m)

    def _block(self, prefix: str, x: np.ndarray) -> np.ndarray:
        t = self._t
        for conv, norm in ((0, 1), (3, 4)):
            x = conv3d(x, t[f"{prefix}.{conv}.weight"], t[f"{prefix}.{conv}.bias"])
            cout = x.shape[0]
            x = group_norm(x, 4 if cout % 4 == 0 else 1, t[f"{prefix}.{norm}.weight"], t[f"{prefix}.{norm}.bias"])
            x = np.maximum(x, 0.0)
        return x

    def grid_features(self, x: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Raw feature grid (C, M, M, M) float64 of constraints ``x`` (N, 3) with labels (N,) (+-1),
        the twin of :meth:`FeatureNet.grid_features <nkf_model.kernel.feature_net.FeatureNet.grid_features>`."""
        h = self.cell_grid(x, labels)
        levels = self.config.unet_levels
        skips = []
        for i in range(levels):
            if i > 0:
                h = max_pool2(h)
            h = self._block(f"unet.down.{i}", h)
            skips.append(h)
        for i, skip in enumerate(reversed(skips[:-1])):
            h = upsample_trilinear(h, skip.shape[1:])
            h = self._block(f"unet.up.{i}", np.concatenate([h, skip], axis=0))
        return conv3d(h, self._t["unet.head.weight"], self._t["unet.head.bias"])
