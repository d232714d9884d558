"""PCD point clouds (the Point Cloud Library's format, versions 0.6 and 0.7), parsed with NumPy.

``DATA ascii``, ``binary`` (row-major records, read through a memory map in chunks) and
``binary_compressed`` (column-major, LZF-compressed; decompressed by :func:`lzf_decompress`,
compiled with numba when it is installed). Fields: ``x y z`` (required), ``normal_x normal_y normal_z`` (or
``nx ny nz``), ``rgb``/``rgba`` (PCL packs 8-bit colours into a float32 or uint32), ``r g b``,
``intensity``, ``label``/``classification``; other fields are skipped. Organised clouds
(``HEIGHT`` > 1) mark missing points with NaN: those rows are skipped. A ``VIEWPOINT`` other than
the identity gives the sensor position as a viewpoint.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from .cloud import Gatherer, PointCloud, colors_to_uint8

CHUNK = 262_144
TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
         ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}
NORMALS = (("normal_x", "normal_y", "normal_z"), ("nx", "ny", "nz"))


COMPILED_ABOVE = 8 << 20  # bytes: about 2.5 s in Python, where loading numba starts to pay
LZF_ERRORS = {-1: "literal run past the end", -2: "reference past the end", -3: "reference out of range"}


def lzf_decompress(data: bytes, size: int, compiled: bool | None = None) -> bytearray:
    """Decompress an LZF block (liblzf's format, as PCL writes it) of ``size`` bytes.

    ``compiled=None`` uses the numba loop of :mod:`._lzf_kernels` for blocks of ``COMPILED_ABOVE``
    bytes or more when numba is installed, else this Python loop. On a compressible organised
    640x480 scan: 3.3 MB/s in Python, 269 MB/s compiled; loading numba and the cached loop costs
    about 2-4 s and 117 MB once per process, more than the Python loop takes for small blocks.
    Raises ``ValueError`` on a corrupt or short block."""
    if compiled is None:
        compiled = None if size >= COMPILED_ABOVE else False
    if compiled is None or compiled:
        try:
            from ._lzf_kernels import lzf_into
        except ImportError:
            if compiled:
                raise
        else:
            out = bytearray(size)
            got = lzf_into(np.frombuffer(data, np.uint8), np.frombuffer(out, np.uint8))
            if got < 0:
                raise ValueError(LZF_ERRORS[got])
            if got != size:
                raise ValueError(f"decompressed {got} bytes, expected {size}")
            return out
    src = memoryview(data)
    out = bytearray(size)
    ip, op, n = 0, 0, len(src)
    while ip < n:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n or op + length > size:
                raise ValueError("literal run past the end")
            out[op : op + length] = src[ip : ip + length]
            ip += length
            op += length
        else:  # a back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    raise ValueError("reference past the end")
                length += src[ip]
                ip += 1
            if ip >= n:
                raise ValueError("reference past the end")
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                raise ValueError("reference out of range")
            dist = op - ref
            if dist >= length:
                out[op : op + length] = out[ref : ref + length]
            else:  # overlapping: the last dist bytes repeat
                pattern = bytes(out[ref:op])
                out[op : op + length] = (pattern * (length // dist + 1))[:length]
            op += length
    if op != size:
        raise ValueError(f"decompressed {op} bytes, expected {size}")
    return out


def _header(fh, path):
    """The header's keys and values, and the number of lines it took."""
    meta = {}
    lines = 0
    while True:
        raw = fh.readline()
        lines += 1
        if not raw:
            raise PointCloudFileError(f"{path}: not a PCD file (no DATA line in its header)")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudFileError(f"{path}: not a PCD file (binary data in its header)") from None
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        key = key.upper()
        meta[key] = rest.split()
        if key == "DATA":
            return meta, lines
        if len(meta) > 20:
            raise PointCloudFileError(f"{path}: not a PCD file")


def _layout(meta, path):
    """(names, numpy dtype of one record, number of points)."""
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in meta:
            raise PointCloudFileError(f"{path}: not a PCD file (no {key} line in its header)")
    names, sizes, types = meta["FIELDS"], meta["SIZE"], meta["TYPE"]
    counts = meta.get("COUNT", ["1"] * len(names))
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise PointCloudFileError(
            f"{path}: unsupported PCD field layout: FIELDS, SIZE, TYPE and COUNT differ in length"
        )
    fields, seen = [], {}
    for name, size, typ, count in zip(names, sizes, types, counts):
        try:
            size, count = int(size), int(count)
        except ValueError:
            raise PointCloudFileError(f"{path}: unsupported PCD field layout: SIZE/COUNT '{size}'/'{count}'") from None
        dt = TYPES.get((typ.upper(), size))
        if dt is None or count < 1:
            raise PointCloudFileError(
                f"{path}: unsupported PCD field layout: field '{name}' TYPE {typ} SIZE {size} COUNT {count}"
            )
        if name in ("x", "y", "z") and count != 1:
            raise PointCloudFileError(f"{path}: unsupported PCD field layout: field '{name}' has COUNT {count}")
        key = name if name not in seen else f"{name}__{len(seen)}"  # PCL pads with repeated "_" fields
        seen[name] = True
        fields.append((key, dt, (count,)) if count > 1 else (key, dt))
    if not all(c in seen for c in ("x", "y", "z")):
        raise PointCloudFileError(f"{path}: the PCD file has no x/y/z fields (its fields: {' '.join(names)})")
    dtype = np.dtype(fields)
    try:
        if "POINTS" in meta:
            n = int(meta["POINTS"][0])
        else:
            n = int(meta["WIDTH"][0]) * int(meta.get("HEIGHT", ["1"])[0])
    except (ValueError, IndexError, KeyError):
        raise PointCloudFileError(f"{path}: not a PCD file (no valid POINTS or WIDTH line)") from None
    if n < 0:
        raise PointCloudFileError(f"{path}: negative POINTS in its header")
    return dtype, n


def _viewpoint(meta):
    vp = meta.get("VIEWPOINT")
    if not vp or len(vp) != 7:
        return None
    try:
        t = np.array([float(v) for v in vp[:3]])
        q = np.array([float(v) for v in vp[3:]])
    except ValueError:
        return None
    if not np.any(t) and np.allclose(q, [1, 0, 0, 0]):
        return None
    return t.reshape(1, 3)


def _add(g, rec):
    names = rec.dtype.names
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    normals = None
    for trio in NORMALS:
        if all(c in names for c in trio):
            normals = np.stack([rec[c] for c in trio], axis=1).astype(np.float64)
            break
    rgb = None
    packed = "rgb" if "rgb" in names else ("rgba" if "rgba" in names else None)
    if packed is not None:
        v = np.ascontiguousarray(rec[packed])
        bits = v.view(np.uint32) if v.dtype.itemsize == 4 else v.astype(np.uint32)
        rgb = np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1).astype(np.uint8)
    elif all(c in names for c in ("r", "g", "b")):
        raw = np.stack([rec["r"], rec["g"], rec["b"]], axis=1)
        rgb = colors_to_uint8(raw, 255.0 if raw.dtype.kind == "f" and raw.size and raw.max() <= 1 else 1.0)
    inten = np.asarray(rec["intensity"], np.float32) if "intensity" in names else None
    cls_name = "classification" if "classification" in names else ("label" if "label" in names else None)
    cls = np.asarray(rec[cls_name]).astype(np.uint8) if cls_name else None
    g.add(xyz, normals=normals, colors=rgb, intensity=inten, classification=cls)


