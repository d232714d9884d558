"""The sidebar panel: View3D > Sidebar > NKF.

Shows the active object's point count, where its normals come from (or a notice that they will be
estimated) and its colours, the parameters (with the scan options: normals mode, orientation, trim,
minimum piece, colours), the time and memory estimate for this object and these settings,
Reconstruct or (while running) live progress with the stage and Cancel, the last run's time and
triangle count, and an actionable message when packages are missing, the object cannot be used or
the estimate exceeds the memory budget (or a setting is out of range). ``draw`` reads only cheap
state (no arrays; the estimate is cached), so it can run on every redraw. It never imports
PyTorch: whether NKF can run is :func:`nkf_blender.methods.quick_status` (files and packages
found); the estimate imports nkf_model's time and memory model (``nkf_model.pipeline.budget``,
NumPy only).
"""

from __future__ import annotations

import bpy

from . import batch, deps, estimates, live, methods, ops, prefs, prepare, preset_menu, result, runner, settings, source
from .errors import UserError
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


def _prepare_line(layout) -> None:
    """The background step after enabling while it runs (the first-time preparation, compiling
    the solver, or a later session's short load step), or why it failed."""
    st = prepare.status()
    load = st.kind == prepare.LOAD
    if st.state == prepare.RUNNING:
        what = "Loading the solver" if load else "Preparing the solver (first time only)"
        layout.progress(factor=st.fraction, type="BAR", text=f"{what} {st.fraction * 100:.0f}%")
    elif st.state == prepare.FAILED:
        col = layout.column()
        col.alert = True
        wrapped(col, f"{'Loading' if load else 'Preparing'} the solver failed: {st.error}", icon="ERROR", width=WRAP)


def _normals_line(box, info, s, context) -> str:
    """Say where the normals come from; return a problem that blocks the run, else ``""``."""
    if info.normals is not None:
        box.label(text=f"Normals: {info.normals}", icon="CHECKMARK")
        return ""
    orient = s.orientation.lower()
    if s.normals_mode == "ESTIMATE":
        box.label(text=f"Normals: estimated ({orient})", icon="INFO")
    else:
        wrapped(box, f"No normals: they will be estimated ({orient})", icon="INFO", width=WRAP)
    if s.orientation == "VIEWPOINT":
        scanners = runner.scanners(context.active_object)
        if scanners:
            box.label(text=f"Viewpoints: the {len(scanners)} scanner position(s) of the scan", icon="INFO")
        elif context.scene.camera is None:
            return "Orientation Viewpoint needs a scene camera (where the scanner was)"
    return ""


def _estimate_line(layout, info, s, context) -> str:
    """The time and memory estimate; return the over-budget message (or what is wrong with the
    settings), else ``""``."""
    try:
        opts = settings.to_options(s, prefs.memory_budget(context))
    except UserError as exc:
        col = layout.column()
        col.alert = True
        wrapped(col, str(exc), icon="ERROR", width=WRAP)
        return str(exc)
    try:
        look = estimates.outlook(info.count, opts, info.normals is None, s.use_colors and info.colors is not None)
    except ImportError:
        return ""
    col = layout.column()
    col.alert = bool(look.problem)
    wrapped(col, f"Estimate: {look.summary}", icon="MEMORY", width=WRAP)
    if look.problem:
        wrapped(col, look.problem, icon="ERROR", width=WRAP)
    return look.problem


def _result_box(layout, obj, s) -> None:
    """How the active result was made (its custom properties), with Re-run and Select Source."""
    box = layout.box()
    src = result.source_of(obj)
    name = obj.get("nkf_source", "")
    if src is None:
        col = box.column()
        col.alert = True
        wrapped(col, f"Result of '{name}', which no longer exists: Re-run is not possible", icon="ERROR", width=WRAP)
    else:
        box.label(text=f"Result of '{src.name}'", icon="LINKED")
    trim = obj.get("nkf_trim", -1.0)
    method = obj.get("nkf_method", "?")
    used = obj.get("nkf_used", method)  # "splines" when the learned kernel's balloon check fell back
    lines = [
        f"{method}{f' (used {used}: balloon check)' if used != method else ''}, "
        f"Lambda {settings.format_lambda(obj.get('nkf_lambda', 0.0))}, Resolution {obj.get('nkf_resolution', 0)}",
        f"{obj.get('nkf_points', 0):,} points, normals {obj.get('nkf_normals', '?')}, "
        + ("closed" if trim is None or trim < 0 else f"trim {trim:g}, min piece {obj.get('nkf_min_piece', 0):g}")
        + (", watertight" if obj.get("nkf_close") else ""),
        f"{obj.get('nkf_seconds', 0.0):.1f} s, solver {obj.get('nkf_solver', '?')}"
        + (f", weights {obj['nkf_weights']}" if obj.get("nkf_weights") else ""),
    ]
    col = box.column(align=True)
    for line in lines:
        col.label(text=line)
    row = box.row(align=True)
    sub = row.row(align=True)
    sub.enabled = src is not None and runner.active_job(src) is None
    op = sub.operator(ops.OBJECT_OT_nkf_reconstruct.bl_idname, text="Re-run", icon="FILE_REFRESH")
    for prop in settings.PROPERTY_NAMES:
        setattr(op, prop, getattr(s, prop))
    op.use_new_object = False
    if src is not None:
        op.source_name, op.target_name = src.name, obj.name
    row.operator(ops.OBJECT_OT_nkf_select_source.bl_idname, text="Select Source", icon="RESTRICT_SELECT_OFF")


