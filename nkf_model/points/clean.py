"""Checking and cleaning the caller's oriented points before anything is computed.

:func:`clean_points` turns whatever the caller passed into finite float64 points with unit
normals, or raises a precise :class:`~nkf_model.errors.NKFInputError`. Rows that cannot be used
(NaN or infinite coordinates, NaN, infinite or zero-length normals, exact duplicates) are dropped
and counted, so the caller can warn about them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import (
    DegenerateInputError,
    InvalidPointCloudError,
    MissingNormalsError,
    TooFewPointsError,
)

MIN_POINTS = 10
# Relative size of the second and third principal extents below which the points are treated as
# lying on a line or a plane (the input then encloses no volume).
FLATNESS_TOLERANCE = 1e-5


@dataclass
class CleanPoints:
    """Usable points and what was dropped to get them.

    Attributes
    ----------
    points : (N, 3) float64
        Finite positions, in the input's units, without exact duplicates.
    normals : (N, 3) float64 or None
        Unit normals (``None`` when they were not required and not given).
    index : (N,) int64
        Row of each kept point in the caller's arrays.
    dropped : dict
        How many rows were dropped, by reason.
    """

    points: np.ndarray
    normals: np.ndarray
    index: np.ndarray
    dropped: dict = field(default_factory=dict)

    def warnings(self) -> list[str]:
        """Human-readable lines describing each kind of dropped row."""
        text = {
            "nonfinite_points": "with NaN or infinite coordinates",
            "bad_normals": "with NaN, infinite or zero-length normals",
            "duplicates": "that duplicate another point",
        }
        return [
            f"dropped {n} point{'s' if n != 1 else ''} {text[k]}"
            for k, n in self.dropped.items()
            if n
        ]


def _as_array(name: str, a) -> np.ndarray:
    if a is None:
        if name == "normals":
            raise MissingNormalsError(
                "normals are required: pass one unit normal per point (x y z nx ny nz)"
            )
        raise InvalidPointCloudError(f"{name} is None")
    try:
        arr = np.asarray(a)
    except Exception as exc:  # pragma: no cover - numpy raises many types here
        raise InvalidPointCloudError(f"{name} cannot be read as an array: {exc}") from None
    if arr.dtype.kind not in "fiu":
        raise InvalidPointCloudError(f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPointCloudError(f"{name} must have shape (N, 3), got {arr.shape}")
    return arr.astype(np.float64, copy=False)


def clean_points(points, normals, *, require_normals: bool = True, allow_flat: bool = False) -> CleanPoints:
    """Validate and clean oriented points.

    Parameters
    ----------
    points : array_like, (N, 3)
        Positions, any real dtype, in any units.
    normals : array_like, (N, 3)
        Normals pointing out of the surface; any positive length (they are normalised). May be
        ``None`` when ``require_normals`` is false (they will be estimated).
    require_normals : bool
        Raise :class:`MissingNormalsError` when ``normals`` is ``None``.
    allow_flat : bool
        Accept points on a plane (an open scan of a flat surface, trimmed afterwards).

    Returns
    -------
    CleanPoints

    Raises
    ------
    InvalidPointCloudError
        Wrong shape or dtype, or point and normal counts differ.
    MissingNormalsError
        ``normals`` is ``None``.
    TooFewPointsError
        Fewer than 10 usable points remain.
    DegenerateInputError
        The points are all identical, or lie on a line or a plane.
    """
    p = _as_array("points", points)
    if normals is None and not require_normals:
        n = np.ones_like(p)  # stand-in, dropped below: only the positions are checked
        given = False
    else:
        n = _as_array("normals", normals)
        given = True
    if p.shape[0] != n.shape[0]:
        raise InvalidPointCloudError(
            f"points and normals differ in length ({p.shape[0]} and {n.shape[0]})"
        )
    dropped = {"nonfinite_points": 0, "bad_normals": 0, "duplicates": 0}
    finite_p = np.isfinite(p).all(axis=1)
    dropped["nonfinite_points"] = int((~finite_p).sum())
    with np.errstate(over="ignore", invalid="ignore"):
        length = np.linalg.norm(n, axis=1)
    good_n = np.isfinite(n).all(axis=1) & np.isfinite(length) & (length > 1e-12)
    dropped["bad_normals"] = int((finite_p & ~good_n).sum())
    keep = finite_p & good_n
    index = np.flatnonzero(keep)
    p = p[keep]
    n = n[keep] / length[keep, None]

    if len(p) >= 1:
        _, first = np.unique(p, axis=0, return_index=True)
        if len(first) < len(p):
            first.sort()
            dropped["duplicates"] = int(len(p) - len(first))
            p, n, index = p[first], n[first], index[first]

    result = CleanPoints(points=p, normals=n if given else None, index=index, dropped=dropped)
    total = int(np.asarray(points).shape[0])
    if len(p) < MIN_POINTS:
        detail = "; ".join(result.warnings())
        raise TooFewPointsError(
            f"{len(p)} usable point{'s' if len(p) != 1 else ''} of {total}; "
            f"at least {MIN_POINTS} are needed" + (f" ({detail})" if detail else "")
        )
    check_spans_volume(p, allow_flat=allow_flat)
    return result


def check_spans_volume(points: np.ndarray, allow_flat: bool = False) -> None:
    """Raise :class:`DegenerateInputError` unless ``points`` (N, 3) span a volume (or, with
    ``allow_flat``, at least a plane)."""
    extent = points.max(axis=0) - points.min(axis=0)
    size = float(extent.max())
    if not size > 0.0 or size <= 1e-12 * max(1.0, float(np.abs(points).max())):
        raise DegenerateInputError("all points are identical: there is no surface to fit")
    centred = (points - points.mean(axis=0)) / size
    s = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(points))
    if s[1] < FLATNESS_TOLERANCE * s[0]:
        raise DegenerateInputError("all points lie on a line: there is no surface to fit")
    if s[2] < FLATNESS_TOLERANCE * s[0] and not allow_flat:
        raise DegenerateInputError(
            "all points lie on a plane: they enclose no volume, so no closed surface can be fit"
        )
