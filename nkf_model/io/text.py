"""Text point clouds: XYZ, PTS, TXT, CSV (one point per line), parsed with NumPy.

* Separators: spaces or tabs, commas, or semicolons (found from the first data line).
* Leading lines that are not rows of numbers are skipped; the last of them names the columns when
  its names are recognised (``x y z``, ``nx ny nz`` / ``normal_x`` / ``Nx``, ``r g b`` / ``red``,
  ``intensity`` / ``i``, ``classification``; CloudCompare's ``//X,Y,Z,R,G,B`` too). A PTS file's
  first line, the point count, is checked against the rows read.
* Without names the columns are recognised by their count and values: x y z, then among intensity
  (one column), colours (three columns of 0-255 integers or 0-1 values) and normals (three columns of
  unit length), in the orders the common writers use (PTS: ``x y z i r g b``). When that is
  ambiguous or impossible, the reader says so and asks for a header line (or ``columns=``).
* Read in chunks of ``CHUNK`` lines; a line that is not numbers, or with another column count,
  stops the read with its line number.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError
from .cloud import Gatherer, PointCloud, color_scale, colors_to_uint8

CHUNK = 50_000
MAX_HEADER_LINES = 64

ALIASES = {
    "x": "x", "y": "y", "z": "z",
    "nx": "nx", "ny": "ny", "nz": "nz", "normal_x": "nx", "normal_y": "ny", "normal_z": "nz",
    "normalx": "nx", "normaly": "ny", "normalz": "nz", "n_x": "nx", "n_y": "ny", "n_z": "nz",
    "r": "r", "g": "g", "b": "b", "red": "r", "green": "g", "blue": "b",
    "i": "i", "intensity": "i", "reflectance": "i",
    "classification": "class", "class": "class", "label": "class",
}
ROLES = ("x", "y", "z", "nx", "ny", "nz", "r", "g", "b", "i", "class")

# Column layouts after x y z, by the count of extra columns, most common first.
# n: normals (3), c: colours (3), i: intensity (1).
LAYOUTS = {
    0: [()],
    1: [("i",)],
    3: [("n",), ("c",)],
    4: [("i", "c"), ("c", "i"), ("n", "i"), ("i", "n")],
    6: [("c", "n"), ("n", "c")],
    7: [("i", "c", "n"), ("c", "n", "i"), ("n", "c", "i"), ("c", "i", "n"), ("i", "n", "c"), ("n", "i", "c")],
}
WIDTH = {"n": 3, "c": 3, "i": 1}
EXPAND = {"n": ("nx", "ny", "nz"), "c": ("r", "g", "b"), "i": ("i",)}


def _numbers(line: str, sep: str | None) -> list[str] | None:
    parts = line.split(sep) if sep else line.split()
    parts = [t.strip() for t in parts]
    if parts and parts[-1] == "" and sep:  # a trailing separator
        parts = parts[:-1]
    try:
        for t in parts:
            float(t)
    except ValueError:
        return None
    return parts


def _separator(line: str) -> str | None:
    if ";" in line:
        return ";"
    if "," in line:
        return ","
    return None


def _header_roles(line: str) -> list[str | None] | None:
    """The roles named by a header line, or None when it names no x y z."""
    text = line.strip().lstrip("/#").strip()
    names = [t.strip("\"'") for t in re.split(r"[,;\s]+", text) if t.strip("\"'")]
    roles = []
    for name in names:
        key = name.lower()
        if key.startswith("scalar_"):
            key = key[len("scalar_"):]
        roles.append(ALIASES.get(key))
    return roles if {"x", "y", "z"} <= set(r for r in roles if r) else None


def _parse_columns(columns, path) -> list[str | None]:
    names = [c for c in re.split(r"[,;\s]+", columns) if c] if isinstance(columns, str) else list(columns)
    roles = []
    for name in names:
        role = ALIASES.get(name.lower())
        if role is None and name not in ("_", "-", "skip"):
            raise PointCloudFileError(
                f"{path}: unknown column name '{name}' (use x y z nx ny nz r g b intensity classification, "
                f"or _ to skip a column)"
            )
        roles.append(role)
    if not {"x", "y", "z"} <= set(roles):
        raise PointCloudFileError(f"{path}: the columns must include x, y and z")
    return roles


def _is_unit(block: np.ndarray) -> bool:
    norm = np.linalg.norm(block, axis=1)
    return bool(np.mean(np.abs(norm - 1.0) < 0.02) > 0.95)


def _is_color(block: np.ndarray) -> bool:
    if block.size == 0 or block.min() < 0:
        return False
    if block.max() <= 1.0:
        return True
    return bool(block.max() <= 255 and np.all(block == np.round(block)))


def guess_roles(sample: np.ndarray, path) -> list[str | None]:
    """Roles of the columns of ``sample`` (rows, columns) from their count and values."""
    k = sample.shape[1] - 3
    if k < 0:
        raise PointCloudFileError(f"{path}: has {sample.shape[1]} columns; x y z need at least 3")
    for layout in LAYOUTS.get(k, []):
        ok, col = True, 3
        for part in layout:
            block = sample[:, col : col + WIDTH[part]]
            if part == "n" and not _is_unit(block) or part == "c" and not _is_color(block):
                ok = False
                break
            col += WIDTH[part]
        if ok:
            return ["x", "y", "z"] + [r for part in layout for r in EXPAND[part]]
    raise PointCloudFileError(
        f"{path}: cannot tell what its {sample.shape[1]} columns are; add a header line naming them "
        f"(for example 'x y z nx ny nz red green blue') or give the columns (--columns)"
    )


def _bad_line(lines, first_lineno: int, sep, ncols: int, path) -> PointCloudFileError:
    for j, line in enumerate(lines):
        if not line.strip():
            continue
        parts = _numbers(line, sep)
        shown = line.strip()[:40]
        if parts is None:
            return PointCloudFileError(f"{path}: line {first_lineno + j} is not a row of numbers: '{shown}'")
        if len(parts) != ncols:
            return PointCloudFileError(
                f"{path}: line {first_lineno + j} has {len(parts)} columns, the lines before have {ncols}"
            )
    return PointCloudFileError(f"{path}: cannot parse the lines from {first_lineno} on")


def _count_lines(path) -> int:
    """Lines in the file (an upper bound on its rows), counted in binary blocks: the arrays are
    then allocated once, and the peak memory stays near the arrays kept."""
    count, last = 0, b"\n"
    with open(path, "rb") as fh:
        while block := fh.read(1 << 24):
            count += block.count(b"\n")
            last = block[-1:]
    return count + (last != b"\n")


def read_text(path, *, columns=None, classes=None, progress=None, chunk_lines: int = CHUNK) -> PointCloud:
    """Read an XYZ/PTS/TXT/CSV point cloud.

    Returns a :class:`~.cloud.PointCloud` with points (N, 3) float64 relative to its offset and,
    as the columns say, normals (N, 3) float64, colours (N, 3) uint8 (0-1 values scaled by 255),
    intensity (N,) float32, classification (N,) uint8. ``columns``: the column roles in order
    (``"x y z i r g b"``, ``_`` skips one), instead of a header line or the guess.
    ``progress(fraction)`` after each chunk (by bytes read).

    Raises
    ------
    PointCloudFileError
        Missing or binary file, no rows, columns that cannot be recognised, a line that is not
        numbers or has another column count, a PTS count that does not match.
    """
    p = Path(path)
    if not p.is_file():
        raise PointCloudFileError(f"{p}: no such file" if not p.exists() else f"{p}: is not a file")
    size = max(p.stat().st_size, 1)
    try:
        fh = open(p, encoding="utf-8-sig", errors="strict", newline=None)  # -sig: a BOM is not a column name
    except PermissionError:
        raise PointCloudFileError(f"{p}: permission denied") from None
    except OSError as exc:
        raise PointCloudFileError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    with fh:
        try:
            return _read(fh, p, size, columns, classes, progress, chunk_lines)
        except UnicodeDecodeError:
            raise PointCloudFileError(f"{p}: not a text point cloud (it holds binary data)") from None
        except OSError as exc:
            raise PointCloudFileError(f"{p}: cannot be read ({exc.strerror or exc})") from None


def _read(fh, p, size, columns, classes, progress, chunk_lines) -> PointCloud:
    lineno = 0
    header_roles = None
    pts_count = None
    first = None
    while first is None:
        line = fh.readline()
        if line == "":
            break
        lineno += 1
        if not line.strip():
            continue
        if _numbers(line, _separator(line)) is not None:
            parts = _numbers(line, _separator(line))
            if len(parts) == 1 and pts_count is None and lineno <= 2 and "." not in parts[0]:
                pts_count = int(float(parts[0]))  # PTS: the point count
                continue
            first = line
            break
        if lineno > MAX_HEADER_LINES:
            raise PointCloudFileError(f"{p}: no rows of numbers in its first {MAX_HEADER_LINES} lines")
        roles = _header_roles(line)
        if roles is not None:
            header_roles = roles
    if first is None:
        raise PointCloudFileError(f"{p}: the file holds no points")
    sep = _separator(first)
    ncols = len(_numbers(first, sep))
    first_lineno = lineno

    def chunks():
        start, lines = first_lineno, [first]
        while True:
            lines += itertools.islice(fh, chunk_lines - len(lines))
            if not lines:
                return
            yield start, lines
            if len(lines) < chunk_lines:
                return
            start, lines = start + len(lines), []

    roles = None
    if columns is not None:
        roles = _parse_columns(columns, p)
    elif header_roles is not None:
        roles = header_roles
    if roles is not None and len(roles) != ncols:
        raise PointCloudFileError(
            f"{p}: {'--columns' if columns is not None else 'the header line'} names {len(roles)} columns, "
            f"line {first_lineno} has {ncols}"
        )
    g = Gatherer(p, expected=_count_lines(p), classes=classes)
    scale = None
    read_bytes = 0
    for start, lines in chunks():
        try:
            with np.errstate(all="ignore"):
                block = np.loadtxt(lines, delimiter=sep, dtype=np.float64, ndmin=2, comments=None)
        except ValueError:
            raise _bad_line(lines, start, sep, ncols, p) from None
        if block.shape[1] != ncols:
            raise _bad_line(lines, start, sep, ncols, p)
        if roles is None:
            roles = guess_roles(block[np.isfinite(block).all(axis=1)][:10_000], p)
        idx = {r: j for j, r in enumerate(roles) if r is not None}
        if classes is not None and "class" not in idx:
            raise PointCloudFileError(f"{p}: has no classification column to filter by class")
        normals = block[:, [idx["nx"], idx["ny"], idx["nz"]]] if {"nx", "ny", "nz"} <= idx.keys() else None
        rgb = None
        if {"r", "g", "b"} <= idx.keys():
            raw = block[:, [idx["r"], idx["g"], idx["b"]]]
            if scale is None:
                scale = color_scale(raw)
            rgb = colors_to_uint8(np.nan_to_num(raw), scale)
        g.add(
            block[:, [idx["x"], idx["y"], idx["z"]]],
            normals=normals,
            colors=rgb,
            intensity=block[:, idx["i"]].astype(np.float32) if "i" in idx else None,
            classification=np.nan_to_num(block[:, idx["class"]]).astype(np.uint8) if "class" in idx else None,
        )
        if progress is not None:
            read_bytes += sum(len(s) for s in lines)
            progress(min(1.0, read_bytes / size))
    rows = g.n + g.skipped + g.filtered
    if pts_count is not None and pts_count != rows:
        raise PointCloudFileError(f"{p}: its first line says {pts_count:,} points, the file holds {rows:,} rows")
    kind = p.suffix.lower().lstrip(".").upper() or "text"
    return g.finish(format=f"{kind} text" if kind != "text" else "text")
