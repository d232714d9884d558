"""Turn an ``nkf_model.Mesh`` into a new Blender mesh object, on the main thread.

The mesh data are written with ``foreach_set`` on the ``position`` and ``.corner_vert``
attributes (about 0.3 s for a million triangles). Vertices are in the source object's local
coordinates, computed in float64 from ``Mesh.center + Mesh.local_vertices`` before the single cast
to float32, and the new object takes the source's world matrix, so the two line up exactly.
``Mesh.colors`` (when the points had colours) become a BYTE_COLOR POINT attribute ``Col``, the
active and render colour attribute, so the viewport's Attribute colour mode and renders show it.
"""

from __future__ import annotations

import bpy
import numpy as np

SUFFIX = "_nkf"
COLOR_ATTRIBUTE = "Col"
OFFSET_PROPERTY = "nkf_offset"  # as importer.OFFSET_PROPERTY: the result exports back in map coordinates


def mesh_data(name: str, mesh) -> bpy.types.Mesh:
    """A new ``bpy.types.Mesh`` holding ``mesh``'s triangles, smooth shaded."""
    me = bpy.data.meshes.new(name)
    _fill(me, mesh)
    return me


def _fill(me, mesh) -> None:
    """Write ``mesh``'s triangles (and colours) into the empty mesh data ``me``, smooth shaded."""
    local = np.asarray(mesh.local_vertices, dtype=np.float64)
    verts = (local + np.asarray(mesh.center, dtype=np.float64)).astype(np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    nv, nf = len(verts), len(faces)
    me.vertices.add(nv)
    me.loops.add(3 * nf)
    me.polygons.add(nf)
    me.attributes["position"].data.foreach_set("vector", verts.ravel())
    me.attributes[".corner_vert"].data.foreach_set("value", faces.ravel())
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
    me.update(calc_edges=True)
    me.shade_smooth()
    colors = getattr(mesh, "colors", None)
    if colors is not None and len(colors) == nv:
        add_colors(me, colors)


def add_colors(me, colors) -> None:
    """Write (V, 3) uint8 sRGB ``colors`` as the mesh's active BYTE_COLOR POINT attribute ``Col``."""
    rgba = np.ones((len(colors), 4), dtype=np.float32)
    rgba[:, :3] = np.asarray(colors, dtype=np.float32) / 255.0
    attr = me.color_attributes.new(COLOR_ATTRIBUTE, "BYTE_COLOR", "POINT")
    attr.data.foreach_set("color_srgb", rgba.ravel())
    me.color_attributes.active_color = attr
    me.color_attributes.default_color_name = attr.name


TRANSFORM_ATTRIBUTES = (
    "location", "rotation_euler", "rotation_quaternion", "rotation_axis_angle", "scale",
    "delta_location", "delta_rotation_euler", "delta_rotation_quaternion", "delta_scale",
)


def copy_transform(dst, src, matrix_world) -> None:
    """Give ``dst`` the world transform of ``src`` (or ``matrix_world`` when ``src`` is gone).

    Copying the parent and the transform channels reproduces the source's world matrix bit for
    bit (assigning ``matrix_world`` would round-trip it through a decomposition). Constraints or a
    bone/vertex parent fall back to assigning the evaluated world matrix.
    """
    if src is None or len(src.constraints) or (src.parent is not None and src.parent_type != "OBJECT"):
        dst.matrix_world = matrix_world
        return
    if src.parent is not None:
        dst.parent = src.parent
        dst.matrix_parent_inverse = src.matrix_parent_inverse.copy()
    dst.rotation_mode = src.rotation_mode
    for attr in TRANSFORM_ATTRIBUTES:
        value = getattr(src, attr)
        setattr(dst, attr, value.copy() if hasattr(value, "copy") else tuple(value))


def add_object(context, mesh, *, name: str, source, matrix_world, collections) -> bpy.types.Object:
    """Link a new object for ``mesh`` into ``collections``, placed like ``source``, selected and active.

    ``source``: the source object, or None when it was deleted meanwhile (then ``matrix_world``,
    its world matrix when the job started, places the result). ``collections``: the source's
    collections (the scene's collection when empty or all gone). Other objects are deselected, as
    Blender's own add operators do; nothing else changes.
    """
    me = mesh_data(name, mesh)
    ob = bpy.data.objects.new(name, me)
    copy_transform(ob, source, matrix_world)
    if source is not None and source.get(OFFSET_PROPERTY) is not None:  # an imported scan's map offset
        ob[OFFSET_PROPERTY] = [float(v) for v in source[OFFSET_PROPERTY]]
    targets = [c for c in collections if c is not None] or [context.scene.collection]
    targets[0].objects.link(ob)
    _select_only(context, ob)
    return ob


def _select_only(context, ob) -> None:
    view_layer = context.view_layer
    for other in list(view_layer.objects.selected):
        if other is not None:  # a just-removed object reads as None until the next update
            other.select_set(False)
    if ob.name in view_layer.objects:
        ob.select_set(True)
        view_layer.objects.active = ob
    view_layer.update()  # evaluates ob.matrix_world from the copied channels


# Custom properties on a result object: how it was made (shown by the panel, kept in the .blend).
SOURCE_REF = "nkf_source_ref"  # the source object itself (an ID property: follows renames)
STAMP_KEYS = (
    "nkf_source", "nkf_method", "nkf_lambda", "nkf_resolution", "nkf_normals", "nkf_orientation", "nkf_trim",
    "nkf_min_piece", "nkf_close", "nkf_colors", "nkf_max_points", "nkf_device", "nkf_weights", "nkf_points",
    "nkf_seconds", "nkf_solver", "nkf_used",
)


def is_result(ob) -> bool:
    return ob is not None and ob.type == "MESH" and "nkf_source" in ob.keys()


def source_of(ob):
    """The source object of a result (None when it was deleted or ``ob`` is not a result)."""
    if not is_result(ob):
        return None
    ref = ob.get(SOURCE_REF)
    if isinstance(ref, bpy.types.Object) and ref.name in bpy.data.objects:
        return ref
    return None


def find_result(source, source_name: str = ""):
    """The result object that a new run of ``source`` updates in place: the most recently made
    mesh object whose ``nkf_source_ref`` is ``source`` (None when there is none)."""
    if source is None:
        return None
    found = [ob for ob in bpy.data.objects if is_result(ob) and ob.get(SOURCE_REF) == source and ob.users]
    if not found:
        return None
    return max(found, key=lambda ob: float(ob.get("nkf_time", 0.0)))


def replace_mesh(context, ob, mesh):
    """Write ``mesh`` into the result object ``ob``'s mesh data in place: the object, its name,
    transform, materials, modifiers and collections stay; the geometry and the colour attribute
    are replaced. A mesh data block shared with other objects is not touched: ``ob`` gets a copy."""
    me = ob.data
    if me.users > 1:
        me = me.copy()
        ob.data = me
    me.clear_geometry()
    for attr in [a for a in me.color_attributes if a.name == COLOR_ATTRIBUTE]:
        me.color_attributes.remove(attr)
    _fill(me, mesh)
    _select_only(context, ob)
    return ob


def stamp(ob, source, source_name: str, options, stats: dict, seconds: float, *, points_used: int,
          colors: bool) -> None:
    """Record how ``ob`` was made in its custom properties (see :data:`STAMP_KEYS`)."""
    import time

    if source is not None:
        ob[SOURCE_REF] = source
    ob["nkf_source"] = source.name if source is not None else source_name
    ob["nkf_method"] = options.method
    ob["nkf_lambda"] = float(options.lam)
    ob["nkf_resolution"] = int(options.resolution)
    ob["nkf_normals"] = str(stats.get("normals", options.normals_mode))
    ob["nkf_orientation"] = str(options.orientation or "")
    ob["nkf_trim"] = -1.0 if options.trim is None else float(options.trim)  # -1: closed surface
    ob["nkf_min_piece"] = float(options.min_piece)
    ob["nkf_close"] = bool(options.close)
    ob["nkf_colors"] = bool(colors)
    ob["nkf_max_points"] = 0 if options.max_points is None else int(options.max_points)
    ob["nkf_device"] = str(options.device)
    ob["nkf_weights"] = weights_hash(stats.get("weights")) if options.method == "nkf" else ""
    ob["nkf_points"] = int(points_used)
    ob["nkf_seconds"] = round(float(seconds), 3)
    ob["nkf_solver"] = str(stats.get("solver", ""))
    # The kernel the mesh came from: "splines" when the learned kernel's balloon check fell back.
    ob["nkf_used"] = str((stats.get("balloon_check") or {}).get("used", options.method))
    ob["nkf_time"] = time.time()


_HASHES: dict[str, str] = {}


def weights_hash(path) -> str:
    """The first 12 hex digits of the weights file's SHA-256 ("" when unknown)."""
    import hashlib

    if not path:
        return ""
    path = str(path)
    if path not in _HASHES:
        try:
            with open(path, "rb") as f:
                _HASHES[path] = hashlib.file_digest(f, "sha256").hexdigest()[:12]
        except OSError:
            return ""
    return _HASHES[path]


def result_name(source_name: str) -> str:
    return f"{source_name}{SUFFIX}"
