"""Carrying per-point colours onto a mesh.

Each mesh vertex takes the inverse-distance-weighted mean colour of its ``k`` nearest input points
(weights ``1 / d^2``; a vertex on top of a point takes that point's colour). Colours are handled as
8-bit sRGB values, as PLY files store them (``red green blue`` uchar); float inputs are read as 0-1.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InvalidPointCloudError

DEFAULT_K = 8


def as_rgb8(colors, n_points: int) -> np.ndarray:
    """Validate per-point colours and return them as (N, 3) float64 in 0-255.

    Accepts (N, 3) or (N, 4) arrays (alpha is ignored), integer (0-255) or float (0-1).
    """
    try:
        c = np.asarray(colors)
    except Exception:  # pragma: no cover - numpy raises many types here
        raise InvalidPointCloudError("colors cannot be read as an array") from None
    if c.ndim != 2 or c.shape[1] not in (3, 4):
        raise InvalidPointCloudError(f"colors must have shape (N, 3) or (N, 4), got {c.shape}")
    if c.shape[0] != n_points:
        raise InvalidPointCloudError(f"colors and points differ in length ({c.shape[0]} and {n_points})")
    if c.dtype.kind not in "fiu":
        raise InvalidPointCloudError(f"colors must be numeric, got dtype {c.dtype}")
    c = c[:, :3].astype(np.float64)
    if np.asarray(colors).dtype.kind == "f":
        c = np.nan_to_num(c, nan=0.0, posinf=1.0, neginf=0.0) * 255.0
    return np.clip(c, 0.0, 255.0)


def transfer_colors(vertices: np.ndarray, points: np.ndarray, colors: np.ndarray, k: int = DEFAULT_K,
                    tree=None) -> np.ndarray:
    """Colour of every vertex from the nearest points.

    Parameters
    ----------
    vertices : (V, 3) float
        Mesh vertices, in the frame of ``points``.
    points : (N, 3) float
    colors : (N, 3) float
        Colours of the points in 0-255 (see :func:`as_rgb8`).
    k : int
        Neighbours per vertex.

    Returns
    -------
    (V, 3) uint8
    """
    if len(vertices) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    tree = tree if tree is not None else cKDTree(points)
    k = int(min(max(1, k), len(points)))
    d, idx = tree.query(vertices, k=k, workers=-1)
    if k == 1:
        d, idx = d[:, None], idx[:, None]
    w = 1.0 / np.maximum(d, 1e-12) ** 2
    w /= w.sum(axis=1, keepdims=True)
    rgb = np.einsum("vk,vkc->vc", w, colors[idx])
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
