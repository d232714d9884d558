"""Read points, normals and colours from a Blender object, on the main thread, without changing it.

Supported objects: a Mesh with loose vertices (what PLY import gives), a Mesh with faces, a
PointCloud. Positions and normals are read in the object's local coordinates with
``foreach_get`` into float32 NumPy arrays. Normals come from, in order:

1. the ``normal`` POINT attribute (``bpy.ops.wm.ply_import`` puts nx ny nz there),
2. the ``custom_normal`` POINT attribute,
3. the vertex normals, for a Mesh with faces.

A point cloud without any of these is fine: its normals are estimated by ``nkf_model`` (normals
mode Auto or Estimate); only the Given mode requires them. Colours come from a POINT-domain colour
attribute (PLY import makes ``Col``, FLOAT_COLOR, from ``red green blue``): the mesh's render
colour attribute when it is on the points, else ``Col``, else the first one. They are read as
sRGB (``color_srgb``), i.e. the file's 8-bit values, and returned as (N, 3) uint8.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from .errors import UserError

NORMAL_ATTRIBUTES = ("normal", "custom_normal")
COLOR_ATTRIBUTE = "Col"
COLOR_TYPES = ("FLOAT_COLOR", "BYTE_COLOR")
SUPPORTED_TYPES = ("MESH", "POINTCLOUD")


class SourceError(UserError):
    """The object cannot be reconstructed; the message is written for the user."""


@dataclass(frozen=True)
class SourceInfo:
    """What the panel shows about an object, found without reading any arrays.

    ``count`` points; ``normals`` where the normals come from (``None`` when there are none, or
    when the normals mode ignores them); ``colors`` the colour attribute's name or ``None``;
    ``problem`` one line when the object cannot be used, else ``""``.
    """

    count: int
    normals: str | None
    problem: str
    colors: str | None = None


@dataclass(frozen=True)
class SourceData:
    """What :func:`read_points` read: ``points`` (N, 3) float32 and ``normals`` (N, 3) float32 or
    ``None`` (to be estimated), both in the object's local frame; ``normals_from`` where they came
    from; ``colors`` (N, 3) uint8 sRGB or ``None``, ``colors_from`` the attribute's name."""

    points: np.ndarray
    normals: np.ndarray | None
    normals_from: str | None
    colors: np.ndarray | None = None
    colors_from: str | None = None


def _data(obj):
    if obj is None:
        raise SourceError("No active object: select a point cloud (a mesh or point cloud object)")
    if obj.type not in SUPPORTED_TYPES:
        raise SourceError(
            f"'{obj.name}' is a {obj.type.lower().replace('_', ' ')} object; "
            "select a mesh or point cloud object with points"
        )
    return obj.data


def _count(obj) -> int:
    data = obj.data
    return len(data.vertices) if obj.type == "MESH" else len(data.points)


def _normal_attribute(data):
    for name in NORMAL_ATTRIBUTES:
        attr = data.attributes.get(name)
        if attr is not None and attr.domain == "POINT" and attr.data_type == "FLOAT_VECTOR":
            return attr
    return None


def _color_attribute(data):
    """The POINT-domain colour attribute to read, or None."""
    def usable(attr):
        return attr is not None and attr.domain == "POINT" and attr.data_type in COLOR_TYPES

    colors = getattr(data, "color_attributes", None)
    names = []
    if colors is not None and getattr(colors, "default_color_name", ""):
        names.append(colors.default_color_name)
    names.append(COLOR_ATTRIBUTE)
    for name in names:
        attr = data.attributes.get(name)
        if usable(attr):
            return attr
    return next((a for a in data.attributes if usable(a) and not a.name.startswith(".")), None)


def _has_faces(obj) -> bool:
    return obj.type == "MESH" and len(obj.data.polygons) > 0


def _normal_source(obj, data) -> str | None:
    attr = _normal_attribute(data)
    if attr is not None:
        return f"'{attr.name}' attribute"
    if obj.type == "MESH" and len(data.polygons) > 0:
        return "vertex normals"
    return None


