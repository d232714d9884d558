"""What every point-cloud reader returns, and how readers gather points chunk by chunk.

:class:`PointCloud` holds coordinates in float64 *relative to an offset*: a file in map
coordinates (LiDAR around 1e5-1e7 m) is recentred near the origin, and ``offset`` (float64) is
kept so that a mesh made from the points can be written back in the file's coordinates
(``points + offset`` is the file's value, to float64 precision). Files whose coordinates all lie
within ``RECENTRE_ABOVE`` of the origin keep a zero offset.

:class:`Gatherer` is the readers' shared accumulator: it takes chunks of rows (any size), drops rows
with non-finite coordinates (counted in ``PointCloud.skipped``), applies a classification filter,
subtracts a provisional offset so that nothing large is ever stored, and writes into preallocated
arrays when the reader knows the row count (else it keeps the chunks and joins them once: at most
twice the kept arrays at the peak). Standard library and NumPy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import PointCloudFileError

RECENTRE_ABOVE = 1.0e4
"""Coordinates are recentred (a non-zero ``offset``) when some coordinate's magnitude exceeds
this (in the file's units): float32, as Blender and most mesh files store positions, keeps about
1 mm at 1e4."""


@dataclass
class PointCloud:
    """Points read from a file.

    Attributes
    ----------
    points : (N, 3) float64
        Positions relative to ``offset``, in the file's units (metres for LAS and E57).
    offset : (3,) float64
        Add to ``points`` for the file's own coordinates; zeros unless they were large.
    normals : (N, 3) float64 or None
        The file's normals (``nx ny nz``, ``normal_x ...``), not renormalised; ``None`` when absent.
    colors : (N, 3) uint8 or None
        Red, green, blue in 0-255 (16-bit and 0-1 colours are scaled).
    intensity : (N,) float32 or None
        The file's intensity or reflectance values, unscaled.
    classification : (N,) uint8 or None
        LAS classification codes (or a ``classification`` column of other formats).
    viewpoints : (K, 3) float64 or None
        Scanner positions relative to ``offset`` (E57 scan poses, a PCD ``VIEWPOINT``).
    format : str
        What was read, for messages: ``"PLY"``, ``"LAZ 1.4 point format 6"``, ``"E57"``, ...
    scans : int
        Scans in the file (E57); 1 for the others.
    skipped : int
        Rows dropped for non-finite coordinates.
    filtered : int
        Rows left out by a classification filter.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    intensity: np.ndarray | None = None
    classification: np.ndarray | None = None
    viewpoints: np.ndarray | None = None
    format: str = "PLY"
    scans: int = 1
    skipped: int = 0
    filtered: int = 0

    def absolute_points(self) -> np.ndarray:
        """(N, 3) float64: the points in the file's own coordinates."""
        return np.asarray(self.points, np.float64) + self.offset

    def describe(self) -> str:
        """What was read, in a few words: ``'LAZ 1.4 point format 3: 12,345 points, colours,
        intensity, classification'``."""
        parts = [f"{len(self.points):,} points"]
        if self.scans > 1:
            parts.append(f"{self.scans} scans")
        for name, value in (("normals", self.normals), ("colours", self.colors),
                            ("intensity", self.intensity), ("classification", self.classification)):
            if value is not None:
                parts.append(name)
        if self.viewpoints is not None:
            k = len(self.viewpoints)
            parts.append(f"{k} scanner position{'s' if k != 1 else ''}")
        if self.skipped:
            parts.append(f"{self.skipped:,} rows with NaN or infinite coordinates skipped")
        if self.filtered:
            parts.append(f"{self.filtered:,} points of other classes left out")
        if np.any(self.offset):
            parts.append("offset " + " ".join(f"{v:.10g}" for v in self.offset))
        return f"{self.format}: " + ", ".join(parts)


def colors_to_uint8(rgb: np.ndarray, scale: float) -> np.ndarray:
    """(n, 3) colours of any numeric type to uint8: ``rgb * scale`` rounded and clipped to 0-255."""
    rgb = np.asarray(rgb)
    if scale == 1.0 and rgb.dtype == np.uint8:
        return rgb
    return np.clip(np.rint(rgb.astype(np.float64) * scale), 0, 255).astype(np.uint8)


def color_scale(rgb: np.ndarray) -> float:
    """The factor that brings colours into 0-255, judged from a sample: 255 for 0-1 floats, 1/257
    for 16-bit values, 1 for 8-bit ones."""
    rgb = np.asarray(rgb)
    if rgb.size == 0:
        return 1.0
    hi = float(np.nanmax(rgb))
    if rgb.dtype.kind == "f" and hi <= 1.0:
        return 255.0
    if hi > 255:
        return 1.0 / 257.0
    return 1.0


class Gatherer:
    """Collect chunks of rows into a :class:`PointCloud` (see the module docstring).

    ``path`` names the file in messages; ``expected`` is the row count when the reader knows it
    (arrays are then allocated once); ``classes`` keeps only rows whose classification is in it
    (a reader that has no classification must not be given ``classes``).
    """

    def __init__(self, path, expected: int | None = None, classes=None):
        self.path = path
        self.expected = expected
        self.classes = None if classes is None else np.asarray(sorted(set(int(c) for c in classes)))
        self.offset = None
        self.n = 0
        self.skipped = 0
        self.filtered = 0
        self._cols: dict[str, list | np.ndarray] = {}
        self._present: set[str] | None = None

    def add(self, xyz, *, normals=None, colors=None, intensity=None, classification=None) -> None:
        """Add ``xyz`` (n, 3) float64 in file coordinates and the optional per-row attributes
        (normals (n, 3), colors (n, 3) uint8, intensity (n,), classification (n,))."""
        xyz = np.asarray(xyz, dtype=np.float64)
        cols = {"normals": normals, "colors": colors, "intensity": intensity, "classification": classification}
        present = {k for k, v in cols.items() if v is not None}
        if self._present is None:
            self._present = present
        elif present != self._present:  # a later scan lacks (or adds) an attribute: drop it everywhere
            self._present &= present
        keep = np.isfinite(xyz).all(axis=1)
        if self.classes is not None:
            cls = cols["classification"]
            if cls is None:
                raise PointCloudFileError(f"{self.path}: has no classification to filter by class")
            in_class = np.isin(cls, self.classes)
            self.filtered += int(np.count_nonzero(keep & ~in_class))
            keep &= in_class
        n_keep = int(np.count_nonzero(keep))
        self.skipped += int(np.count_nonzero(~np.isfinite(xyz).all(axis=1)))
        if n_keep == 0:
            return
        all_kept = n_keep == len(xyz)
        if self.offset is None:
            first = xyz[np.argmax(keep)]
            self.offset = np.round(first) if np.abs(first).max() > RECENTRE_ABOVE else np.zeros(3)
        local = (xyz if all_kept else xyz[keep]) - self.offset
        self._put("points", local, np.float64)
        for name, dtype in (("normals", np.float64), ("colors", np.uint8),
                            ("intensity", np.float32), ("classification", np.uint8)):
            value = cols[name]
            if value is not None:
                value = np.asarray(value)
                self._put(name, value if all_kept else value[keep], dtype)
        self.n += n_keep

    def _put(self, name, value, dtype):
        if self.expected is not None:
            arr = self._cols.get(name)
            if arr is None:
                arr = np.empty((self.expected,) + value.shape[1:], dtype=dtype)
                self._cols[name] = arr
            if self.n + len(value) > len(arr):
                raise PointCloudFileError(f"{self.path}: holds more points than its header says ({len(arr):,})")
            arr[self.n : self.n + len(value)] = value
        else:
            self._cols.setdefault(name, []).append(np.asarray(value, dtype=dtype))

    def finish(self, *, format: str, scans: int = 1, viewpoints=None) -> PointCloud:
        """The :class:`PointCloud`; recentres on the bounding box's rounded centre when the
        coordinates are large. Raises :class:`PointCloudFileError` when no usable point was read.
        ``viewpoints`` (K, 3) in file coordinates."""
        if self.n == 0:
            if self.filtered:
                raise PointCloudFileError(f"{self.path}: no point of the classes asked for ({self.filtered:,} others)")
            if self.skipped:
                raise PointCloudFileError(
                    f"{self.path}: every point has NaN or infinite coordinates: 0 usable points of {self.skipped:,}"
                )
            raise PointCloudFileError(f"{self.path}: the file holds no points")
        out = {}
        for name, value in self._cols.items():
            if name != "points" and name not in self._present:
                continue
            if isinstance(value, list):
                joined = value[0] if len(value) == 1 else np.concatenate(value)
                value.clear()
                out[name] = joined
            elif self.n < 0.9 * len(value):  # an upper bound far above the rows kept: free the rest
                out[name] = value[: self.n].copy()
                self._cols[name] = None
            else:
                out[name] = value[: self.n]
        pts = out["points"]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        absolute = np.maximum(np.abs(lo + self.offset), np.abs(hi + self.offset))
        if absolute.max() > RECENTRE_ABOVE:
            new_offset = np.round(self.offset + (lo + hi) / 2.0)
        else:
            new_offset = np.zeros(3)
        delta = new_offset - self.offset
        if np.any(delta):
            pts -= delta  # in place: no second copy of the points
        vp = None
        if viewpoints is not None and len(viewpoints):
            vp = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3) - new_offset
        return PointCloud(
            points=pts, normals=out.get("normals"), colors=out.get("colors"), offset=new_offset,
            intensity=out.get("intensity"), classification=out.get("classification"), viewpoints=vp,
            format=format, scans=scans, skipped=self.skipped, filtered=self.filtered,
        )


def require(module: str, what: str, install: str):
    """Import ``module`` or raise :class:`PointCloudFileError` saying what to install."""
    from importlib import import_module

    try:
        return import_module(module)
    except ImportError:
        raise PointCloudFileError(
            f"reading {what} needs the Python package '{install}', which is not installed: "
            f"pip install {install}"
        ) from None