def read_pcd(path, *, classes=None, progress=None, chunk_size: int = CHUNK) -> PointCloud:
    """Read a PCD file.

    Returns a :class:`~.cloud.PointCloud`: points (N, 3) float64 relative to its offset, normals
    (N, 3) float64, colours (N, 3) uint8, intensity (N,) float32, classification (N,) uint8 (from a
    ``label`` field) when present; ``viewpoints`` (1, 3) from a non-identity ``VIEWPOINT``.

    Raises
    ------
    PointCloudFileError
        Missing file, not a PCD file, an unsupported field layout or DATA kind, a truncated or
        corrupt file, no points.
    """
    p = Path(path)
    if not p.is_file():
        raise PointCloudFileError(f"{p}: no such file" if not p.exists() else f"{p}: is not a file")
    try:
        fh = open(p, "rb")
    except PermissionError:
        raise PointCloudFileError(f"{p}: permission denied") from None
    except OSError as exc:
        raise PointCloudFileError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    with fh:
        meta, header_lines = _header(fh, p)
        dtype, n = _layout(meta, p)
        kind = (meta["DATA"] or ["?"])[0].lower()
        start = fh.tell()
        size = p.stat().st_size
        has_cls = any(c in dtype.names for c in ("classification", "label"))
        if classes is not None and not has_cls:
            raise PointCloudFileError(f"{p}: the PCD file has no label or classification field to filter by class")
        g = Gatherer(p, expected=n, classes=classes)
        if kind == "ascii":
            _read_ascii(fh, p, dtype, n, g, progress, chunk_size, header_lines + 1)
        elif kind == "binary":
            need = n * dtype.itemsize
            if size - start < need:
                raise PointCloudFileError(
                    f"{p}: truncated: its header says {n:,} points ({need:,} bytes), the file holds {size - start:,}"
                )
            mm = np.memmap(p, dtype=dtype, mode="r", offset=start, shape=(n,)) if n else np.empty(0, dtype)
            for s in range(0, n, chunk_size):
                _add(g, np.array(mm[s : s + chunk_size]))
                if progress is not None:
                    progress(min(1.0, (s + chunk_size) / n))
            del mm
        elif kind == "binary_compressed":
            _read_compressed(fh, p, dtype, n, g, progress, chunk_size)
        else:
            raise PointCloudFileError(
                f"{p}: unsupported PCD DATA kind '{kind}' (ascii, binary and binary_compressed are read)"
            )
    return g.finish(format=f"PCD ({kind})", viewpoints=_viewpoint(meta))


