"""Read oriented points from a Blender object, on the main thread, without changing it.

Supported objects: a Mesh with loose vertices (what PLY import gives), a Mesh with faces, a
PointCloud. Positions and normals are read in the object's local coordinates with
``foreach_get`` into float32 NumPy arrays. Normals come from, in order:

1. the ``normal`` POINT attribute (``bpy.ops.wm.ply_import`` puts nx ny nz there),
2. the ``custom_normal`` POINT attribute,
3. the vertex normals, for a Mesh with faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from .errors import UserError

NORMAL_ATTRIBUTES = ("normal", "custom_normal")
SUPPORTED_TYPES = ("MESH", "POINTCLOUD")


class SourceError(UserError):
    """The object cannot be reconstructed; the message is written for the user."""


@dataclass(frozen=True)
class SourceInfo:
    """What the panel shows about an object, found without reading any arrays.

    ``count`` points; ``normals`` where the normals come from (``None`` when there are none);
    ``problem`` one line when the object cannot be used, else ``""``.
    """

    count: int
    normals: str | None
    problem: str


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


def _has_faces(obj) -> bool:
    return obj.type == "MESH" and len(obj.data.polygons) > 0


def describe(obj) -> SourceInfo:
    """Point count, normal source and any problem, cheaply (safe to call from a panel's draw)."""
    try:
        data = _data(obj)
    except SourceError as exc:
        return SourceInfo(0, None, str(exc))
    count = _count(obj)
    if count == 0:
        return SourceInfo(0, None, f"'{obj.name}' has no points")
    attr = _normal_attribute(data)
    if attr is not None:
        return SourceInfo(count, f"'{attr.name}' attribute", "")
    if _has_faces(obj):
        return SourceInfo(count, "vertex normals", "")
    return SourceInfo(count, None, _no_normals(obj))


def _no_normals(obj) -> str:
    return (
        f"'{obj.name}' has no normals: NKF needs oriented points. Import a PLY with nx ny nz, "
        "or add a 'normal' point attribute"
    )


def read_points(obj) -> tuple[np.ndarray, np.ndarray, str]:
    """Positions (N, 3) float32 and normals (N, 3) float32 in ``obj``'s local coordinates.

    Returns ``(points, normals, normal_source)``. Raises :class:`SourceError` with a message for
    the user when ``obj`` cannot be used. ``obj`` is never modified. A mesh in Edit Mode is read with
    its current edits: they are synced to the mesh (as Blender's own tools do) and read from a
    temporary copy, since attributes cannot be read while the mesh is being edited.
    """
    _data(obj)
    if obj.type == "MESH" and obj.mode == "EDIT":
        obj.update_from_editmode()
        tmp = obj.data.copy()
        try:
            return _read(obj, tmp)
        finally:
            bpy.data.meshes.remove(tmp)
    return _read(obj, obj.data)


def _read(obj, data):
    count = len(data.vertices) if obj.type == "MESH" else len(data.points)
    if count == 0:
        raise SourceError(f"'{obj.name}' has no points")
    pts = np.empty(count * 3, dtype=np.float32)
    data.attributes["position"].data.foreach_get("vector", pts)
    nrm = np.empty(count * 3, dtype=np.float32)
    attr = _normal_attribute(data)
    if attr is not None:
        attr.data.foreach_get("vector", nrm)
        where = f"'{attr.name}' attribute"
    elif obj.type == "MESH" and len(data.polygons) > 0:
        data.vertex_normals.foreach_get("vector", nrm)
        where = "vertex normals"
    else:
        raise SourceError(_no_normals(obj))
    return pts.reshape(-1, 3), nrm.reshape(-1, 3), where