def describe(obj, normals_mode: str = "auto") -> SourceInfo:
    """Point count, normal and colour sources and any problem, cheaply (safe to call from a
    panel's draw). ``normals_mode``: ``"auto"``, ``"given"`` or ``"estimate"`` (which ignores the
    object's normals)."""
    try:
        data = _data(obj)
    except SourceError as exc:
        return SourceInfo(0, None, str(exc))
    count = _count(obj)
    if count == 0:
        return SourceInfo(0, None, f"'{obj.name}' has no points")
    attr = _color_attribute(data)
    colors = attr.name if attr is not None else None
    where = _normal_source(obj, data) if normals_mode != "estimate" else None
    if where is None and normals_mode == "given":
        return SourceInfo(count, None, _no_normals(obj), colors)
    return SourceInfo(count, where, "", colors)


def _no_normals(obj) -> str:
    return (
        f"'{obj.name}' has no normals, and Normals is set to Given: choose Auto or Estimate to estimate "
        "them, import a PLY with nx ny nz, or add a 'normal' point attribute"
    )


def read_points(obj, normals_mode: str = "auto", colors: bool = True, depsgraph=None) -> SourceData:
    """Positions, normals and colours of ``obj`` in its local coordinates.

    ``normals_mode`` ``"auto"`` (the object's normals when it has them, else ``None``),
    ``"given"`` (raise :class:`SourceError` when it has none) or ``"estimate"`` (``None``, the
    object's normals are not read). ``colors``: read a colour attribute when there is one.

    Raises :class:`SourceError` with a message for the user when ``obj`` cannot be used. ``obj``
    is never modified. A mesh in Edit Mode is read with its current edits: they are synced to the
    mesh (as Blender's own tools do) and read from a temporary copy, since attributes cannot be
    read while the mesh is being edited.

    ``depsgraph``: read the object as evaluated in it (modifiers and Geometry Nodes applied, what
    the viewport shows) instead of its original data.
    """
    _data(obj)
    if depsgraph is not None and obj.mode != "EDIT":
        ev = obj.evaluated_get(depsgraph)
        if ev.data is not None and ev.type == obj.type:
            return _read(obj, ev.data, normals_mode, colors)
    if obj.type == "MESH" and obj.mode == "EDIT":
        obj.update_from_editmode()
        tmp = obj.data.copy()
        try:
            return _read(obj, tmp, normals_mode, colors)
        finally:
            bpy.data.meshes.remove(tmp)
    return _read(obj, obj.data, normals_mode, colors)


def _read(obj, data, normals_mode: str, colors: bool) -> SourceData:
    count = len(data.vertices) if obj.type == "MESH" else len(data.points)
    if count == 0:
        raise SourceError(f"'{obj.name}' has no points")
    where = _normal_source(obj, data) if normals_mode != "estimate" else None
    if where is None and normals_mode == "given":
        raise SourceError(_no_normals(obj))
    pts = np.empty(count * 3, dtype=np.float32)
    data.attributes["position"].data.foreach_get("vector", pts)
    nrm = None
    if where is not None:
        nrm = np.empty(count * 3, dtype=np.float32)
        attr = _normal_attribute(data)
        if attr is not None:
            attr.data.foreach_get("vector", nrm)
        else:
            data.vertex_normals.foreach_get("vector", nrm)
        nrm = nrm.reshape(-1, 3)
    rgb, rgb_from = None, None
    attr = _color_attribute(data) if colors else None
    if attr is not None:
        rgba = np.empty(count * 4, dtype=np.float32)
        attr.data.foreach_get("color_srgb", rgba)
        rgb = np.clip(np.rint(rgba.reshape(-1, 4)[:, :3] * 255.0), 0, 255).astype(np.uint8)
        rgb_from = attr.name
    return SourceData(pts.reshape(-1, 3), nrm, where, rgb, rgb_from)
