"""The learned kernel at inference time: features and weights for the core's solver and evaluator.

Given the augmented constraints ``x +- eps n`` (unit box) of one input, :meth:`LearnedKernel.prepare`
runs the feature network once (PyTorch on the CPU without gradients, or its NumPy twin
:class:`~nkf_model.kernel.feature_net_numpy.NumpyFeatureNet` when PyTorch is absent), keeps the
feature grid as a NumPy array and returns what :func:`nkf_model.fit.solve.solve_dense` /
:func:`~nkf_model.fit.solve.solve_falkon` and :class:`~nkf_model.fit.solve.KernelFunction` need:

* the homogeneous constraints ``a_i = w_i [x_i : phi(x_i) : 1]`` and targets ``w_i y_i``. Scaling
  ``a_i`` by the per-point weight ``w_i`` scales ``K(., a_i)`` by ``w_i`` (the kernel is homogeneous
  of degree one in each argument), so the plain solve ``(G' + lam I) g = w y`` with ``G' = W G W`` is
  the weighted fit ``(W G W + lam I) g = W y`` of the paper, and ``f(x) = sum_j g_j K(x, a_j)``;
* ``phi``: unit-box points (N, 3) -> features (N, d) float64, by trilinear interpolation of the
  grid in NumPy (no PyTorch call per chunk of grid points).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..points.normalise import GRID_HALF
from .feature_net_numpy import sample_grid_numpy
from .neural_spline import homogeneous


def _softplus(x):
    return np.logaddexp(0.0, x)


@nb.njit(inline="always")
def _cell(v, half, scale, m):  # pragma: no cover - compiled
    s = (v + half) * scale - 0.5
    s = min(max(s, 0.0), m - 1.0)
    k = min(int(math.floor(s)), m - 2) if m > 1 else 0
    return k, s - k


@nb.njit(parallel=True, nogil=True, cache=True)
def _gated_trilinear(grid, gate, x, half):  # pragma: no cover - compiled
    """``gate * tanh(trilinear(grid, x))``: grid (M, M, M, d), gate (d,), x (N, 3) -> (N, d).

    The same interpolation as :func:`nkf_model.kernel.feature_net.sample_grid_numpy` (values at cell
    centres, border values extended outside), fused with the gate.
    """
    m = grid.shape[0]
    d = grid.shape[3]
    n = x.shape[0]
    out = np.zeros((n, d))
    scale = m / (2.0 * half)
    for i in nb.prange(n):
        i0, f0 = _cell(x[i, 0], half, scale, m)
        i1, f1 = _cell(x[i, 1], half, scale, m)
        i2, f2 = _cell(x[i, 2], half, scale, m)
        for a in range(2):
            wa = f0 if a else 1.0 - f0
            for b in range(2):
                wb = wa * (f1 if b else 1.0 - f1)
                for cc in range(2):
                    w = wb * (f2 if cc else 1.0 - f2)
                    row = grid[i0 + a, i1 + b, i2 + cc]
                    for c in range(d):
                        out[i, c] += w * row[c]
        for c in range(d):
            out[i, c] = gate[c] * math.tanh(out[i, c])
    return out


@dataclass
class Prepared:
    """Inputs of the solve for one point cloud.

    Attributes
    ----------
    a : (2N, 3 + d + 1) float64
        Weighted homogeneous constraints.
    y : (2N,) float64
        Weighted targets.
    weights : (2N,) float64 or None
        Per-constraint weights ``w``, if the model has them.
    phi : callable
        Unit-box points (M, 3) -> features (M, d) float64.
    """

    a: np.ndarray
    y: np.ndarray
    weights: np.ndarray | None
    phi: object


class LearnedKernel:
    """A trained feature network ready for inference (see the module docstring)."""

    def __init__(self, net, meta: dict):
        # net: a FeatureNet (PyTorch) or a NumpyFeatureNet (backend "numpy"); both have the same
        # config, learned_dim, gate and constant_feature().
        self.net = net.eval()
        self.meta = meta
        self.config = net.config
        self.backend = getattr(net, "backend", "torch")
        gate = net.gate
        self.gate = np.array(gate.detach().double().numpy() if hasattr(gate, "detach") else gate, dtype=np.float64)

    @property
    def feature_dim(self) -> int:
        return self.config.feature_dim

    def feature_grid(self, xa: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Raw feature grid (M, M, M, C) float64 for constraints ``xa`` (2N, 3) and labels (2N,)."""
        if self.backend == "numpy":
            return np.ascontiguousarray(np.moveaxis(self.net.grid_features(xa, y), 0, -1))
        import torch

        # One intra-op thread: the network is small (about 0.1 s), and on a busy machine a second
        # OpenMP thread made it several times slower, not faster.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with torch.no_grad():
                g = self.net.grid_features(
                    torch.as_tensor(xa, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32)
                )
        finally:
            torch.set_num_threads(threads)
        return np.ascontiguousarray(g.permute(1, 2, 3, 0).double().numpy())

    def prepare(self, xa: np.ndarray, y: np.ndarray, feature_scale: float = 1.0) -> Prepared:
        """Features, weights and homogeneous constraints for augmented points (see the module).

        ``feature_scale`` in [0, 1] multiplies the learned spatial features (not the learned constant
        feature): 0 leaves the Neural Spline kernel on ``[x : c : 1]``, the learned kernel's scale
        without its conditioning on the input (see ``nkf_model.pipeline.reconstruct.NKF_FEATURE_NOISE``).
        """
        if not 0.0 <= feature_scale <= 1.0:
            raise ValueError(f"feature_scale must be in [0, 1], got {feature_scale!r}")
        grid = self.feature_grid(xa, y)
        d = self.net.learned_dim
        feat = np.ascontiguousarray(grid[..., :d])
        gate = self.gate
        const = self.net.constant_feature() if self.config.const_channel else None

        def phi(x):
            if feature_scale == 0.0:
                # No spatial features: the kernel on [x : c : 1] (or [x : 1]), the same Gram as with
                # zero features and cheaper to evaluate.
                return np.full((len(x), 1 if const is not None else 0), const if const is not None else 0.0)
            f = _gated_trilinear(feat, gate, np.ascontiguousarray(x, dtype=np.float64), GRID_HALF)
            if feature_scale != 1.0:
                f *= feature_scale
            if const is None:
                return f
            out = np.empty((len(f), d + 1))
            out[:, 0] = const
            out[:, 1:] = f
            return out

        a = homogeneous(xa, phi(xa))
        w = None
        if self.config.point_weights:
            rho = sample_grid_numpy(np.ascontiguousarray(grid[..., d : d + 1]), xa)[:, 0]
            w = np.exp(-_softplus(rho))
            a = a * w[:, None]
            y = y * w
        return Prepared(a=a, y=np.asarray(y, np.float64), weights=w, phi=phi)
