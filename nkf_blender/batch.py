"""Reconstruct every selected point cloud: one job each, queued, one at a time.

``object.nkf_reconstruct_selected`` collects the selected mesh and point cloud objects (results of
earlier runs are skipped: they are meshes made by this add-on), then runs them in turn through
:mod:`nkf_blender.runner`, each result updated in place or added as for a single source. Invoked
from the UI it is modal: a 0.1 s timer finishes one job and starts the next; the panel shows the
queue with each object's progress; Esc or **Cancel All** stops the running job and drops the rest.
Executed (scripts, headless) it runs them one after another and returns when all are done. An
object that cannot be reconstructed (no points, a setting out of range) is reported and skipped;
the others still run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy

from . import prefs, result, runner, settings
from .errors import UserError
from .job import RUNNING

TIMER_INTERVAL = 0.1


@dataclass
class Batch:
    """The queue of a running ``nkf_reconstruct_selected``."""

    names: list = field(default_factory=list)  # every source, in order
    done: dict = field(default_factory=dict)  # name -> "done" | "failed: ..." | "cancelled" | "skipped: ..."
    current: str = ""
    key: int | None = None


BATCH = Batch()


def eligible(context) -> list:
    """Selected mesh and point cloud objects that are not results, active first."""
    sel = [o for o in context.selected_objects if o is not None and o.type in ("MESH", "POINTCLOUD")]
    sel = [o for o in sel if not result.is_result(o)]
    act = context.active_object
    return sorted(sel, key=lambda o: (o != act, o.name))


def running() -> bool:
    return bool(BATCH.names) and len(BATCH.done) < len(BATCH.names)


def cancel_all() -> None:
    """Stop the running job and drop the objects still waiting."""
    if BATCH.key is not None:
        runner.cancel(BATCH.key)
    for name in BATCH.names:
        BATCH.done.setdefault(name, "cancelled")


class OBJECT_OT_nkf_reconstruct_selected(bpy.types.Operator):
    """Reconstruct every selected point cloud with the panel's settings, one after another"""

    bl_idname = "object.nkf_reconstruct_selected"
    bl_label = "Reconstruct Selected"
    bl_options = {"UNDO"}

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and not running() and len(eligible(context)) > 0

    def _start(self, context):
        BATCH.names = [o.name for o in eligible(context)]
        BATCH.done, BATCH.current, BATCH.key = {}, "", None

    def _next(self, context) -> bool:
        """Start the next object's job; False when none is left."""
        s = context.scene.nkf_settings
        for name in BATCH.names:
            if name in BATCH.done:
                continue
            obj = bpy.data.objects.get(name)
            if obj is None:
                BATCH.done[name] = "skipped: deleted"
                continue
            try:
                opts = settings.to_options(s, prefs.memory_budget(context))
                BATCH.current = name
                BATCH.key = runner.start(context, obj, opts, colors=s.use_colors, new_object=s.use_new_object,
                                         evaluated=s.use_evaluated)
                return True
            except UserError as exc:
                BATCH.done[name] = f"skipped: {exc}"
                self.report({"WARNING"}, f"NKF: '{name}': {exc}")
        BATCH.current, BATCH.key = "", None
        return False

    def _finish_current(self, context) -> None:
        name, key = BATCH.current, BATCH.key
        BATCH.key = None
        try:
            ob = runner.finish(context, key)
            BATCH.done[name] = "done" if ob is not None else "cancelled"
        except UserError as exc:
            BATCH.done[name] = f"failed: {exc}"
            self.report({"WARNING"}, f"NKF: '{name}': {exc}")

    def _summary(self) -> dict:
        ok = sum(1 for v in BATCH.done.values() if v == "done")
        self.report({"INFO"}, f"NKF: {ok} of {len(BATCH.names)} reconstructed")
        return {"FINISHED"} if ok else {"CANCELLED"}

    def execute(self, context):
        self._start(context)
        s = context.scene.nkf_settings
        for name in BATCH.names:
            obj = bpy.data.objects.get(name)
            try:
                opts = settings.to_options(s, prefs.memory_budget(context))
                ob = runner.run_sync(context, obj, opts, colors=s.use_colors, new_object=s.use_new_object,
                                     evaluated=s.use_evaluated)
                BATCH.done[name] = "done" if ob is not None else "cancelled"
            except UserError as exc:
                BATCH.done[name] = f"failed: {exc}"
                self.report({"WARNING"}, f"NKF: '{name}': {exc}")
        return self._summary()

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._start(context)
        if not self._next(context):
            return self._summary()
        wm = context.window_manager
        self._timer = wm.event_timer_add(TIMER_INTERVAL, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            cancel_all()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if BATCH.key is not None and runner.poll(BATCH.key) == RUNNING:
            n = len(BATCH.done) + 1
            frac, label = runner.progress(BATCH.key)
            context.workspace.status_text_set(
                f"NKF: {n} of {len(BATCH.names)}: '{BATCH.current}' {label} {frac * 100:.0f}% (Esc cancels all)")
            return {"PASS_THROUGH"}
        if BATCH.key is not None:
            self._finish_current(context)
        if self._next(context):
            return {"PASS_THROUGH"}
        self._end(context)
        return self._summary()

    def cancel(self, context):
        cancel_all()
        if BATCH.key is not None:
            runner.cancel(BATCH.key, wait=True)
            if runner.poll(BATCH.key) != RUNNING:
                self._finish_current(context)
        self._end(context)

    def _end(self, context) -> None:
        timer = getattr(self, "_timer", None)
        if timer is not None:
            context.window_manager.event_timer_remove(timer)
            self._timer = None
        if context.workspace is not None:
            context.workspace.status_text_set(None)


class OBJECT_OT_nkf_cancel_all(bpy.types.Operator):
    """Stop every reconstruction and drop the queued ones"""

    bl_idname = "object.nkf_cancel_all"
    bl_label = "Cancel All"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return running() or runner.running_count() > 0

    def execute(self, context):
        cancel_all()
        for key in runner.running_keys():
            runner.cancel(key)
        return {"FINISHED"}


def draw_queue(layout) -> bool:
    """The queue while it runs (each object's state, the current one's progress); True if shown."""
    if not running():
        return False
    box = layout.box()
    box.label(text=f"Queue: {len(BATCH.done)} of {len(BATCH.names)} done", icon="SORTTIME")
    for name in BATCH.names:
        state = BATCH.done.get(name)
        if name == BATCH.current and BATCH.key is not None:
            frac, label = runner.progress(BATCH.key)
            box.progress(factor=frac, type="BAR", text=f"{name}: {label} {frac * 100:.0f}%")
        else:
            box.label(text=f"{name}: {state or 'waiting'}", icon="CHECKMARK" if state == "done" else "DOT")
    box.operator(OBJECT_OT_nkf_cancel_all.bl_idname, icon="CANCEL")
    return True


CLASSES = (OBJECT_OT_nkf_reconstruct_selected, OBJECT_OT_nkf_cancel_all)
