"""Writers of small point-cloud files for the format tests: LAS/LAZ with laspy, E57 with pye57, PCD
and text by hand (PCD's binary_compressed with a small LZF compressor written here)."""

from __future__ import annotations

import numpy as np


def sphere(n: int, seed: int = 0, radius: float = 1.0):
    """(n, 3) points on a sphere of ``radius`` and their unit normals, float64."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * radius, d


def write_las(path, xyz, *, rgb=None, intensity=None, classification=None, point_format=3, version="1.2",
              scale=1e-4, offset=None):
    """Write ``xyz`` (n, 3) float64 (file coordinates) as LAS, or LAZ when ``path`` ends in .laz."""
    import laspy

    hdr = laspy.LasHeader(point_format=point_format, version=version)
    hdr.offsets = np.floor(xyz.min(axis=0)) if offset is None else np.asarray(offset, float)
    hdr.scales = np.array([scale] * 3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        las.red, las.green, las.blue = (np.asarray(rgb[:, k], np.uint16) for k in range(3))
    if intensity is not None:
        las.intensity = np.asarray(intensity, np.uint16)
    if classification is not None:
        las.classification = np.asarray(classification, np.uint8)
    las.write(str(path))
    return path


def write_e57(path, scans):
    """``scans``: list of dicts with ``xyz`` (n, 3) in the scanner's frame, ``translation`` (3,),
    ``rotation`` (w, x, y, z) and optional ``rgb`` (n, 3) uint8, ``intensity`` (n,), ``invalid`` (n,) bool."""
    import pye57

    e = pye57.E57(str(path), mode="w")
    for s in scans:
        xyz = s["xyz"]
        data = {"cartesianX": xyz[:, 0].copy(), "cartesianY": xyz[:, 1].copy(), "cartesianZ": xyz[:, 2].copy()}
        if "rgb" in s:
            for k, name in enumerate(("colorRed", "colorGreen", "colorBlue")):
                data[name] = np.ascontiguousarray(s["rgb"][:, k], np.uint8)
        if "intensity" in s:
            data["intensity"] = np.asarray(s["intensity"], np.float32)
        if "invalid" in s:
            data["cartesianInvalidState"] = np.asarray(s["invalid"], np.int8)
        e.write_scan_raw(data, rotation=np.asarray(s.get("rotation", (1.0, 0, 0, 0)), float),
                         translation=np.asarray(s.get("translation", (0.0, 0, 0)), float))
    e.close()
    return path


def lzf_compress(data: bytes) -> bytes:
    """A small LZF compressor (liblzf's stream format: literal runs and back references), greedy,
    with a dictionary of 3-byte prefixes. Slow; for test files only."""
    out = bytearray()
    lit = bytearray()
    table: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush():
        for s in range(0, len(lit), 32):
            run = lit[s : s + 32]
            out.append(len(run) - 1)
            out.extend(run)
        lit.clear()

    while i < n:
        key = data[i : i + 3]
        ref = table.get(key) if len(key) == 3 else None
        table[key] = i
        if ref is not None and 0 < i - ref <= 8192:
            length = 3
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            off = i - ref - 1
            ln = length - 2
            if ln < 7:
                out.append((ln << 5) | (off >> 8))
            else:
                out.append((7 << 5) | (off >> 8))
                out.append(ln - 7)
            out.append(off & 0xFF)
            i += length
        else:
            lit.append(data[i])
            i += 1
    flush()
    return bytes(out)


def pcd_bytes(fields, kind="binary", viewpoint="0 0 0 1 0 0 0", width=None, height=1, types=None):
    """A PCD file of ``fields`` (name -> (n,) array, float32 unless ``types`` says "U4" etc.)."""
    names = list(fields)
    n = len(next(iter(fields.values())))
    types = types or {}
    dt = np.dtype([(k, types.get(k, "<f4")) for k in names])
    rec = np.empty(n, dtype=dt)
    for k in names:
        rec[k] = fields[k]
    size = " ".join(str(dt[k].itemsize) for k in names)
    typ = " ".join({"f": "F", "u": "U", "i": "I"}[dt[k].kind] for k in names)
    width = n if width is None else width
    head = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(names)}\nSIZE {size}\n"
            f"TYPE {typ}\nCOUNT {' '.join('1' for _ in names)}\nWIDTH {width}\nHEIGHT {height}\n"
            f"VIEWPOINT {viewpoint}\nPOINTS {n}\nDATA {kind}\n").encode()
    if kind == "ascii":
        rows = [" ".join(repr(rec[k][i].item()) for k in names) for i in range(n)]
        return head + ("\n".join(rows) + "\n").encode()
    if kind == "binary":
        return head + rec.tobytes()
    raw = b"".join(np.ascontiguousarray(rec[k]).tobytes() for k in names)
    comp = lzf_compress(raw)
    return head + np.array([len(comp), len(raw)], "<u4").tobytes() + comp


def pack_rgb(rgb):
    """PCL's packed colour: 0x00RRGGBB as the bits of a float32."""
    rgb = np.asarray(rgb, np.uint32)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).astype(np.uint32).view(np.float32)