def _read_ascii(fh, p, dtype, n, g, progress, chunk_size, lineno):
    ncols = sum(int(np.prod(dtype[name].shape)) if dtype[name].shape else 1 for name in dtype.names)
    got = 0
    while got < n:
        lines = [ln for ln in (fh.readline() for _ in range(min(chunk_size, n - got))) if ln]
        if not lines:
            break
        try:
            flat = np.loadtxt([ln.decode("ascii", "replace") for ln in lines], dtype=np.float64, ndmin=2,
                              comments=None)
        except ValueError:
            for j, ln in enumerate(lines):
                parts = ln.split()
                try:
                    [float(t) for t in parts]
                except ValueError:
                    shown = ln.decode("ascii", "replace").strip()[:40]
                    raise PointCloudFileError(f"{p}: line {lineno + j} is not a row of numbers: '{shown}'") from None
                if len(parts) != ncols:
                    raise PointCloudFileError(
                        f"{p}: line {lineno + j} has {len(parts)} values, the header's fields need {ncols}"
                    ) from None
            raise PointCloudFileError(f"{p}: cannot parse the points from line {lineno} on") from None
        if flat.shape[1] != ncols:
            raise PointCloudFileError(
                f"{p}: the points have {flat.shape[1]} values each, the header's fields need {ncols}"
            )
        rec = np.empty(len(flat), dtype=dtype)
        col = 0
        for name in dtype.names:
            width = int(np.prod(dtype[name].shape)) if dtype[name].shape else 1
            block = flat[:, col : col + width]
            if name in ("rgb", "rgba") and dtype[name].base.kind == "f":
                # ascii PCD writes the packed colour as the float's decimal or as the integer
                as_int = block[:, 0]
                if np.all(as_int == np.round(as_int)) and as_int.max(initial=0) > 1e6:
                    rec[name] = as_int.astype(np.uint32).view(np.float32)
                else:
                    rec[name] = as_int.astype(np.float32)
            else:
                rec[name] = block.reshape(rec[name].shape).astype(dtype[name].base)
            col += width
        _add(g, rec)
        got += len(rec)
        lineno += len(lines)
        if progress is not None:
            progress(min(1.0, got / max(n, 1)))
    if got < n:
        raise PointCloudFileError(f"{p}: truncated: its header says {n:,} points, the file holds {got:,}")


def _read_compressed(fh, p, dtype, n, g, progress, chunk_size):
    head = fh.read(8)
    if len(head) < 8:
        raise PointCloudFileError(f"{p}: truncated: the compressed block's sizes are missing")
    csize, usize = (int(v) for v in np.frombuffer(head, "<u4"))
    if usize != n * dtype.itemsize:
        raise PointCloudFileError(
            f"{p}: corrupt: the compressed block unpacks to {usize:,} bytes, {n:,} points need {n * dtype.itemsize:,}"
        )
    data = fh.read(csize)
    if len(data) < csize:
        raise PointCloudFileError(f"{p}: truncated: the compressed block holds {len(data):,} of {csize:,} bytes")
    try:
        raw = lzf_decompress(data, usize) if usize else bytearray()
    except ValueError as exc:
        raise PointCloudFileError(f"{p}: corrupt compressed data ({exc})") from None
    del data
    # Column-major: each field's values for all points, one field after another. Views, no copies.
    columns, pos = {}, 0
    for name in dtype.names:
        ft = dtype[name]
        width = max(1, int(np.prod(ft.shape)))
        columns[name] = np.frombuffer(raw, dtype=ft.base, count=n * width, offset=pos).reshape((n,) + ft.shape)
        pos += n * ft.itemsize
    for s in range(0, n, chunk_size):
        rec = np.empty(min(chunk_size, n - s), dtype=dtype)
        for name, col in columns.items():
            rec[name] = col[s : s + len(rec)]
        _add(g, rec)
        if progress is not None:
            progress(min(1.0, (s + chunk_size) / n))
