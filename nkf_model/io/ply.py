"""PLY point clouds (ASCII and binary), read with :mod:`plyfile`.

Property names vary between writers; these are recognised (case-insensitive, CloudCompare's
``scalar_`` prefix ignored):

* positions ``x y z`` (float or double; large ones are recentred, see :mod:`.cloud`);
* normals ``nx ny nz``, ``normal_x normal_y normal_z`` (PCL, Open3D's PLY writer as read back by
  others), ``normalx ...``, ``n_x ...``;
* colours ``red green blue``, ``r g b``, ``diffuse_red ...`` (uchar, ushort scaled from 16 bits,
  or 0-1 floats);
* ``intensity`` (or ``scalar_intensity``), ``classification``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from .cloud import Gatherer, PointCloud, color_scale, colors_to_uint8, require

NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"), ("normalx", "normaly", "normalz"),
                ("n_x", "n_y", "n_z"))
COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
INTENSITY_NAMES = ("intensity", "reflectance")
CLASS_NAMES = ("classification", "class", "label")
CHUNK = 262_144


def open_ply(path):
    """Parse ``path`` with plyfile; one-line :class:`PointCloudFileError` for every failure."""
    PlyData = require("plyfile", "PLY files", "plyfile").PlyData
    p = Path(path)
    if not p.exists():
        raise PointCloudFileError(f"{p}: no such file")
    if p.is_dir():
        raise PointCloudFileError(f"{p}: is a folder, not a PLY file")
    try:
        with open(p, "rb") as fh:
            return PlyData.read(fh)
    except PermissionError:
        raise PointCloudFileError(f"{p}: permission denied") from None
    except OSError as exc:
        raise PointCloudFileError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    except Exception as exc:  # plyfile raises PlyParseError, ValueError, struct errors, ...
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PointCloudFileError(f"{p}: not a valid PLY file ({detail})") from None


def vertex_element(ply, path):
    try:
        return ply["vertex"]
    except KeyError:
        raise PointCloudFileError(f"{path}: the PLY file has no 'vertex' element") from None


def _key(name: str) -> str:
    n = name.lower()
    return n[len("scalar_"):] if n.startswith("scalar_") else n


def property_map(el) -> dict[str, str]:
    """Normalised property name -> the file's own name."""
    out = {}
    for p in el.properties:
        out.setdefault(_key(p.name), p.name)
    return out


def find(props: dict[str, str], options) -> tuple[str, ...] | None:
    """The file's names of the first triple (or single name) of ``options`` that it has."""
    for names in options:
        names = (names,) if isinstance(names, str) else names
        if all(n in props for n in names):
            return tuple(props[n] for n in names)
    return None


def read_ply(path, *, classes=None, progress=None) -> PointCloud:
    """Read a PLY point cloud (the ``vertex`` element; faces, if any, are ignored).

    Returns a :class:`~.cloud.PointCloud` with points (N, 3) float64 relative to its offset,
    normals (N, 3) float64, colours (N, 3) uint8, intensity (N,) float32 and classification (N,)
    uint8 when the file has them under any of the recognised names. ``classes``: keep only those
    classification codes. ``progress(fraction)`` is called as chunks are copied.

    Raises
    ------
    PointCloudFileError
        Missing, unreadable or corrupt file, no ``vertex`` element, or no ``x y z``.
    """
    ply = open_ply(path)
    el = vertex_element(ply, path)
    props = property_map(el)
    xyz_names = find(props, [("x", "y", "z")])
    if xyz_names is None:
        missing = [n for n in ("x", "y", "z") if n not in props]
        raise PointCloudFileError(f"{path}: the vertices have no {'/'.join(missing)} properties")
    nrm_names = find(props, NORMAL_NAMES)
    rgb_names = find(props, COLOR_NAMES)
    int_name = find(props, INTENSITY_NAMES)
    cls_name = find(props, CLASS_NAMES)
    if classes is not None and cls_name is None:
        raise PointCloudFileError(f"{path}: the PLY file has no classification property to filter by class")
    n = el.count
    g = Gatherer(path, expected=n, classes=classes)
    data = el.data
    scale = color_scale(np.stack([data[c][: min(n, CHUNK)] for c in rgb_names], axis=1)) if rgb_names else 1.0
    try:
        for s in range(0, n, CHUNK):
            rows = data[s : s + CHUNK]

            def stack(names, rows=rows):
                return np.stack([np.asarray(rows[c], dtype=np.float64) for c in names], axis=1)

            g.add(
                stack(xyz_names),
                normals=stack(nrm_names) if nrm_names else None,
                colors=colors_to_uint8(np.stack([rows[c] for c in rgb_names], axis=1), scale) if rgb_names else None,
                intensity=np.asarray(rows[int_name[0]], np.float32) if int_name else None,
                classification=np.asarray(rows[cls_name[0]]).astype(np.uint8) if cls_name else None,
            )
            if progress is not None:
                progress(min(1.0, (s + CHUNK) / max(n, 1)))
    except PointCloudFileError:
        raise
    except Exception as exc:
        raise PointCloudFileError(f"{path}: cannot read the vertices ({exc})") from None
    fmt = "PLY" if ply.text is False else "PLY (ASCII)"
    return g.finish(format=fmt)
