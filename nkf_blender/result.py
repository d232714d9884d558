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
    local = np.asarray(mesh.local_vertices, dtype=np.float64)
    verts = (local + np.asarray(mesh.center, dtype=np.float64)).astype(np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    nv, nf = len(verts), len(faces)
    me = bpy.data.meshes.new(name)
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
    return me


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
    view_layer = context.view_layer
    for other in view_layer.objects.selected:
        other.select_set(False)
    if ob.name in view_layer.objects:
        ob.select_set(True)
        view_layer.objects.active = ob
    view_layer.update()  # evaluates ob.matrix_world from the copied channels
    return ob


def result_name(source_name: str) -> str:
    return f"{source_name}{SUFFIX}"
