"""The first-time preparation (compiling the solver in the background): progress in the panel, a
marker so it runs once, a clear message when it fails, and a prompt stop when the add-on is
disabled meanwhile. The real compilation is measured in tests/blender_env (a fresh install);
here ``warm_up`` is replaced by a stand-in that can be held, failed or cancelled at will."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest
from blender_helpers import ext, holdable_warm_up
from recording_layout import RecordingLayout

import nkf_model.pipeline.warmup as warmup_mod


def _draw(bpy) -> RecordingLayout:
    layout = RecordingLayout()
    bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
    return layout


@pytest.fixture
def held_warm_up(monkeypatch):
    """``warm_up`` that reports 25 % and then waits for ``release`` (or the cancel event)."""
    release = threading.Event()
    calls = []

    fake = holdable_warm_up(release, lambda steps: calls.append(1))
    monkeypatch.setattr(warmup_mod, "warm_up", fake)
    yield SimpleNamespace(release=release, calls=calls)
    release.set()
    ext("prepare").stop()


def test_runs_once_with_progress_in_the_panel(scene, bpy_module, held_warm_up, tmp_path):
    prepare = ext("prepare")
    assert prepare.start(tmp_path, force=True)
    deadline = threading.Event()
    while prepare.status().label != "exact solve, Neural Splines" and not deadline.wait(0.02):
        pass
    (bar,) = [i for i in _draw(bpy_module).items if i.kind == "progress"]
    # warm_up's 25 %, of the share of the bar before the bytecode is written
    assert bar.text == f"Preparing the solver (first time only) {prepare.WARM_UP_SHARE * 0.25 * 100:.0f}%"
    held_warm_up.release.set()
    assert prepare.wait(10) and prepare.status().state == "done"
    assert "Preparing" not in _draw(bpy_module).joined()
    assert "numba" in (tmp_path / prepare.MARKER).read_text()
    assert prepare.is_prepared(tmp_path)
    assert not prepare.start(tmp_path, load=False)  # prepared: nothing to do (the load step: test_blender_load_step)
    assert held_warm_up.calls == [1]


def test_failure_is_one_line_in_the_panel_and_leaves_no_marker(scene, bpy_module, monkeypatch, tmp_path):
    def broken(progress=None, cancel=None, methods=()):
        raise ModuleNotFoundError("No module named 'llvmlite'\n(more lines)", name="llvmlite")

    monkeypatch.setattr(warmup_mod, "warm_up", broken)
    prepare = ext("prepare")
    assert prepare.start(tmp_path, force=True) and prepare.wait(10)
    st = prepare.status()
    assert st.state == "failed" and "\n" not in st.error
    assert st.error.startswith("the Python package llvmlite is missing (ModuleNotFoundError: No module named "
                               "'llvmlite')"), st.error
    assert "Preparing the solver failed: the Python package llvmlite is missing" in " ".join(
        _draw(bpy_module).alerts())
    assert not (tmp_path / prepare.MARKER).exists()


def test_unwritable_folder_still_prepares(scene, bpy_module, held_warm_up, tmp_path):
    # A folder that cannot be made (its parent is a file; a chmod would not stop root).
    (tmp_path / "file").write_text("")
    folder = tmp_path / "file" / "cache"
    prepare = ext("prepare")
    held_warm_up.release.set()
    assert prepare.start(folder, force=True) and prepare.wait(10)
    assert prepare.status().state == "done"
    assert not prepare.is_prepared(folder)  # no marker: it runs again next session, from numba's cache


def test_disabling_the_add_on_meanwhile_stops_it(bpy_module, addon, held_warm_up, tmp_path):
    import addon_utils

    prepare = ext("prepare")
    assert prepare.start(tmp_path, force=True)
    pkg = addon.__name__
    addon_utils.disable(pkg, default_set=True)
    try:
        assert prepare.status().state == "cancelled"
        assert not [t for t in threading.enumerate() if t.name == prepare.THREAD_NAME and t.is_alive()]
    finally:
        addon_utils.enable(pkg, default_set=True)


def test_a_reconstruction_started_meanwhile_cancels_it(scene, bpy_module, held_warm_up, tmp_path):
    # numba's workqueue threading layer (where OpenMP is missing) aborts on parallel loops entered
    # from two threads at once, so the preparation gives way to the user's job.
    from blender_helpers import fibonacci_sphere, import_ply, write_ply

    from nkf_model.options import Options

    bpy = bpy_module
    prepare, runner = ext("prepare"), ext("runner")
    pts, nrm = fibonacci_sphere(400, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))
    assert prepare.start(tmp_path, force=True)
    assert ext()._start_prepare() == 0.5  # the timer keeps polling while it runs
    key = runner.start(bpy.context, src, Options(method="splines", resolution=64, device="cpu"))
    try:
        ext()._start_prepare()  # the timer's next tick sees the job
        assert prepare.wait(10) and prepare.status().state == "cancelled"
        assert ext()._start_prepare() is None  # ended: the timer stops
        assert not (tmp_path / prepare.MARKER).exists()  # it runs again next session
    finally:
        runner.cancel(key, wait=True)
        runner.finish(bpy.context, key)
