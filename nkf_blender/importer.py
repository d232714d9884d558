"""File > Import > Point Cloud: LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD and PLY through ``nkf_model``'s
readers (``nkf_model.io.files.read_point_cloud``), also by drag and drop into the 3D viewport.

Every file is read first (a progress bar in the window manager), and only when all of them read
well are objects added, so a bad file adds nothing (one ERROR report, the operator cancelled, no
undo step). Each file becomes a Point Cloud object (or, with **Vertex-Only Mesh**, a mesh of loose
vertices like Blender's own PLY import) with the attributes named as the PLY importer names them:
``normal`` (FLOAT_VECTOR), ``Col`` (FLOAT_COLOR, the file's 8-bit sRGB values), and
``intensity`` (FLOAT) and ``classification`` (INT) when present. Large (map) coordinates are
recentred near the origin: the offset is stored on the object as ``nkf_offset`` (three doubles;
the file's coordinates are the positions plus it) and :data:`EXPORT_IDNAME` writes meshes back in
those coordinates. E57 scanner positions become empties parented to the cloud, marked
``nkf_scanner``; the NKF panel's Viewpoint orientation uses them. The whole import is one undo step.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper, ImportHelper

EXTENSIONS = (".las", ".laz", ".e57", ".xyz", ".pts", ".txt", ".csv", ".pcd", ".ply")
OFFSET_PROPERTY = "nkf_offset"
SCANNER_PROPERTY = "nkf_scanner"
EXPORT_IDNAME = "export_mesh.nkf_map_coordinates"
INSTALL_HINT = " (in Blender: Edit > Preferences > Add-ons > NKF > Install Dependencies)"


class ImportFailed(Exception):
    """A file could not be read; the message is one line for the user."""


def _read(path: str, classes, progress):
    from nkf_model.errors import NKFInputError
    from nkf_model.io.files import read_point_cloud

    try:
        return read_point_cloud(path, classes=classes, progress=progress)
    except NKFInputError as exc:
        msg = str(exc)
        if "needs the Python package" in msg:
            msg += INSTALL_HINT
        raise ImportFailed(msg) from None
    except MemoryError:
        raise ImportFailed(f"{path}: not enough memory to read it") from None


def parse_classes(text: str):
    """``"2, 6"`` -> (2, 6); empty -> None. Raises :class:`ImportFailed` on anything else."""
    text = text.strip()
    if not text:
        return None
    try:
        codes = tuple(int(t) for t in text.replace(" ", "").split(",") if t)
    except ValueError:
        codes = ()
    if not codes or any(not 0 <= c <= 255 for c in codes):
        raise ImportFailed(f"Classes: classification codes 0-255 separated by commas, got '{text}'")
    return codes


def _set(attrs, name, kind, key, values):
    attr = attrs.new(name, kind, "POINT")
    attr.data.foreach_set(key, np.ascontiguousarray(values).ravel())
    return attr


def build_object(context, name: str, cloud, *, as_mesh: bool, scanners: bool = True, source: str = ""):
    """Add an object for ``cloud`` (an ``nkf_model.io.cloud.PointCloud`` read from the file
    ``source``) to the active collection, selected and active; return it."""
    n = len(cloud.points)
    me = bpy.data.meshes.new(name)
    me.vertices.add(n)
    me.attributes["position"].data.foreach_set("vector", cloud.points.astype(np.float32).ravel())
    if cloud.normals is not None:
        _set(me.attributes, "normal", "FLOAT_VECTOR", "vector", cloud.normals.astype(np.float32))
    if cloud.colors is not None:
        rgba = np.ones((n, 4), dtype=np.float32)
        rgba[:, :3] = cloud.colors / 255.0
        col = me.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
        col.data.foreach_set("color_srgb", rgba.ravel())
        me.color_attributes.active_color = col
        me.color_attributes.default_color_name = col.name
    if cloud.intensity is not None:
        _set(me.attributes, "intensity", "FLOAT", "value", cloud.intensity.astype(np.float32))
    if cloud.classification is not None:
        _set(me.attributes, "classification", "INT", "value", cloud.classification.astype(np.int32))
    me.update()
    ob = bpy.data.objects.new(name, me)
    context.collection.objects.link(ob)
    view_layer = context.view_layer
    for other in view_layer.objects.selected:
        if other is not None:
            other.select_set(False)
    ob.select_set(True)
    view_layer.objects.active = ob
    if not as_mesh:
        with context.temp_override(active_object=ob, object=ob, selected_objects=[ob],
                                   selected_editable_objects=[ob]):
            bpy.ops.object.convert(target="POINTCLOUD")
        if me.users == 0:
            bpy.data.meshes.remove(me)
        sel = ob.data.attributes.get(".select_vert")
        if sel is not None:
            ob.data.attributes.remove(sel)
    ob[OFFSET_PROPERTY] = [float(v) for v in cloud.offset]
    ob["nkf_import"] = f"{Path(source).name}: {cloud.describe()}"  # what was read, for the user
    if scanners and cloud.viewpoints is not None:
        for i, vp in enumerate(cloud.viewpoints):
            empty = bpy.data.objects.new(f"{name} scanner {i + 1}", None)
            empty.empty_display_type = "PLAIN_AXES"
            empty.empty_display_size = max(0.1, float(np.ptp(cloud.points, axis=0).max()) * 0.02)
            empty.parent = ob
            empty.location = tuple(float(v) for v in vp)
            empty[SCANNER_PROPERTY] = True
            context.collection.objects.link(empty)
    view_layer.update()
    return ob


def import_files(context, paths, *, as_mesh=False, classes=None, scanners=True, progress=None):
    """Read every file in ``paths``, then add one object per file; return the objects.

    Raises :class:`ImportFailed` (nothing added) when a file cannot be read."""
    clouds = []
    for k, path in enumerate(paths):
        def part(fraction, k=k):
            if progress is not None:
                progress((k + fraction) / len(paths))

        clouds.append((path, _read(path, classes, part)))
    return [build_object(context, Path(path).stem, cloud, as_mesh=as_mesh, scanners=scanners, source=path)
            for path, cloud in clouds]


class IMPORT_SCENE_OT_nkf_point_cloud(bpy.types.Operator, ImportHelper):
    """Import point clouds: LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD or PLY (large coordinates are
    recentred, the offset kept on the object)"""

    bl_idname = "import_scene.nkf_point_cloud"
    bl_label = "Import Point Cloud"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ""
    filter_glob: bpy.props.StringProperty(default=";".join(f"*{e}" for e in EXTENSIONS), options={"HIDDEN"})
    files: bpy.props.CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: bpy.props.StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    as_mesh: bpy.props.BoolProperty(
        name="Vertex-Only Mesh",
        description="Make a mesh of loose vertices (as Blender's PLY import does) instead of a Point Cloud object",
        default=False,
    )
    classes: bpy.props.StringProperty(
        name="Classes",
        description="Keep only points of these classification codes, separated by commas "
                    "(LAS/LAZ: 2 ground, 6 building); empty keeps all",
        default="",
    )
    scanners: bpy.props.BoolProperty(
        name="Scanner Positions",
        description="Add an empty at each scanner position of an E57 file (used by NKF's Viewpoint orientation)",
        default=True,
    )

    def _paths(self):
        if self.files and self.directory:
            names = [f.name for f in self.files if f.name]
            if names:
                return [str(Path(self.directory) / n) for n in names]
        return [self.filepath] if self.filepath else []

    def invoke(self, context, event):
        if self.directory and self.files:  # dropped on the viewport: ask for the options only
            return self.invoke_popup(context)
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        paths = self._paths()
        if not paths:
            self.report({"ERROR"}, "NKF: no file given to import")
            return {"CANCELLED"}
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        try:
            objs = import_files(
                context, paths, as_mesh=self.as_mesh, classes=parse_classes(self.classes), scanners=self.scanners,
                progress=lambda f: wm.progress_update(int(1000 * f)),
            )
        except ImportFailed as exc:
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        total = sum(len(o.data.points) if o.type == "POINTCLOUD" else len(o.data.vertices) for o in objs)
        self.report({"INFO"}, f"NKF: imported {total:,} points into {', '.join(o.name for o in objs)}")
        return {"FINISHED"}


class IO_FH_nkf_point_cloud(bpy.types.FileHandler):
    """Drag and drop of point-cloud files into the 3D viewport."""

    bl_idname = "IO_FH_nkf_point_cloud"
    bl_label = "Point Cloud (NKF)"
    bl_import_operator = IMPORT_SCENE_OT_nkf_point_cloud.bl_idname
    bl_file_extensions = ";".join(EXTENSIONS)

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def object_offset(obj) -> np.ndarray:
    """The ``nkf_offset`` stored on ``obj`` (zeros when none), float64."""
    value = obj.get(OFFSET_PROPERTY) if obj is not None else None
    if value is None or len(value) != 3:
        return np.zeros(3)
    return np.array([float(v) for v in value], dtype=np.float64)


def mesh_arrays(context, obj):
    """World-space vertices (V, 3) float64 and triangles (F, 3) of ``obj``'s evaluated mesh."""
    depsgraph = context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        me.calc_loop_triangles()
        v = np.empty(len(me.vertices) * 3, dtype=np.float32)
        me.attributes["position"].data.foreach_get("vector", v)
        f = np.empty(len(me.loop_triangles) * 3, dtype=np.int32)
        me.loop_triangles.foreach_get("vertices", f)
    finally:
        ev.to_mesh_clear()
    m = np.array(obj.matrix_world, dtype=np.float64)
    v = v.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    return v, f.reshape(-1, 3)


