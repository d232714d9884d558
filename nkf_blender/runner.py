"""Reconstruction jobs as Blender sees them: start, poll, finish, cancel, all on the main thread.

The operator (interactive and headless), the Python API and the panel share this module. A job
is keyed by its source object's ``session_uid`` (stable across undo and renames), so each object
runs at most one job at a time. Nothing here touches ``bpy`` from another thread: the points are
read before the worker starts, and the mesh is built by :func:`finish` after it has ended.

Driving a job the way the modal operator does::

    opts = settings.to_options(props)       # one nkf_model.options.Options (UserError if invalid)
    key = runner.start(context, obj, opts, colors=props.use_colors)  # reads the points, starts the worker
    while runner.poll(key) == "running":    # from a timer: returns at once
        ...
    new_obj = runner.finish(context, key)   # builds the mesh; None if cancelled/failed
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import bpy
import numpy as np

from nkf_model.options import Options

from . import deps, estimates, fitcache, result, source
from .errors import UserError
from .job import CANCELLED, DONE, FAILED, RUNNING, ReconstructJob


@dataclass
class Active:
    """A job in flight and what is needed to place its result."""

    job: ReconstructJob
    source_uid: int
    source_name: str
    matrix_world: object  # mathutils.Matrix, copied at start
    collections: list  # names of the source's collections
    fit_key: object = None  # fitcache.FitKey of the points and fit settings
    new_object: bool = False  # add a new result object even when the source has one
    target_uid: int | None = None  # the result object to update in place (None: find or add one)


@dataclass
class LastRun:
    """The outcome of the last finished job of an object, for the panel."""

    source_name: str
    state: str
    seconds: float
    points: int
    triangles: int = 0
    result_name: str = ""
    message: str = ""
    reused: bool = False  # the source's kept fit was reused (a re-solve or re-mesh only)
    updated: bool = False  # an existing result was updated in place
    device: str = ""  # "CPU, 2 threads", "CUDA: NVIDIA ..."


_active: dict[int, Active] = {}
_last: dict[int, LastRun] = {}


def key_of(obj) -> int:
    """The object's ``session_uid``, or its address where the API lacks it (older Blender)."""
    uid = getattr(obj, "session_uid", None)
    return uid if uid is not None else obj.as_pointer()


def find_object(uid: int):
    """The object with this ``session_uid``, or None if it was deleted."""
    for ob in bpy.data.objects:
        if key_of(ob) == uid:
            return ob
    return None


def active_job(obj) -> Active | None:
    """The job running for ``obj``, if any."""
    if obj is None:
        return None
    try:
        return _active.get(key_of(obj))
    except ReferenceError:
        return None


def last_run(obj) -> LastRun | None:
    if obj is None:
        return None
    return _last.get(key_of(obj))


def running_count() -> int:
    return len(_active)


def running_keys() -> list[int]:
    """Keys of every job in flight."""
    return list(_active)


def record(key: int) -> LastRun | None:
    """The outcome of the last finished job for this key (source or result object)."""
    return _last.get(key)


def prepare(
    context, obj, options: Options, on_progress=None, *, colors: bool = True, new_object: bool = False,
    evaluated: bool = True, require_kept: bool = False,
) -> tuple[ReconstructJob, Active]:
    """Check everything that can be checked now and read the points; the job is not started.

    ``options`` are the settings; ``colors``: read the object's colours and carry them onto the
    mesh (the Colours property). Raises :class:`~nkf_blender.errors.UserError` (nothing changed) when the object or the
    installation cannot run.
    """
    if obj is not None and key_of(obj) in _active:
        raise UserError(
            f"A reconstruction of '{obj.name}' is already running: wait for it to finish or press Cancel"
        )
    st = deps.status()
    if not st.ready:
        st = deps.refresh()
    if not st.ready:
        raise UserError(st.message())
    src = source.read_points(obj, options.normals_mode, colors=bool(colors), **_evaluated(context, evaluated))
    estimate_normals = src.normals is None
    viewpoints = viewpoint(context, obj) if estimate_normals and options.orientation == "viewpoint" else None
    check_budget(len(src.points), options, estimate_normals, src.colors is not None)
    fit_key, kept = _kept_fit(obj, options, src.points, src.normals, src.colors, viewpoints)
    if require_kept and kept is None:
        raise UserError(
            f"no kept fit of '{obj.name}' for these settings (its points or a setting the fit depends on "
            "changed): press Reconstruct once"
        )
    job = ReconstructJob(
        src.points, src.normals, options, on_progress=on_progress, colors=src.colors, viewpoints=viewpoints,
        fit=kept, keep_fit=kept is None,
    )
    act = Active(
        job=job,
        source_uid=key_of(obj),
        source_name=obj.name,
        matrix_world=obj.matrix_world.copy(),
        collections=[c.name for c in obj.users_collection],
        fit_key=fit_key,
        new_object=bool(new_object),
    )
    return job, act


