"""Reading point clouds (by extension: PLY, LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD) and meshes (PLY);
writing meshes as PLY or OBJ.

Each point-cloud format has its reader module beside this one (``ply``, ``las``, ``e57``,
``text``, ``pcd``; ``cloud`` holds what they return). Writing goes to a temporary file in the
destination folder that is renamed over the destination only when complete, so a failed or
interrupted write never leaves a partial file behind; the file gets the permissions ``open()``
would give it (the umask's, or the replaced file's own), and the free space is checked first.
A mesh made from recentred points is written back in the file's coordinates (``offset``), in
float64.
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
from pathlib import Path

import numpy as np

from ..errors import OutputPathError, PointCloudFileError
from .cloud import PointCloud
from .ply import open_ply as _open_ply
from .ply import vertex_element as _vertex_element

MESH_FORMATS = (".ply", ".obj")


POINT_FORMATS = {
    ".ply": "ply", ".las": "las", ".laz": "las", ".e57": "e57", ".pcd": "pcd",
    ".xyz": "text", ".pts": "text", ".txt": "text", ".csv": "text",
}
"""Point-cloud file extensions read by :func:`read_point_cloud`, and the reader of each."""


def _columns(el, names, path, what):
    props = {p.name for p in el.properties}
    missing = [n for n in names if n not in props]
    if missing:
        return None, missing
    try:
        return np.stack([np.asarray(el[n], dtype=np.float64) for n in names], axis=1), []
    except Exception as exc:
        raise PointCloudFileError(f"{path}: cannot read {what} ({exc})") from None


def read_point_cloud(path, *, classes=None, columns=None, progress=None) -> PointCloud:
    """Read a point cloud, the format chosen by the file's extension (:data:`POINT_FORMATS`).

    PLY (``io/ply.py``), LAS/LAZ (``io/las.py``, laspy with lazrs), E57 (``io/e57.py``, pye57),
    XYZ/PTS/TXT/CSV (``io/text.py``), PCD (``io/pcd.py``). Returns a :class:`~.cloud.PointCloud`
    whose ``points`` (N, 3) float64 are relative to its ``offset`` (zeros unless the coordinates
    are large, see :mod:`.cloud`). ``classes``: keep only points of these classification codes
    (LAS, or files with a classification column); ``columns``: the column roles of a text file
    (``"x y z i r g b"``); ``progress(fraction)``.

    Raises
    ------
    PointCloudFileError
        Unknown extension; missing, unreadable, truncated or corrupt file; no usable points; a
        library the format needs is not installed (the message says what to install).
    """
    p = Path(path)
    if p.is_dir():
        raise PointCloudFileError(f"{p}: is a folder, not a point-cloud file")
    if not p.exists():
        raise PointCloudFileError(f"{p}: no such file")
    kind = POINT_FORMATS.get(p.suffix.lower())
    if kind is None:
        known = " ".join(sorted(POINT_FORMATS))
        raise PointCloudFileError(f"{p}: unsupported point-cloud format '{p.suffix or '(none)'}' (read: {known})")
    if columns is not None and kind != "text":
        raise PointCloudFileError(f"{p}: column names apply to text files (.xyz .pts .txt .csv) only")
    if kind == "ply":
        from .ply import read_ply

        return read_ply(p, classes=classes, progress=progress)
    if kind == "las":
        from .las import read_las

        return read_las(p, classes=classes, progress=progress)
    if kind == "e57":
        from .e57 import read_e57

        return read_e57(p, classes=classes, progress=progress)
    if kind == "pcd":
        from .pcd import read_pcd

        return read_pcd(p, classes=classes, progress=progress)
    from .text import read_text

    return read_text(p, columns=columns, classes=classes, progress=progress)


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


def _umask() -> int:
    """This process's umask, read without changing it where Linux allows (else set and restored)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _new_file_mode(path: Path) -> int:
    """The permission bits ``open(path, "w")`` would leave: the existing file's, else 0o666 less the umask."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except OSError:
        return 0o666 & ~_umask()


def _check_space(path: Path, size: int | None) -> None:
    if size is None:
        return
    try:
        usage = shutil.disk_usage(path.parent if str(path.parent) else ".")
    except OSError:
        return
    free = usage.free
    if usage.total > 0 and size > free:  # pseudo file systems (/proc) report no size: the write says
        raise OutputPathError(
            f"{path}: not enough space in {path.parent}: the file needs {size / 2**20:,.1f} MiB, "
            f"{free / 2**20:,.1f} MiB are free"
        )


def _atomic_write(path: Path, write, formats=MESH_FORMATS, size: int | None = None) -> None:
    path = check_output_path(path, formats)
    _check_space(path, size)
    mode = _new_file_mode(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    try:
        os.fchmod(fd, mode)
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
    path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
    colors: np.ndarray | None = None, *, offset=None,
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
    offset : (3,) float or None
        Added to ``vertices`` in float64 (the :attr:`~.cloud.PointCloud.offset` of recentred
        points). When it is non-zero the positions are written in float64 (PLY ``double``, OBJ
        with 15 significant digits) so that map coordinates keep their millimetres; otherwise
        float32 as before.

    Raises
    ------
    OutputPathError
        Bad extension or folder, not enough free space for the file, or a failed write (the
        destination is then untouched).
    """
    p = Path(path)
    wide = offset is not None and bool(np.any(np.asarray(offset, dtype=np.float64)))
    if wide:
        v = np.asarray(vertices, dtype=np.float64) + np.asarray(offset, dtype=np.float64)
    else:
        v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int32)
    n = None if normals is None else np.asarray(normals, dtype=np.float32)
    c = None if colors is None else np.asarray(colors, dtype=np.uint8)
    per_vertex = v.itemsize * 3 + (12 if n is not None else 0) + (3 if c is not None else 0)
    if p.suffix.lower() == ".obj":
        digits = 60 if wide else 40
        size = len(v) * (digits + (30 if n is not None else 0)) + len(f) * 24
        _atomic_write(p, lambda fh: _write_obj(fh, v, f, n, c), size=size)
    else:
        size = 512 + len(v) * per_vertex + len(f) * 13
        _atomic_write(p, lambda fh: _write_ply_mesh(fh, v, f, n, c), size=size)
    return p


def _write_ply_mesh(fh, v, f, n, c=None):
    kind, code = ("double", "<f8") if v.dtype == np.float64 else ("float", "<f4")
    props = [f"property {kind} x", f"property {kind} y", f"property {kind} z"]
    fields = [("x", code), ("y", code), ("z", code)]
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
    fmt = "%.15g" if v.dtype == np.float64 else "%.7g"
    if c is None:
        _write_rows(fh, "v", v, fmt)
    else:
        vc = np.concatenate([v.astype(np.float64), c.astype(np.float64) / 255.0], axis=1)
        _write_rows(fh, "v", vc, fmt)
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