class EXPORT_MESH_OT_nkf_map_coordinates(bpy.types.Operator, ExportHelper):
    """Write the active mesh as PLY or OBJ in the coordinates of the file its points came from
    (the object's NKF offset added back, in double precision)"""

    bl_idname = EXPORT_IDNAME
    bl_label = "Export Mesh in Map Coordinates"
    bl_options = {"REGISTER"}

    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply;*.obj", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH"

    def execute(self, context):
        from nkf_model.errors import NKFInputError
        from nkf_model.io.files import write_mesh

        obj = context.active_object
        verts, faces = mesh_arrays(context, obj)
        if len(faces) == 0:
            self.report({"ERROR"}, f"NKF: '{obj.name}' has no faces to export")
            return {"CANCELLED"}
        try:
            path = write_mesh(self.filepath, verts, faces, offset=object_offset(obj))
        except NKFInputError as exc:
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"NKF: wrote {path} ({len(faces):,} triangles)")
        return {"FINISHED"}


def _menu_import(self, context):
    self.layout.operator(IMPORT_SCENE_OT_nkf_point_cloud.bl_idname,
                         text="Point Cloud (.las .laz .e57 .xyz .pts .txt .pcd .ply)")


def _menu_export(self, context):
    self.layout.operator(EXPORT_IDNAME, text="Mesh in Map Coordinates (.ply .obj, NKF)")


CLASSES = (IMPORT_SCENE_OT_nkf_point_cloud, IO_FH_nkf_point_cloud, EXPORT_MESH_OT_nkf_map_coordinates)


def register_menus() -> None:
    bpy.types.TOPBAR_MT_file_import.append(_menu_import)
    bpy.types.TOPBAR_MT_file_export.append(_menu_export)


def unregister_menus() -> None:
    bpy.types.TOPBAR_MT_file_import.remove(_menu_import)
    bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
