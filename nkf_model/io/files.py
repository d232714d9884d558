"""Reading point clouds and meshes from PLY, writing meshes as PLY or OBJ.

Reading uses :mod:`plyfile` (ASCII and binary PLY). Writing goes to a temporary file in the
destination folder that is renamed over the destination only when complete, so a failed or
interrupted write never leaves a partial file behind.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OutputPathError, PointCloudFileError

MESH_FORMATS = (".ply", ".obj")


@dataclass
class PointCloud:
    """Points read from a file.

    Attributes
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64 or None
        ``None`` when the file has no ``nx ny nz`` properties.
    colors : (N, 3) uint8 or None
        ``red green blue`` when present.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None


def _open_ply(path):
    from plyfile import PlyData

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


def _vertex_element(ply, path):
    try:
        return ply["vertex"]
    except KeyError:
        raise PointCloudFileError(f"{path}: the PLY file has no 'vertex' element") from None


def _columns(el, names, path, what):
    props = {p.name for p in el.properties}
    missing = [n for n in names if n not in props]
    if missing:
        return None, missing
    try:
        return np.stack([np.asarray(el[n], dtype=np.float64) for n in names], axis=1), []
    except Exception as exc:
        raise PointCloudFileError(f"{path}: cannot read {what} ({exc})") from None


def read_point_cloud(path) -> PointCloud:
    """Read a PLY point cloud with ``x y z`` and, if present, ``nx ny nz`` and ``red green blue``.

    Raises
    ------
    PointCloudFileError
        Missing, unreadable or corrupt file, or no ``x y z``.
    """
    ply = _open_ply(path)
    el = _vertex_element(ply, path)
    pts, missing = _columns(el, ("x", "y", "z"), path, "positions")
    if pts is None:
        raise PointCloudFileError(f"{path}: the vertices have no {'/'.join(missing)} properties")
    normals, _ = _columns(el, ("nx", "ny", "nz"), path, "normals")
    colors = None
    props = {p.name for p in el.properties}
    if {"red", "green", "blue"} <= props:
        colors = np.stack([np.asarray(el[c]) for c in ("red", "green", "blue")], axis=1)
        if colors.dtype.kind == "f":
            colors = np.clip(colors * 255.0 + 0.5, 0, 255)
        colors = colors.astype(np.uint8)
    return PointCloud(points=pts, normals=normals, colors=colors)