def _evaluated(context, evaluated: bool) -> dict:
    """Keyword arguments for :func:`source.read_points`: the depsgraph when the evaluated geometry
    (modifiers, Geometry Nodes) is to be read."""
    return {"depsgraph": context.evaluated_depsgraph_get() if evaluated else None}


def _kept_fit(obj, options: Options, *arrays):
    """The cache key of these arrays and settings, and the kept fit for it (or None)."""
    key = fitcache.key_for(key_of(obj), options, *arrays)
    kept = fitcache.CACHE.get(key)
    if kept is None:
        # a reduced input was fitted for its resolution: that one is keyed with it
        key_r = fitcache.key_for(key_of(obj), options, *arrays, resolution_dependent=True)
        kept = fitcache.CACHE.get(key_r)
        if kept is not None:
            key = key_r
    return key, kept


SCANNER_PROPERTY = "nkf_scanner"  # as importer.SCANNER_PROPERTY: an E57 scanner position


def scanners(obj) -> list:
    """The scanner-position empties of an imported scan (its children marked ``nkf_scanner``)."""
    if obj is None:
        return []
    return [c for c in obj.children if c.get(SCANNER_PROPERTY)]


def viewpoint(context, obj):
    """The scanner positions that estimated normals point towards (orientation Viewpoint), in
    ``obj``'s local frame, (K, 3) float64: the scanner empties of an imported E57 scan when it has
    them, else the scene camera's world position."""
    found = scanners(obj)
    if found:
        try:
            inv = obj.matrix_world.inverted()
        except ValueError:
            raise UserError(f"'{obj.name}' has a flat (non-invertible) transform; apply or fix its scale") from None
        return np.array([tuple(inv @ c.matrix_world.translation) for c in found], dtype=np.float64)
    cam = context.scene.camera if context.scene is not None else None
    if cam is None:
        raise UserError(
            "Orientation is Viewpoint but the scene has no camera: add a camera where the scanner "
            "was (and make it the scene camera), or choose Outward or Up"
        )
    try:
        local = obj.matrix_world.inverted() @ cam.matrix_world.translation
    except ValueError:
        raise UserError(f"'{obj.name}' has a flat (non-invertible) transform; apply or fix its scale") from None
    return np.array([tuple(local)], dtype=np.float64)


def check_budget(count: int, options: Options, estimate_normals: bool, colors: bool) -> None:
    """Raise :class:`UserError` when the estimated memory of the run exceeds the memory budget."""
    try:
        look = estimates.outlook(count, options, estimate_normals, colors)
    except ImportError:
        return  # nkf_model itself will say what is missing
    if look.problem:
        raise UserError(look.problem)


def start(context, obj, options: Options, *, colors: bool = True, new_object: bool = False,
          evaluated: bool = True, target=None, require_kept: bool = False) -> int:
    """Start a job for ``obj`` on a worker thread; return its key for :func:`poll` and :func:`finish`.

    ``new_object``: add a new result even when ``obj`` has one (else its result is updated in
    place); ``target``: the result object to update; ``evaluated``: read the evaluated geometry
    (modifiers and Geometry Nodes applied) instead of the original data; ``require_kept``: refuse
    (UserError) unless a kept fit of these points and settings can be reused (Live)."""
    job, act = prepare(context, obj, options, colors=colors, new_object=new_object, evaluated=evaluated,
                       require_kept=require_kept)
    act.target_uid = None if target is None else key_of(target)
    _active[act.source_uid] = act
    job.start()
    return act.source_uid


def poll(key: int) -> str:
    """``"running"``, or how the job ended (``"done"``, ``"failed"``, ``"cancelled"``). Never blocks."""
    act = _active.get(key)
    if act is None:
        return CANCELLED
    job = act.job
    if not job.finished:
        return RUNNING
    if job.cancel_event.is_set():
        return CANCELLED
    return job.state


