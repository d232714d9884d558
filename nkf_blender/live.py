"""Live: a changed Lambda, Resolution or clean-up setting updates the result by itself.

With the panel's **Live** on, a change of a setting that a kept fit only re-solves or re-meshes for
(:func:`nkf_blender.settings.annotations`' ``update``) marks the settings dirty and starts a 0.05 s
timer. While changes keep coming (a slider being dragged: the last one less than :data:`DEBOUNCE`
ago) the timer runs previews at Resolution at most :data:`PREVIEW_RESOLUTION`; once they stop it runs
the full mesh. Every run is an ordinary job of :mod:`nkf_blender.runner` on a worker thread that
reuses the source's kept fit (:mod:`nkf_blender.fitcache`) and updates the result in place, so the
UI never waits and Esc (:class:`NKF_OT_live_escape`, a modal watcher started with each update in a
window), Cancel or turning Live off stops it. A full run made stale by a newer change is
cancelled. Live acts on the active object when it is a result (its source is re-run) or a source
that has a result and a kept fit; it never starts a whole new fit by itself.

Headless Blender has no timers: call :func:`tick` until it returns None.

Also here: the handlers that forget kept fits when a source's geometry changes, an object is
deleted, or another file is loaded (which also cancels every job: nothing lands in the new file).
"""

from __future__ import annotations

import time

import bpy
from bpy.app.handlers import persistent

from . import fitcache, prefs, result, runner, settings
from .errors import UserError
from .job import RUNNING

DEBOUNCE = 0.35  # seconds without a change before the full mesh
PREVIEW_RESOLUTION = 64
POLL = 0.05


class _State:
    def __init__(self):
        self.reset()

    def reset(self):
        self.dirty = False
        self.changed_at = 0.0
        self.key: int | None = None  # the running live job's source key
        self.full = False  # whether the running job is the full mesh
        self.message = ""  # why Live did nothing, or the last error
        self.last_seconds = 0.0
        self.last_preview = False
        self.watching = False  # the Esc watcher (NKF_OT_live_escape) is running


STATE = _State()


def target(context):
    """``(source, result)`` that Live updates for the active object, or ``(None, None)``."""
    ob = context.active_object if context is not None else None
    if ob is None:
        return None, None
    try:
        if result.is_result(ob):
            return result.source_of(ob), ob
        res = result.find_result(ob)
    except ReferenceError:
        return None, None
    return (ob, res) if res is not None else (None, None)


def changed(props, context) -> None:
    """Update callback of the scene settings Live follows."""
    if context is None or context.scene is None or props != getattr(context.scene, "nkf_settings", None):
        return
    if not props.live:
        return
    STATE.dirty = True
    STATE.changed_at = time.perf_counter()
    if not bpy.app.background and not bpy.app.timers.is_registered(tick):
        bpy.app.timers.register(tick, first_interval=POLL)


def stop() -> None:
    """Cancel the running live job (Live turned off, the add-on disabled, a file loaded)."""
    if STATE.key is not None:
        runner.cancel(STATE.key, wait=True)
        try:
            if runner.poll(STATE.key) != RUNNING:
                runner.finish(bpy.context, STATE.key)
        except (UserError, ReferenceError, AttributeError):
            pass
    STATE.reset()
    if bpy.app.timers.is_registered(tick):
        bpy.app.timers.unregister(tick)


