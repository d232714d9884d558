"""The interactive path, driven as Blender's modal operator drives it: start, poll from a timer,
finish on the main thread, and cancel. Real threads, real ``nkf_model``, real ``bpy``."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from blender_helpers import ext, fibonacci_sphere, import_ply, nkf_threads, snapshot, write_ply

from nkf_model.options import Options

TIMER = 0.05  # the operator polls every 0.1 s; poll faster here to see the stages


def _settings(resolution=40, method="splines"):
    return Options(method=method, resolution=resolution, lam=1e-10, device="cpu")


@pytest.fixture
def sphere(scene, bpy_module, tmp_path):
    pts, nrm = fibonacci_sphere(400, 1.0, (0.0, 0.0, 1.0))
    return import_ply(bpy_module, write_ply(tmp_path / "ball.ply", pts, nrm))


def test_start_poll_finish_builds_the_mesh_on_the_main_thread(bpy_module, sphere):
    bpy = bpy_module
    runner = ext("runner")
    key = runner.start(bpy.context, sphere, _settings())
    act = runner.active_job(sphere)
    assert act is not None and act.job.thread.name == "nkf-reconstruct"
    assert act.job.thread is not threading.main_thread()
    seen, slowest_poll = [], 0.0
    deadline = time.monotonic() + 60
    while True:
        t0 = time.perf_counter()
        state = runner.poll(key)
        frac, label = runner.progress(key)
        slowest_poll = max(slowest_poll, time.perf_counter() - t0)
        if state != "running":
            break
        seen.append((frac, label))
        assert time.monotonic() < deadline, "the worker did not finish"
        time.sleep(TIMER)
    assert state == "done"
    assert slowest_poll < 0.01  # a poll never waits for the worker
    fracs = [f for f, _ in seen]
    assert fracs == sorted(fracs)  # progress only moves forward
    # Nothing is added to the scene until finish() runs on the main thread.
    assert [o.name for o in bpy.data.objects] == ["ball"]
    new = runner.finish(bpy.context, key)
    assert new is not None and new.name == "ball_nkf"
    assert bpy.context.view_layer.objects.active == new
    assert runner.active_job(sphere) is None
    assert not act.job.alive
    rec = runner.last_run(sphere)
    assert rec.state == "done" and rec.triangles == len(new.data.polygons) and rec.seconds > 0
    assert runner.last_run(new) is rec  # the panel shows it for the new active object too


def test_cancel_midway_stops_promptly_and_leaves_nothing(bpy_module, scene, tmp_path):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(1500, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "big.ply", pts, nrm))
    before = snapshot(bpy)
    runner = ext("runner")
    key = runner.start(bpy.context, src, _settings(resolution=256))
    deadline = time.monotonic() + 60
    while runner.progress(key)[1] not in ("Evaluating", "Meshing"):
        assert runner.poll(key) == "running", "finished before it could be cancelled; use a bigger input"
        assert time.monotonic() < deadline
        time.sleep(0.01)
    act = runner.active_job(src)
    assert bpy.ops.object.nkf_cancel() == {"FINISHED"}  # the panel's Cancel button
    t0 = time.monotonic()
    while runner.poll(key) == "running":
        assert time.monotonic() - t0 < 2.0, "cancel took longer than 2 s"
        time.sleep(0.01)
    stopped_after = time.monotonic() - t0
    assert runner.poll(key) == "cancelled"
    assert runner.finish(bpy.context, key) is None
    assert stopped_after < 1.0
    assert not act.job.alive and not nkf_threads()
    assert snapshot(bpy) == before
    assert runner.last_run(src).state == "cancelled"
    assert runner.running_count() == 0


def test_cancel_right_after_start_never_adds_the_result(bpy_module, sphere):
    """Even when the worker finishes before it sees the cancel, the result is dropped."""
    bpy = bpy_module
    runner = ext("runner")
    before = snapshot(bpy)
    key = runner.start(bpy.context, sphere, _settings(resolution=24))
    runner.cancel(key)
    assert runner.cancel(key, wait=True)
    assert runner.poll(key) == "cancelled"
    assert runner.finish(bpy.context, key) is None
    assert snapshot(bpy) == before and not nkf_threads()


def test_one_job_per_object_and_a_second_request_says_so(bpy_module, sphere):
    bpy = bpy_module
    runner = ext("runner")
    key = runner.start(bpy.context, sphere, _settings(resolution=96))
    try:
        with pytest.raises(RuntimeError, match="already running"):
            bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32)
        with pytest.raises(ext("errors").UserError, match="already running"):
            runner.start(bpy.context, sphere, _settings())
    finally:
        runner.cancel(key, wait=True)
        runner.finish(bpy.context, key)
    assert [o.name for o in bpy.data.objects] == ["ball"]


def test_failure_in_the_worker_is_reported_by_finish_and_changes_nothing(bpy_module, scene, tmp_path):
    bpy = bpy_module
    # All points on a plane: nkf_model refuses with a clear DegenerateInputError.
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)]
    nrm = np.tile([0.0, 0.0, 1.0], (200, 1))
    src = import_ply(bpy, write_ply(tmp_path / "flat.ply", pts, nrm))
    before = snapshot(bpy)
    runner = ext("runner")
    key = runner.start(bpy.context, src, _settings())
    deadline = time.monotonic() + 30
    while runner.poll(key) == "running":
        assert time.monotonic() < deadline
        time.sleep(TIMER)
    assert runner.poll(key) == "failed"
    with pytest.raises(ext("errors").UserError, match="plane"):
        runner.finish(bpy.context, key)
    assert snapshot(bpy) == before
    assert runner.last_run(src).state == "failed"
    assert not nkf_threads()


class _OperatorInstance:
    """Stands in for the operator instance Blender would create: holds ``_key`` and records reports.

    (Blender never calls ``modal()`` in module mode, so the real ``modal`` function is called with
    this ``self`` and an event record, exactly as the window manager calls it on each event.)
    """

    def __init__(self, cls, key):
        self._key = key
        self._timer = None
        self.reports = []
        self._end = cls._end.__get__(self)

    def report(self, kind, message):
        self.reports.append((set(kind), message))


def _event(type_, value="NOTHING"):
    from types import SimpleNamespace

    return SimpleNamespace(type=type_, value=value)


def test_modal_steps_pass_events_through_and_finish_with_the_object(bpy_module, sphere):
    bpy = bpy_module
    ops = ext("ops")
    cls = ops.OBJECT_OT_nkf_reconstruct
    key = ext("runner").start(bpy.context, sphere, _settings())
    op = _OperatorInstance(cls, key)
    assert cls.modal(op, bpy.context, _event("MOUSEMOVE")) == {"PASS_THROUGH"}  # the user keeps working
    deadline = time.monotonic() + 60
    while (ret := cls.modal(op, bpy.context, _event("TIMER"))) == {"PASS_THROUGH"}:
        assert time.monotonic() < deadline
        time.sleep(ops.TIMER_INTERVAL)
    assert ret == {"FINISHED"}
    assert bpy.context.active_object.name == "ball_nkf"
    assert any("triangles" in msg for kind, msg in op.reports if kind == {"INFO"})


def test_modal_escape_cancels_and_reports(bpy_module, sphere):
    bpy = bpy_module
    ops = ext("ops")
    cls = ops.OBJECT_OT_nkf_reconstruct
    key = ext("runner").start(bpy.context, sphere, _settings(resolution=128))
    op = _OperatorInstance(cls, key)
    assert cls.modal(op, bpy.context, _event("ESC", "PRESS")) == {"RUNNING_MODAL"}
    t0 = time.monotonic()
    while (ret := cls.modal(op, bpy.context, _event("TIMER"))) == {"PASS_THROUGH"}:
        assert time.monotonic() - t0 < 2.0
        time.sleep(0.02)
    assert ret == {"CANCELLED"}
    assert [o.name for o in bpy.data.objects] == ["ball"]
    assert any("cancelled" in msg for _kind, msg in op.reports)
    assert not nkf_threads()