def read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from PLY: vertices (V, 3) float64 and faces (F, 3) int64."""
    ply = _open_ply(path)
    el = _vertex_element(ply, path)
    verts, missing = _columns(el, ("x", "y", "z"), path, "positions")
    if verts is None:
        raise PointCloudFileError(f"{path}: the vertices have no {'/'.join(missing)} properties")
    try:
        faces_el = ply["face"]
    except KeyError:
        raise PointCloudFileError(f"{path}: the PLY file has no 'face' element") from None
    name = faces_el.properties[0].name
    rows = faces_el[name]
    lengths = np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows))
    if len(rows) and (lengths == 3).all():
        faces = np.stack(rows).astype(np.int64)
    else:  # fan-triangulate polygons
        tris = [[r[0], r[i], r[i + 1]] for r in rows for i in range(1, len(r) - 1)]
        faces = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    return verts, faces


def check_output_path(path, formats=MESH_FORMATS) -> Path:
    """Check that a file in one of ``formats`` can be written to ``path`` before any work is done.

    Raises
    ------
    OutputPathError
        Unknown extension, missing folder, folder not writable, or ``path`` is a folder.
    """
    p = Path(path)
    if p.suffix.lower() not in formats:
        raise OutputPathError(
            f"{p}: unsupported output format '{p.suffix or '(none)'}'; use {' or '.join(formats)}"
        )
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise OutputPathError(f"{p}: is a folder; give a file name ending in {' or '.join(formats)}")
    if not parent.exists():
        raise OutputPathError(f"{p}: the folder {parent} does not exist")
    if not parent.is_dir():
        raise OutputPathError(f"{p}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{p}: the folder {parent} is not writable")
    return p


def _atomic_write(path: Path, write, formats=MESH_FORMATS) -> None:
    path = check_output_path(path, formats)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        _remove(tmp)
        raise OutputPathError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    except BaseException:
        _remove(tmp)
        raise


def _remove(tmp):
    try:
        os.unlink(tmp)
    except OSError:
        pass


def write_mesh(
    path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None, colors: np.ndarray | None = None
) -> Path:
    """Write a triangle mesh as binary PLY or as OBJ, chosen by the extension of ``path``.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    normals : (V, 3) float or None
        Written as ``nx ny nz`` (PLY) or ``vn`` (OBJ) when given.
    colors : (V, 3) uint8 or None
        Per-vertex colours, written as ``red green blue`` uchar (PLY) or as ``v x y z r g b``
        with components in 0-1 (OBJ, as MeshLab and Blender read it).
    """
    p = Path(path)
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int32)
    n = None if normals is None else np.asarray(normals, dtype=np.float32)
    c = None if colors is None else np.asarray(colors, dtype=np.uint8)
    if p.suffix.lower() == ".obj":
        _atomic_write(p, lambda fh: _write_obj(fh, v, f, n, c))
    else:
        _atomic_write(p, lambda fh: _write_ply_mesh(fh, v, f, n, c))
    return p


def _write_ply_mesh(fh, v, f, n, c=None):
    props = ["property float x", "property float y", "property float z"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if n is not None:
        props += ["property float nx", "property float ny", "property float nz"]
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if c is not None:
        props += ["property uchar red", "property uchar green", "property uchar blue"]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", "comment made by nkf_model", f"element vertex {len(v)}"]
        + props
        + [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    )
    fh.write((header + "\n").encode("ascii"))
    rec = np.empty(len(v), dtype=fields)
    rec["x"], rec["y"], rec["z"] = v[:, 0], v[:, 1], v[:, 2]
    if n is not None:
        rec["nx"], rec["ny"], rec["nz"] = n[:, 0], n[:, 1], n[:, 2]
    if c is not None:
        rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    fh.write(rec.tobytes())
    frec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = f
    fh.write(frec.tobytes())


def _write_obj(fh, v, f, n, c=None):
    fh.write(b"# made by nkf_model\n")
    if c is None:
        _write_rows(fh, "v", v, "%.7g")
    else:
        vc = np.concatenate([v.astype(np.float64), c.astype(np.float64) / 255.0], axis=1)
        _write_rows(fh, "v", vc, "%.7g")
    if n is not None:
        _write_rows(fh, "vn", n, "%.5f")
        _write_rows(fh, "f", f + 1, "%d", pattern="{0}//{0}")
    else:
        _write_rows(fh, "f", f + 1, "%d")


def _write_rows(fh, tag, arr, fmt, pattern=None, chunk=200_000):
    for s in range(0, len(arr), chunk):
        block = arr[s : s + chunk]
        if pattern is None:
            lines = "\n".join(f"{tag} " + " ".join(fmt % x for x in row) for row in block)
        else:
            lines = "\n".join(f"{tag} " + " ".join(pattern.format(int(x)) for x in row) for row in block)
        fh.write((lines + "\n").encode("ascii"))


def write_point_cloud(path, points: np.ndarray, normals: np.ndarray | None = None,
                      colors: np.ndarray | None = None) -> Path:
    """Write points as a binary PLY: ``x y z`` (float32), ``nx ny nz`` (float32) when ``normals``
    are given, ``red green blue`` (uchar) when ``colors`` (N, 3) uint8 are given."""
    p = Path(path)
    pts = np.asarray(points, dtype=np.float32)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        rec["nx"], rec["ny"], rec["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    if colors is not None:
        col = np.asarray(colors, dtype=np.uint8)
        rec["red"], rec["green"], rec["blue"] = col[:, 0], col[:, 1], col[:, 2]
    types = {"<f4": "float", "u1": "uchar"}

    def write(fh):
        header = "\n".join(
            ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
            + [f"property {types[t]} {name}" for name, t in fields]
            + ["end_header"]
        )
        fh.write((header + "\n").encode("ascii"))
        fh.write(rec.tobytes())

    _atomic_write(p, write, formats=(".ply",))
    return p