def _live_row(layout, s, context) -> None:
    row = layout.row(align=True)
    row.prop(s, "live", toggle=True, icon="REC" if s.live else "PLAY")
    if not s.live:
        return
    st = live.STATE
    if st.key is not None:
        row.label(text="preview…" if not st.full else "updating…", icon="SORTTIME")
    elif st.message:
        wrapped(layout.column(), st.message, icon="INFO", width=WRAP)
    elif st.last_seconds:
        row.label(text=f"{'preview' if st.last_preview else 'updated'} in {st.last_seconds:.2f} s")


def draw_panel(layout, context) -> None:
    ready = _deps_box(layout)
    _prepare_line(layout)
    obj = context.active_object
    s = context.scene.nkf_settings
    is_result = result.is_result(obj)
    if is_result:
        _result_box(layout, obj, s)

    box = layout.box()
    info = source.describe(obj, s.normals_mode.lower())
    problem = info.problem
    if obj is None:
        box.label(text="No active object", icon="INFO")
        wrapped(box, "Select a point cloud: a mesh or point cloud object.", width=WRAP)
    else:
        box.label(text=f"{obj.name}: {info.count:,} points", icon="POINTCLOUD_DATA")
        if problem:
            col = box.column()
            col.alert = True
            wrapped(col, problem, icon="ERROR", width=WRAP)
        else:
            problem = _normals_line(box, info, s, context)
            if problem:
                col = box.column()
                col.alert = True
                wrapped(col, problem, icon="ERROR", width=WRAP)
            if info.colors is not None:
                use = "carried onto the mesh" if s.use_colors else "off"
                box.label(text=f"Colours: '{info.colors}' ({use})", icon="COLOR")

    preset_menu.draw_presets(layout)
    col = layout.column()
    col.use_property_split = True
    col.use_property_decorate = False
    col.prop(s, "method")
    if s.method == "NKF":
        ok, why = methods.quick_status("nkf") if ready else (False, "")
        if ready and not ok:
            sub = col.column()
            sub.alert = True
            wrapped(sub, f"NKF unavailable: {why}", icon="ERROR", width=WRAP)
        elif ok and methods.DEFAULT_METHOD != "nkf":
            wrapped(col, "Not the default: on shapes unlike its training data the learned kernel has not "
                    "yet beaten Neural Splines by the gate's margin (docs/nkf.md)", icon="INFO", width=WRAP)
    sub = col.column()
    sub.enabled = s.method == "NKF"  # the learned kernel's safeguard (nkf_model.fit.balloon_check)
    sub.prop(s, "use_balloon_check")
    col.prop(s, "lambda_text", text="Lambda")
    col.prop(s, "lambda_log", text="log10 Lambda", slider=True)
    col.prop(s, "resolution")
    col.prop(s, "max_points")
    col.prop(s, "device")

    col = layout.column(heading="Scan")
    col.use_property_split = True
    col.use_property_decorate = False
    col.prop(s, "normals_mode")
    sub = col.column()
    sub.enabled = s.normals_mode != "GIVEN"
    sub.prop(s, "orientation")
    col.prop(s, "use_scan")
    sub = col.column()
    sub.enabled = s.use_scan
    sub.prop(s, "trim")
    sub.prop(s, "min_piece")
    col.prop(s, "use_close")
    col.prop(s, "use_outliers")
    col.prop(s, "use_colors")
    col.prop(s, "use_evaluated")
    col.prop(s, "use_new_object")

    if ready and obj is not None and not info.problem:
        problem = _estimate_line(layout, info, s, context) or problem

    job_of = (result.source_of(obj) or obj) if is_result else obj
    act = runner.active_job(job_of)
    if act is not None:
        frac, label = runner.progress(act.source_uid)
        layout.progress(factor=frac, type="BAR", text=f"{label} {frac * 100:.0f}%")
        layout.operator(ops.OBJECT_OT_nkf_cancel.bl_idname, text="Cancel", icon="CANCEL")
    else:
        row = layout.row()
        row.scale_y = 1.4
        row.enabled = ready and obj is not None and not problem
        op = row.operator(ops.OBJECT_OT_nkf_reconstruct.bl_idname, text="Reconstruct", icon="MESH_ICOSPHERE")
        for name in settings.PROPERTY_NAMES:
            setattr(op, name, getattr(s, name))
        if is_result and result.source_of(obj) is not None:  # a result: its source again, into it
            op.source_name, op.target_name = result.source_of(obj).name, obj.name
        _live_row(layout, s, context)
        many = len(batch.eligible(context))
        if many > 1 and not batch.running():
            layout.operator(batch.OBJECT_OT_nkf_reconstruct_selected.bl_idname,
                            text=f"Reconstruct Selected ({many})", icon="OUTLINER_OB_POINTCLOUD")
        batch.draw_queue(layout)
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
