"""Operators: ``object.nkf_reconstruct`` and ``object.nkf_cancel``.

``object.nkf_reconstruct`` acts on the active object. Invoked from the UI with a window, it is
modal: the points are read on the main thread, a worker thread reconstructs, a 0.1 s window timer
polls it (progress in the status bar and the panel), Esc or the Cancel button stops it, and the
mesh is built on the main thread when it ends; Blender pushes one undo step when the operator
finishes. Executed (scripts, ``bpy.app.background``), it runs synchronously and the new object
exists when the call returns. Both paths go through :mod:`nkf_blender.runner`.
"""

from __future__ import annotations

import bpy
from bpy.props import StringProperty

from . import prefs, result, runner, settings
from .errors import UserError
from .job import CANCELLED, FAILED, RUNNING

TIMER_INTERVAL = 0.1


def _tag_redraw(context) -> None:
    wm = context.window_manager
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _report_finished(op, ob, key) -> None:
    rec = runner.record(key)
    if rec is not None and rec.message:
        op.report({"WARNING"}, f"NKF: {rec.message}")
    op.report({"INFO"}, runner.summary(ob, key))


class OBJECT_OT_nkf_reconstruct(bpy.types.Operator):
    """Reconstruct a surface mesh from the active point cloud with Neural Kernel Fields"""

    bl_idname = "object.nkf_reconstruct"
    bl_label = "Reconstruct Surface"
    # No "REGISTER": Adjust Last Operation (F9) would call execute(), which runs the whole
    # reconstruction on the main thread (Blender frozen, no progress, no cancel), so it is not
    # offered; the panel re-runs with changed settings through the worker. "UNDO": one step.
    bl_options = {"UNDO"}

    @classmethod
    def poll(cls, context):
        """A mesh or point cloud is active, Object Mode (or a mesh's Edit Mode), no job on it."""
        obj = context.active_object
        why = ""
        if context.mode not in {"OBJECT", "EDIT_MESH"}:
            why = "Reconstruct works in Object Mode"
        elif obj is None:
            why = "No active object: select a mesh or point cloud"
        elif obj.type not in {"MESH", "POINTCLOUD"}:
            why = f"'{obj.name}' is a {obj.type.lower()} object; select a mesh or point cloud"
        elif runner.active_job(obj) is not None:
            why = f"'{obj.name}' is already running a reconstruction"
        if why:
            cls.poll_message_set(why)
        return not why

    # Properties (method, regularization, resolution, max_points, device, and for scans
    # normals_mode, orientation, use_scan, trim, min_piece, use_close, use_colors) are added by
    # settings.prepare_classes at registration, with the method's default decided then. The memory
    # budget comes from the add-on preferences.
    source_name: StringProperty(
        name="Source", default="", options={"HIDDEN", "SKIP_SAVE"},
        description="The object to reconstruct (default: the active object)",
    )
    target_name: StringProperty(
        name="Result", default="", options={"HIDDEN", "SKIP_SAVE"},
        description="The result object to update in place (default: the source's latest result)",
    )

    def _objects(self, context):
        """The source and the result to update (None: find or add one); raises UserError."""
        obj = context.active_object
        if self.source_name:
            obj = bpy.data.objects.get(self.source_name)
            if obj is None:
                raise UserError(f"the source object '{self.source_name}' no longer exists")
        target = None
        if self.target_name:
            target = bpy.data.objects.get(self.target_name)
            if target is None:
                raise UserError(f"the result object '{self.target_name}' no longer exists")
        return obj, target

    def execute(self, context):
        on_progress = _print_stages() if bpy.app.background else None
        try:
            obj, target = self._objects(context)
            opts = settings.to_options(self, prefs.memory_budget(context))
            ob = runner.run_sync(context, obj, opts, on_progress=on_progress, colors=self.use_colors,
                                 new_object=self.use_new_object, evaluated=self.use_evaluated, target=target)
        except UserError as exc:
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        if ob is None:
            self.report({"WARNING"}, "NKF: cancelled")
            return {"CANCELLED"}
        _report_finished(self, ob, runner.key_of(obj))
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            obj, target = self._objects(context)
            opts = settings.to_options(self, prefs.memory_budget(context))
            self._key = runner.start(context, obj, opts, colors=self.use_colors, new_object=self.use_new_object,
                                     evaluated=self.use_evaluated, target=target)
        except UserError as exc:
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(TIMER_INTERVAL, window=context.window)
        wm.modal_handler_add(self)
        context.workspace.status_text_set(f"NKF: reconstructing '{obj.name}'… (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        key = self._key
        if event.type == "ESC" and event.value == "PRESS":
            runner.cancel(key)
            context.workspace.status_text_set("NKF: cancelling…")
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        state = runner.poll(key)
        if state == RUNNING:
            frac, label = runner.progress(key)
            context.workspace.status_text_set(f"NKF: {label} {frac * 100:.0f}% (Esc to cancel)")
            _tag_redraw(context)
            return {"PASS_THROUGH"}
        self._end(context)
        try:
            ob = runner.finish(context, key)
        except UserError as exc:
            self.report({"ERROR"}, f"NKF: {exc}")
            return {"CANCELLED"}
        if ob is None or state in (CANCELLED, FAILED):
            self.report({"INFO"}, "NKF: reconstruction cancelled, nothing was added")
            return {"CANCELLED"}
        _report_finished(self, ob, key)
        return {"FINISHED"}

    def cancel(self, context):
        # Blender calls this when it drops the modal handler (file load, quit, add-on disabled).
        key = getattr(self, "_key", None)
        if key is not None:
            runner.cancel(key, wait=True)
            if runner.poll(key) != RUNNING:
                runner.finish(context, key)  # records the cancel; builds nothing
        self._end(context)

    def _end(self, context) -> None:
        timer = getattr(self, "_timer", None)
        if timer is not None:
            context.window_manager.event_timer_remove(timer)
            self._timer = None
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        _tag_redraw(context)


class OBJECT_OT_nkf_cancel(bpy.types.Operator):
    """Stop the reconstruction of the active object (all of them when the active object has none)"""

    bl_idname = "object.nkf_cancel"
    bl_label = "Cancel Reconstruction"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return runner.running_count() > 0

    def execute(self, context):
        act = runner.active_job(context.active_object)
        keys = [act.source_uid] if act is not None else runner.running_keys()
        for key in keys:
            runner.cancel(key)
        self.report({"INFO"}, f"NKF: cancelling {len(keys)} reconstruction{'s' if len(keys) != 1 else ''}")
        return {"FINISHED"}


class OBJECT_OT_nkf_select_source(bpy.types.Operator):
    """Select the point cloud this result was reconstructed from and make it active"""

    bl_idname = "object.nkf_select_source"
    bl_label = "Select Source"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return result.is_result(context.active_object)

    def execute(self, context):
        ob = context.active_object
        src = result.source_of(ob)
        if src is None:
            self.report({"ERROR"}, f"NKF: the source of '{ob.name}' ('{ob.get('nkf_source', '')}') no longer exists")
            return {"CANCELLED"}
        if src.name not in context.view_layer.objects:
            self.report({"ERROR"}, f"NKF: the source '{src.name}' is not in this view layer")
            return {"CANCELLED"}
        result._select_only(context, src)
        return {"FINISHED"}


def _print_stages():
    """A progress listener for headless runs: one line per stage on stdout."""
    seen = set()

    def listener(fraction: float, stage: str) -> None:
        if stage not in seen:
            seen.add(stage)
            print(f"NKF: {stage} ({fraction * 100:.0f}%)", flush=True)

    return listener


CLASSES = (OBJECT_OT_nkf_reconstruct, OBJECT_OT_nkf_cancel, OBJECT_OT_nkf_select_source)
