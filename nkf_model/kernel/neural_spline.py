"""The Neural Spline kernel (Williams et al. 2021, appendix; Williams et al. 2022, eq. 5).

For homogeneous inputs ``a = [x : phi(x) : 1]`` and ``b`` the kernel of an infinitely wide ReLU
network with Gaussian initialisation, trained in both layers, is::

    K(a, b) = |a| |b| / pi * (sin t + 2 (pi - t) cos t)

where ``t`` is the angle between ``a`` and ``b``. The angle comes from Kahan's stable formula
``t = 2 atan2(| |b| a - |a| b |, | |b| a + |a| b |)``, which stays accurate for the nearly parallel
vectors that neighbouring points give. In terms of the unit vectors ``u = a/|a|`` and
``v = b/|b|`` and ``d2 = |u - v|^2`` (so ``|u + v|^2 = 4 - d2``) the angle term is::

    g(d2) = sin t + 2 (pi - t) cos t,   sin t = sqrt(d2 (4 - d2)) / 2,   cos t = 1 - d2 / 2,
    t = 2 atan2(sqrt(d2), sqrt(4 - d2))

so ``K(a, b) = |a| |b| g(|u - v|^2) / pi``. With ``phi = 0`` this is the data-free Neural Splines
kernel; the learned kernel passes features in ``phi``.

This module holds the reference implementations (NumPy, and PyTorch for the GPU and for autograd).
The fast CPU sums live in :mod:`nkf_model.kernel._numba_kernels`; :mod:`nkf_model.kernel.engines` picks one.
"""

from __future__ import annotations

import math

import numpy as np


def homogeneous(x: np.ndarray, features: np.ndarray | None = None) -> np.ndarray:
    """Build homogeneous kernel inputs ``[x : features : 1]``.

    Parameters
    ----------
    x : (N, 3) float
        Unit-box positions.
    features : (N, d) float or None
        Learned features ``phi(x)``; ``None`` for the Neural Splines kernel (``d = 0``).

    Returns
    -------
    (N, 3 + d + 1) float64
    """
    x = np.asarray(x, dtype=np.float64)
    parts = [x]
    if features is not None:
        parts.append(np.asarray(features, dtype=np.float64))
    parts.append(np.ones((x.shape[0], 1)))
    return np.concatenate(parts, axis=1)


def split_unit(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split homogeneous inputs (N, D) into C-contiguous unit vectors (N, D) and norms (N,)."""
    r = np.linalg.norm(a, axis=1)
    return np.ascontiguousarray(a / r[:, None]), r


def angle_term(d2: np.ndarray) -> np.ndarray:
    """``g(d2) = sin t + 2 (pi - t) cos t`` for ``d2 = |u - v|^2`` of unit vectors (NumPy)."""
    d2 = np.clip(np.asarray(d2, dtype=np.float64), 0.0, 4.0)
    e2 = 4.0 - d2
    t = 2.0 * np.arctan2(np.sqrt(d2), np.sqrt(e2))
    return 0.5 * np.sqrt(d2 * e2) + 2.0 * (math.pi - t) * (1.0 - 0.5 * d2)


def ns_kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Kernel matrix ``K(a_i, b_j)`` by the textbook formula with Kahan's angle (NumPy).

    A direct transcription, O(N M D) memory; meant for tests and small problems.

    Parameters
    ----------
    a : (N, D) float
    b : (M, D) float

    Returns
    -------
    (N, M) float64
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    na = np.linalg.norm(a, axis=1)[:, None, None]
    nb = np.linalg.norm(b, axis=1)[None, :, None]
    p = nb * a[:, None, :]
    q = na * b[None, :, :]
    t = 2.0 * np.arctan2(np.linalg.norm(p - q, axis=2), np.linalg.norm(p + q, axis=2))
    na = na[..., 0]
    nb = nb[..., 0]
    return na * nb / math.pi * (np.sin(t) + 2.0 * (math.pi - t) * np.cos(t))


def ns_kernel_torch(a, b):
    """Kernel matrix ``K(a_i, b_j)`` for torch tensors (N, D) and (M, D), differentiable.

    Uses the unit-vector form of Kahan's formula. The gradient of ``sqrt`` at ``d2 = 0`` (a point
    paired with itself) is replaced by zero, its one-sided limit along the kernel's ridge.
    """
    import torch

    ra = torch.linalg.vector_norm(a, dim=1)
    rb = torch.linalg.vector_norm(b, dim=1)
    u = a / ra[:, None]
    v = b / rb[:, None]
    diff = u[:, None, :] - v[None, :, :]
    d2 = (diff * diff).sum(-1).clamp(0.0, 4.0)
    return (ra[:, None] * rb[None, :] / math.pi) * angle_term_torch(d2)


def _safe_sqrt(x):
    import torch

    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def angle_term_torch(d2):
    """``g(d2)`` for a torch tensor of squared unit-vector distances, differentiable."""
    import torch

    s = _safe_sqrt(d2)
    e = _safe_sqrt(4.0 - d2)
    t = 2.0 * torch.atan2(s, e)
    return 0.5 * s * e + 2.0 * (math.pi - t) * (1.0 - 0.5 * d2)