def progress(key: int) -> tuple[float, str]:
    """``(fraction, stage label)`` of a running job."""
    act = _active.get(key)
    if act is None:
        return 0.0, ""
    frac, _stage = act.job.progress
    return frac, act.job.stage_label


def cancel(key: int, wait: bool = False, timeout: float = 10.0) -> bool:
    """Ask a job to stop; with ``wait``, also join its thread. True if its thread has ended."""
    act = _active.get(key)
    if act is None:
        return True
    act.job.cancel()
    return act.job.join(timeout) if wait else not act.job.alive


def finish(context, key: int):
    """After :func:`poll` stopped returning ``"running"``: build the result and forget the job.

    Returns the new object, or None when the job was cancelled. Raises
    :class:`~nkf_blender.errors.UserError` with nkf_model's message when it failed.
    """
    act = _active.get(key)
    if act is None:
        return None
    job = act.job
    if job.alive:
        raise RuntimeError("finish() called while the worker is still running; poll() first")
    del _active[key]
    state = CANCELLED if job.cancel_event.is_set() else job.state
    record = LastRun(act.source_name, state, job.elapsed, job.points_used, reused=job.reused)
    _last[key] = record
    if state == CANCELLED:
        record.message = "cancelled"
        return None
    if state == FAILED:
        record.message = job.error or "failed"
        raise UserError(record.message)
    assert state == DONE and job.result is not None
    src = find_object(key)
    if job.fit is not None and not job.reused and act.fit_key is not None:
        fk = act.fit_key
        if job.fit.resolution_dependent:
            fk = fitcache.key_for(fk.source, job.options, resolution_dependent=True)
            fk = fitcache.FitKey(act.fit_key.source, act.fit_key.data, fk.settings)
        if src is not None and fitcache.CACHE.put(fk, job.fit):
            fitcache.factorize_later(job.fit)
    matrix = src.matrix_world.copy() if src is not None else act.matrix_world
    collections = [bpy.data.collections.get(n) for n in act.collections]
    if src is not None:
        collections = list(src.users_collection) or collections
    t0 = time.perf_counter()
    target = None
    if not act.new_object:
        target = find_object(act.target_uid) if act.target_uid is not None else None
        target = target if target is not None else result.find_result(src, act.source_name)
    record.updated = target is not None
    if target is not None:
        ob = result.replace_mesh(context, target, job.result)
    else:
        ob = result.add_object(
            context, job.result, name=result.result_name(act.source_name), source=src, matrix_world=matrix,
            collections=collections,
        )
    result.stamp(ob, src, act.source_name, job.options, job.result.stats, job.elapsed,
                 points_used=job.points_used, colors=job.colors is not None)
    record.seconds = job.elapsed + (time.perf_counter() - t0)
    record.triangles = len(job.result.faces)
    record.result_name = ob.name
    record.message = "; ".join(job.notes)
    record.device = job.device
    _last[key_of(ob)] = record  # the panel shows it for the new (active) object too
    return ob


def run_sync(context, obj, options: Options, on_progress=None, *, colors: bool = True, new_object: bool = False,
             evaluated: bool = True, target=None):
    """Read, reconstruct and build in the calling (main) thread; return the new object.

    Used by the operator when there is no window to run modal in (``bpy.app.background``, or an
    ``EXEC`` call from a script) and by :func:`nkf_blender.api.reconstruct_object`.
    """
    job, act = prepare(context, obj, options, on_progress=on_progress, colors=colors, new_object=new_object,
                       evaluated=evaluated)
    act.target_uid = None if target is None else key_of(target)
    _active[act.source_uid] = act
    try:
        job.run()
    except BaseException:
        _active.pop(act.source_uid, None)
        raise
    return finish(context, act.source_uid)


def stop_all(timeout: float = 10.0) -> list[str]:
    """Cancel every job and join its thread (add-on disabled, Blender quitting).

    Returns the names of the sources whose thread did not end within ``timeout``.
    """
    for act in _active.values():
        act.job.cancel()
    stuck = [act.source_name for act in _active.values() if not act.job.join(timeout)]
    _active.clear()
    return stuck


def summary(ob, key: int) -> str:
    """One line for the status bar after a run."""
    rec = record(key)
    if rec is None or ob is None:
        return ""
    return (
        f"NKF: '{ob.name}' from {rec.points:,} points, {rec.triangles:,} triangles in {rec.seconds:.1f} s"
        + (f" on {rec.device}" if rec.device else "")
    )
