"""The sidebar panel: View3D > Sidebar > NKF.

Shows the active object's point count and where its normals come from, the parameters, Reconstruct
or (while running) live progress with the stage and Cancel, the last run's time and triangle count,
and an actionable message when packages are missing or the object cannot be used. ``draw`` reads
only cheap state (no arrays), so it can run on every redraw.
"""

from __future__ import annotations

import bpy

from . import deps, methods, ops, runner, source
from .prefs import ADDON, wrapped

WRAP = 38


def _deps_box(layout) -> bool:
    """Say what is missing; return True when a reconstruction can run at all."""
    st = deps.status()
    if st.ready and st.torch:
        return True
    box = layout.box()
    col = box.column()
    col.alert = not st.ready
    wrapped(col, st.message(), icon="ERROR" if not st.ready else "INFO", width=WRAP)
    op = box.operator("preferences.addon_show", text="Open Add-on Preferences", icon="PREFERENCES")
    op.module = ADDON
    return st.ready


def draw_panel(layout, context) -> None:
    ready = _deps_box(layout)
    obj = context.active_object
    s = context.scene.nkf_settings

    box = layout.box()
    info = source.describe(obj)
    if obj is None:
        box.label(text="No active object", icon="INFO")
        wrapped(box, "Select a point cloud: a mesh or point cloud object with normals.", width=WRAP)
    else:
        box.label(text=f"{obj.name}: {info.count:,} points", icon="POINTCLOUD_DATA")
        if info.problem:
            col = box.column()
            col.alert = True
            wrapped(col, info.problem, icon="ERROR", width=WRAP)
        else:
            box.label(text=f"Normals: {info.normals}", icon="CHECKMARK")

    col = layout.column()
    col.use_property_split = True
    col.use_property_decorate = False
    col.prop(s, "method")
    if s.method == "NKF":
        ok, why = methods.nkf_available() if ready else (False, "")
        if ready and not ok:
            sub = col.column()
            sub.alert = True
            wrapped(sub, f"NKF unavailable: {why}", icon="ERROR", width=WRAP)
    col.prop(s, "regularization", text="Lambda")
    col.label(text=f"Lambda = {s.regularization:.2g}")
    col.prop(s, "resolution")
    col.prop(s, "max_points")
    col.prop(s, "device")

    act = runner.active_job(obj)
    if act is not None:
        frac, label = runner.progress(act.source_uid)
        layout.progress(factor=frac, type="BAR", text=f"{label} {frac * 100:.0f}%")
        layout.operator(ops.OBJECT_OT_nkf_cancel.bl_idname, text="Cancel", icon="CANCEL")
    else:
        row = layout.row()
        row.scale_y = 1.4
        row.enabled = ready and obj is not None and not info.problem
        op = row.operator(ops.OBJECT_OT_nkf_reconstruct.bl_idname, text="Reconstruct", icon="MESH_ICOSPHERE")
        for name in ("method", "regularization", "resolution", "max_points", "device"):
            setattr(op, name, getattr(s, name))
        others = runner.running_count()
        if others:
            layout.label(text=f"{others} reconstruction{'s' if others > 1 else ''} running", icon="SORTTIME")

    rec = runner.last_run(obj)
    if rec is not None:
        box = layout.box()
        if rec.state == "done":
            box.label(text=f"Last run: {rec.seconds:.1f} s, {rec.triangles:,} triangles", icon="TIME")
            if rec.message:
                wrapped(box, rec.message, icon="INFO", width=WRAP)
        else:
            col = box.column()
            col.alert = rec.state == "failed"
            icon = "ERROR" if col.alert else "INFO"
            wrapped(col, f"Last run {rec.state}: {rec.message}", icon=icon, width=WRAP)


class VIEW3D_PT_nkf(bpy.types.Panel):
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NKF"
    bl_label = "NKF Reconstruction"

    @classmethod
    def poll(cls, context):
        # Object Mode, or Edit Mode of a mesh (its edits are synced before reading).
        return context.mode in {"OBJECT", "EDIT_MESH"} and context.scene is not None

    def draw(self, context):
        draw_panel(self.layout, context)


CLASSES = (VIEW3D_PT_nkf,)
