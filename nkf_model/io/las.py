"""LAS and LAZ point clouds (LiDAR), read with :mod:`laspy` (LAZ through its ``lazrs`` backend).

Read in chunks of ``CHUNK`` points straight into the kept arrays, so the peak memory is about the
arrays kept plus one chunk. Coordinates are the file's scaled values (``X * scale + offset``, in
float64), recentred near the origin with the offset kept (see :mod:`.cloud`). Colours of point
formats 2, 3, 5, 7, 8 and 10 are 16-bit in the standard and scaled to 8 bits (files that store
8-bit values in the 16-bit fields are recognised from their first chunk); intensity is kept as
it is; classification codes (``classes`` filters by them: 2 ground, 6 building, ...). Extra-bytes
dimensions named like normals (``nx``, ``normal_x``, ...) become the normals.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from .cloud import Gatherer, PointCloud, color_scale, colors_to_uint8, require
from .ply import NORMAL_NAMES

CHUNK = 262_144
COLOR_FORMATS = (2, 3, 5, 7, 8, 10)


def _first_line(exc) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_las(path, *, classes=None, progress=None, chunk_size: int = CHUNK) -> PointCloud:
    """Read a LAS or LAZ file (any version laspy reads: 1.0-1.4, point formats 0-10).

    Returns a :class:`~.cloud.PointCloud`: points (N, 3) float64 in the file's units (metres, as a
    rule) relative to ``offset``; colours (N, 3) uint8 for formats with RGB; intensity (N,)
    float32; classification (N,) uint8. ``classes``: iterable of classification codes to keep.
    ``progress(fraction)`` after each chunk.

    Raises
    ------
    PointCloudFileError
        Missing file, laspy or lazrs not installed, not a LAS file, an unsupported point format or
        version, a truncated or corrupt file, no points (of the classes asked for).
    """
    # laspy logs the errors it raises (lazrs' "failed to fill whole buffer" on a truncated LAZ);
    # the one-line message below says it, so its log stays quiet while reading.
    log = logging.getLogger("laspy")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        return _read_las(path, classes, progress, chunk_size)
    finally:
        log.setLevel(level)


def _read_las(path, classes, progress, chunk_size) -> PointCloud:
    p = Path(path)
    if not p.is_file():
        raise PointCloudFileError(f"{p}: no such file" if not p.exists() else f"{p}: is not a file")
    laspy = require("laspy", "LAS/LAZ files", "laspy")
    is_laz = p.suffix.lower() == ".laz"
    if is_laz and not laspy.LazBackend.detect_available():
        raise PointCloudFileError(
            "reading LAZ files needs the Python package 'lazrs', which is not installed: pip install lazrs"
        )
    try:
        reader = laspy.open(str(p))
    except PermissionError:
        raise PointCloudFileError(f"{p}: permission denied") from None
    except laspy.errors.PointFormatNotSupported as exc:
        raise PointCloudFileError(
            f"{p}: unsupported LAS point format {exc} (laspy reads point formats 0-10)"
        ) from None
    except laspy.errors.FileVersionNotSupported as exc:
        raise PointCloudFileError(f"{p}: unsupported LAS version {exc} (laspy reads 1.0-1.4)") from None
    except Exception as exc:  # LaspyException, short or foreign files
        raise PointCloudFileError(f"{p}: not a readable LAS/LAZ file ({_first_line(exc)})") from None
    with reader:
        header = reader.header
        fmt_id = header.point_format.id
        kind = "LAZ" if header.are_points_compressed else "LAS"
        fmt = f"{kind} {header.version.major}.{header.version.minor} point format {fmt_id}"
        total = int(header.point_count)
        dims = {d.lower(): d for d in header.point_format.dimension_names}
        nrm = next((tuple(dims[n] for n in names) for names in NORMAL_NAMES if all(n in dims for n in names)), None)
        has_rgb = fmt_id in COLOR_FORMATS
        g = Gatherer(p, expected=total, classes=classes)
        scale = None
        read = 0
        try:
            for chunk in reader.chunk_iterator(chunk_size):
                n = len(chunk)
                if n == 0:
                    break
                xyz = np.empty((n, 3), dtype=np.float64)
                xyz[:, 0], xyz[:, 1], xyz[:, 2] = chunk.x, chunk.y, chunk.z
                rgb = None
                if has_rgb:
                    raw = np.stack([np.asarray(chunk.red), np.asarray(chunk.green), np.asarray(chunk.blue)], axis=1)
                    if scale is None:
                        scale = color_scale(raw)
                    rgb = colors_to_uint8(raw, scale)
                normals = None
                if nrm is not None:
                    normals = np.stack([np.asarray(chunk[d], np.float64) for d in nrm], axis=1)
                g.add(xyz, normals=normals, colors=rgb, intensity=np.asarray(chunk.intensity, np.float32),
                      classification=np.asarray(chunk.classification, np.uint8))
                read += n
                if progress is not None:
                    progress(min(1.0, read / max(total, 1)))
        except PointCloudFileError:
            raise
        except Exception as exc:  # lazrs / laspy errors on truncated or corrupt data
            raise PointCloudFileError(
                f"{p}: truncated or corrupt {kind} data after {read:,} of {total:,} points ({_first_line(exc)})"
            ) from None
        if read < total:
            raise PointCloudFileError(f"{p}: truncated: its header says {total:,} points, the file holds {read:,}")
    return g.finish(format=fmt)
