"""E57 scans (terrestrial laser scanners), read with :mod:`pye57` (libE57Format).

Every scan in the file is read, in chunks of ``CHUNK`` points, with its pose applied (points in
the file's common frame); points flagged invalid are left out. Cartesian or spherical coordinates
(range, azimuth, elevation; converted as pye57 does). Each scan's position (the translation of
its pose; the origin of its own frame when it has none) becomes a viewpoint, so estimated normals
can be oriented towards the scanner that saw them. Colours (``colorRed ...``, scaled by the file's
colour limits to 0-255) and intensity when every scan has them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from .cloud import Gatherer, PointCloud, colors_to_uint8, require

CHUNK = 262_144
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLORS = ("colorRed", "colorGreen", "colorBlue")


def _first_line(exc) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _color_max(header) -> float:
    try:
        limits = header.node["colorLimits"]
        return float(max(limits[f"color{c}Maximum"].value() for c in ("Red", "Green", "Blue")))
    except Exception:
        return 255.0


def read_e57(path, *, classes=None, progress=None, chunk_size: int = CHUNK) -> PointCloud:
    """Read every scan of an E57 file.

    Returns a :class:`~.cloud.PointCloud`: points (N, 3) float64 in metres relative to
    ``offset``, ``viewpoints`` (scans, 3) the scanner positions in the same frame, colours (N, 3)
    uint8 and intensity (N,) float32 when all scans have them, ``scans`` the number of scans.
    ``progress(fraction)`` after each chunk.

    Raises
    ------
    PointCloudFileError
        Missing file, pye57 not installed, not an E57 file, a scan without Cartesian or spherical
        coordinates, a truncated or corrupt file, no points.
    """
    p = Path(path)
    if not p.is_file():
        raise PointCloudFileError(f"{p}: no such file" if not p.exists() else f"{p}: is not a file")
    if classes is not None:
        raise PointCloudFileError(f"{p}: E57 files have no classification to filter by class")
    pye57 = require("pye57", "E57 files", "pye57")
    try:
        e57 = pye57.E57(str(p))
    except Exception as exc:
        raise PointCloudFileError(f"{p}: not a readable E57 file ({_first_line(exc)})") from None
    try:
        n_scans = e57.scan_count
        if n_scans == 0:
            raise PointCloudFileError(f"{p}: the E57 file holds no 3D scans")
        headers = [e57.get_header(i) for i in range(n_scans)]
        total = sum(int(h.point_count) for h in headers)
        g = Gatherer(p, expected=total)
        viewpoints = []
        read = 0
        for i, h in enumerate(headers):
            fields = set(h.point_fields)
            if set(CARTESIAN) <= fields:
                coords, invalid = CARTESIAN, "cartesianInvalidState"
            elif set(SPHERICAL) <= fields:
                coords, invalid = SPHERICAL, "sphericalInvalidState"
            else:
                raise PointCloudFileError(
                    f"{p}: scan {i + 1} of {n_scans} has no Cartesian or spherical coordinates "
                    f"(its fields: {', '.join(sorted(fields)) or 'none'})"
                )
            wanted = list(coords)
            has_rgb = set(COLORS) <= fields
            if has_rgb:
                wanted += COLORS
            if "intensity" in fields:
                wanted.append("intensity")
            if invalid in fields:
                wanted.append(invalid)
            rot = h.rotation_matrix if h.has_pose() else np.eye(3)
            trans = np.asarray(h.translation, np.float64) if h.has_pose() else np.zeros(3)
            viewpoints.append(trans)
            rgb_scale = 255.0 / _color_max(h) if has_rgb else 1.0
            count = int(h.point_count)
            cap = max(1, min(chunk_size, count))
            bufs, vec = e57.make_buffers(wanted, cap)
            got_scan = 0
            try:
                reader = h.points.reader(vec)
                try:
                    while True:
                        n = reader.read()
                        if n == 0:
                            break
                        cols = {k: v[:n] for k, v in bufs.items()}
                        a, b, c = (np.asarray(cols[k], np.float64) for k in coords)
                        if coords is SPHERICAL:  # range, azimuth, elevation -> x, y, z
                            a, b, c = a * np.cos(c) * np.cos(b), a * np.cos(c) * np.sin(b), a * np.sin(c)
                        xyz = np.stack([a, b, c], axis=1) @ rot.T + trans
                        rgb = None
                        if has_rgb:
                            rgb = colors_to_uint8(np.stack([cols[k] for k in COLORS], axis=1), rgb_scale)
                        inten = np.asarray(cols["intensity"], np.float32) if "intensity" in cols else None
                        if invalid in cols:  # no return (or no coordinates): not a point
                            ok = np.asarray(cols[invalid]) == 0
                            xyz = xyz[ok]
                            rgb = None if rgb is None else rgb[ok]
                            inten = None if inten is None else inten[ok]
                        g.add(xyz, colors=rgb, intensity=inten)
                        got_scan += n
                        read += n
                        if progress is not None:
                            progress(min(1.0, read / max(total, 1)))
                finally:
                    reader.close()
            except PointCloudFileError:
                raise
            except Exception as exc:
                raise PointCloudFileError(
                    f"{p}: truncated or corrupt E57 data in scan {i + 1} of {n_scans} after {got_scan:,} of "
                    f"{count:,} points ({_first_line(exc)})"
                ) from None
            if got_scan < count:
                raise PointCloudFileError(
                    f"{p}: truncated: scan {i + 1} of {n_scans} should hold {count:,} points, it holds {got_scan:,}"
                )
    except PointCloudFileError:
        raise
    except Exception as exc:  # libE57 errors while walking the file's structure
        raise PointCloudFileError(f"{p}: not a readable E57 file ({_first_line(exc)})") from None
    finally:
        try:
            e57.close()
        except Exception:
            pass
    return g.finish(format="E57", scans=n_scans, viewpoints=np.asarray(viewpoints))
