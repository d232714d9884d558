"""Stage 1: map points into the unit box and back, in float64.

The unit box is ``[-0.5, 0.5]^3``: the bounding box of the input is centred on the origin and
scaled so that its longest side is 1. Working in float64 keeps this exact enough for scans whose
coordinates are around 1e6 (georeferenced data) and for objects a few micrometres wide.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The evaluation grid spans [-GRID_HALF, GRID_HALF]^3 of the unit box: the box plus 5 % on each side,
# so surfaces that bulge past the points' bounding box (and the offset constraints at +-eps) stay inside.
GRID_HALF = 0.55


@dataclass(frozen=True)
class Normalisation:
    """An affine map ``unit = (world - center) / scale``.

    Attributes
    ----------
    center : (3,) float64
        Centre of the input's bounding box, in input units.
    scale : float
        Length of the bounding box's longest side, in input units (> 0).
    """

    center: np.ndarray
    scale: float

    @classmethod
    def fit(cls, points: np.ndarray) -> Normalisation:
        """Fit the map to ``points`` ((N, 3), any float dtype)."""
        p = np.asarray(points, dtype=np.float64)
        lo = p.min(axis=0)
        hi = p.max(axis=0)
        center = 0.5 * (lo + hi)
        scale = float((hi - lo).max())
        return cls(center=center, scale=scale)

    def to_unit(self, points: np.ndarray) -> np.ndarray:
        """World coordinates (N, 3) to unit-box coordinates (N, 3) float64."""
        return (np.asarray(points, dtype=np.float64) - self.center) / self.scale

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Unit-box coordinates (N, 3) to world coordinates (N, 3) float64."""
        return np.asarray(points, dtype=np.float64) * self.scale + self.center