def tick():
    """One step of Live; returns the seconds until the next, or None when there is nothing to do."""
    context = bpy.context
    scene = getattr(context, "scene", None)
    s = getattr(scene, "nkf_settings", None) if scene is not None else None
    if s is None or not s.live:
        stop()
        return None
    now = time.perf_counter()
    if STATE.key is not None:
        state = runner.poll(STATE.key)
        if state == RUNNING:
            if STATE.full and STATE.dirty:
                runner.cancel(STATE.key)  # a newer change makes this mesh stale
            return POLL
        key, STATE.key = STATE.key, None
        try:
            ob = runner.finish(context, key)
        except UserError as exc:
            STATE.message = str(exc)
            ob = None
        if ob is not None:
            rec = runner.record(key)
            STATE.last_seconds = rec.seconds if rec is not None else 0.0
            STATE.last_preview = not STATE.full
            STATE.message = ""
            _undo_push("NKF Live")
        _redraw(context)
    if not STATE.dirty:
        return None
    src, res = target(context)
    if src is None or res is None:
        STATE.message = "Live needs a result: select a result, or a source reconstructed once"
        STATE.dirty = False
        return None
    if fitcache.CACHE.fit_for(runner.key_of(src)) is None:
        STATE.message = "Live needs a kept fit: press Reconstruct (or Re-run) once"
        STATE.dirty = False
        return None
    if runner.active_job(src) is not None:
        return POLL  # a reconstruction of this source is running: wait for it
    full = now - STATE.changed_at >= DEBOUNCE
    try:
        opts = settings.to_options(s, prefs.memory_budget(context))
        if not full:
            opts = opts.replace(resolution=min(opts.resolution, PREVIEW_RESOLUTION))
        STATE.key = runner.start(context, src, opts, colors=s.use_colors, evaluated=s.use_evaluated, target=res,
                                 require_kept=True)
    except UserError as exc:
        STATE.message = str(exc)
        STATE.dirty = False
        return None
    STATE.full = full
    if full:
        STATE.dirty = False
    _watch_escape(context)
    return POLL


class NKF_OT_live_escape(bpy.types.Operator):
    """Esc stops the Live update in flight (started by Live with each update; passes every other event on)"""

    bl_idname = "nkf.live_escape"
    bl_label = "Stop Live Update"
    bl_options = {"INTERNAL"}

    def invoke(self, context, event):
        STATE.watching = True
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if STATE.key is None:
            STATE.watching = False
            return {"FINISHED", "PASS_THROUGH"}
        if event.type == "ESC" and event.value == "PRESS":
            runner.cancel(STATE.key)
            STATE.dirty = False
            STATE.message = "Live update stopped (Esc); change a setting to update again"
            STATE.watching = False
            return {"FINISHED"}
        return {"PASS_THROUGH"}


def _watch_escape(context) -> None:
    """Start the Esc watcher in the first window (never headless: no windows, no events)."""
    if bpy.app.background or STATE.watching:
        return
    wm = getattr(context, "window_manager", None)
    windows = list(getattr(wm, "windows", []))
    if not windows:
        return
    try:
        with context.temp_override(window=windows[0]):
            bpy.ops.nkf.live_escape("INVOKE_DEFAULT")
    except RuntimeError:
        STATE.watching = False


CLASSES = (NKF_OT_live_escape,)


def _undo_push(message: str) -> None:
    if bpy.app.background:
        return
    try:
        bpy.ops.ed.undo_push(message=message)
    except RuntimeError:
        pass


def _redraw(context) -> None:
    wm = getattr(context, "window_manager", None)
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


# -- forgetting kept fits -----------------------------------------------------------------------
@persistent
def _on_load_pre(*_args) -> None:
    """Another file replaces this one: stop every job (nothing is added to the new file; a modal
    operator's cancel() finds its job gone) and forget every kept fit."""
    stop()
    from . import batch

    batch.cancel_all()
    stuck = runner.stop_all(timeout=10.0)
    if stuck:
        print(f"NKF: worker threads did not stop for {', '.join(stuck)}")
    fitcache.stop_factorizing(timeout=0.0)
    fitcache.CACHE.clear()


@persistent
def _on_depsgraph_update(scene, depsgraph) -> None:
    if not len(fitcache.CACHE):
        return
    for upd in depsgraph.updates:
        ob = upd.id
        if upd.is_updated_geometry and isinstance(ob, bpy.types.Object):
            fitcache.CACHE.drop_source(runner.key_of(ob.original))
    fitcache.CACHE.keep_only(runner.key_of(ob) for ob in bpy.data.objects)


def register() -> None:
    bpy.app.handlers.load_pre.append(_on_load_pre)
    bpy.app.handlers.depsgraph_update_post.append(_on_depsgraph_update)
    fitcache.CACHE.set_budget(prefs.fit_cache_bytes())


def unregister() -> None:
    stop()
    for handlers, fn in ((bpy.app.handlers.load_pre, _on_load_pre),
                         (bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update)):
        while fn in handlers:
            handlers.remove(fn)
    fitcache.stop_factorizing(timeout=10.0)
    fitcache.CACHE.clear()
