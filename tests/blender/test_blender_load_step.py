"""The short load step of a later session, and the bytecode that the first-time preparation writes.

When the marker says the installation is prepared, the add-on's timer after enabling still runs a
short step in the background (the two 600-point exact solves of ``warm_up``: imports and numba's
tables), shown as "Loading the solver"; never in headless Blender, never on the main thread, given
way to a reconstruction started meanwhile, cancelled by disabling the add-on. The first-time
preparation also writes the bytecode of the packages the extension's wheels unpacked, and skips a
folder it cannot write with a note. ``warm_up`` is a stand-in that can be held, except where the
real one runs (a reconstruction started during it; the fresh process that checks which thread
imports the solver).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from blender_helpers import PKG, ext, fibonacci_sphere, holdable_warm_up, import_ply, write_ply
from recording_layout import RecordingLayout

import nkf_model.pipeline.warmup as warmup_mod
from nkf_model.options import Options


def _draw(bpy) -> RecordingLayout:
    layout = RecordingLayout()
    bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
    return layout


def _until(condition, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


@pytest.fixture
def fresh(monkeypatch):
    """The prepare module as enabling leaves it (idle, no thread), and restored afterwards."""
    prepare = ext("prepare")
    assert prepare.stop(30)
    monkeypatch.setattr(prepare, "_status", prepare.Status())
    yield prepare
    prepare.stop(30)


@pytest.fixture
def held(monkeypatch, fresh):
    """``warm_up`` that records its arguments, reports 25 % and then waits for ``release`` (or the
    cancel event); ``compile_bundled`` that records its calls."""
    release = threading.Event()
    calls, compiled = [], []

    fake = holdable_warm_up(release, lambda steps: calls.append(
        {"steps": steps, "thread": threading.current_thread().name}))
    real_compile = fresh.compile_bundled
    monkeypatch.setattr(warmup_mod, "warm_up", fake)
    monkeypatch.setattr(fresh, "compile_bundled", lambda **kw: compiled.append(kw) or "")
    yield SimpleNamespace(release=release, calls=calls, compiled=compiled, real_compile=real_compile)
    release.set()


def _mark_prepared(prepare) -> Path:
    folder = Path(ext("prefs").prepare_folder())
    (folder / prepare.MARKER).write_text(prepare._key() + "\n")
    assert prepare.is_prepared(folder)
    return folder


def test_never_started_in_background_mode(bpy_module, addon):
    # Headless: timers never fire, and enabling registers none (the first run loads what it needs).
    assert bpy_module.app.background
    assert not bpy_module.app.timers.is_registered(ext()._start_prepare)
    assert not [t for t in threading.enumerate() if t.name == ext("prepare").THREAD_NAME and t.is_alive()]


def test_load_step_runs_after_enable_when_prepared(scene, bpy_module, held):
    prepare = ext("prepare")
    folder = _mark_prepared(prepare)
    marker = (folder / prepare.MARKER).read_text()
    assert ext()._start_prepare() == 0.5  # the timer after enabling: a step runs, it keeps polling
    assert _until(lambda: prepare.status().label == "exact solve, Neural Splines")
    st = prepare.status()
    assert st.state == "running" and st.kind == "load"
    assert held.calls == [{"steps": warmup_mod.LOAD_STEPS, "thread": prepare.THREAD_NAME}]
    (bar,) = [i for i in _draw(bpy_module).items if i.kind == "progress"]
    assert bar.text == "Loading the solver 25%"
    assert "Preparing" not in _draw(bpy_module).joined()
    held.release.set()
    assert prepare.wait(10) and prepare.status().state == "done"
    assert ext()._start_prepare() is None  # ended: the timer stops
    assert "Loading" not in _draw(bpy_module).joined()
    assert held.compiled == []  # the bytecode is the first-time preparation's, not the load step's
    assert (folder / prepare.MARKER).read_text() == marker
    assert warmup_mod.LOAD_STEPS == tuple(s[0] for s in warmup_mod.STEPS if s[1] <= 600)


def test_first_time_preparation_keeps_its_label_and_compiles(scene, bpy_module, held, tmp_path):
    prepare = ext("prepare")
    assert prepare.start(tmp_path)  # no marker there: the first-time preparation
    assert _until(lambda: prepare.status().label == "exact solve, Neural Splines")
    assert prepare.status().kind == "prepare" and held.calls[0]["steps"] is None
    (bar,) = [i for i in _draw(bpy_module).items if i.kind == "progress"]
    assert bar.text.startswith("Preparing the solver (first time only) ")
    held.release.set()
    assert prepare.wait(10) and prepare.status().state == "done"
    assert len(held.compiled) == 1


def test_a_failed_load_step_says_so(scene, bpy_module, fresh, monkeypatch):
    def broken(progress=None, cancel=None, methods=(), steps=None):
        raise ModuleNotFoundError("No module named 'llvmlite'", name="llvmlite")

    monkeypatch.setattr(warmup_mod, "warm_up", broken)
    _mark_prepared(fresh)
    assert ext()._start_prepare() in (0.5, None) and fresh.wait(10)
    assert fresh.status().state == "failed" and fresh.status().kind == "load"
    alerts = " ".join(_draw(bpy_module).alerts())
    assert "Loading the solver failed: the Python package llvmlite is missing" in alerts, alerts


def test_disabling_the_add_on_cancels_the_load_step(bpy_module, addon, held):
    import addon_utils

    prepare = ext("prepare")
    _mark_prepared(prepare)
    assert prepare.start(ext("prefs").prepare_folder())
    assert _until(lambda: prepare.status().label == "exact solve, Neural Splines")
    assert prepare.status().kind == "load"
    t0 = time.perf_counter()
    addon_utils.disable(PKG, default_set=True)
    took = time.perf_counter() - t0
    try:
        assert prepare.status().state == "cancelled"
        assert not [t for t in threading.enumerate() if t.name == prepare.THREAD_NAME and t.is_alive()]
        assert took < 5, f"disabling took {took:.1f} s"
    finally:
        addon_utils.enable(PKG, default_set=True)


def _sphere(bpy, tmp_path):
    pts, nrm = fibonacci_sphere(400, 1.0)
    return import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))


def _run_to_end(bpy, runner, key, timeout=120.0):
    assert _until(lambda: runner.poll(key) != "running", timeout), "the reconstruction did not finish"
    assert runner.poll(key) == "done"
    return runner.finish(bpy.context, key)


def test_the_load_step_gives_way_to_a_reconstruction_at_once(scene, bpy_module, held, tmp_path):
    # No timer tick here: the step itself sees the reconstruction thread and stops at its next check.
    bpy = bpy_module
    prepare, runner = ext("prepare"), ext("runner")
    src = _sphere(bpy, tmp_path)
    _mark_prepared(prepare)
    assert prepare.start(ext("prefs").prepare_folder())
    assert _until(lambda: prepare.status().label == "exact solve, Neural Splines")
    key = runner.start(bpy.context, src, Options(method="splines", resolution=48, device="cpu"))
    try:
        assert prepare.wait(5) and prepare.status().state == "cancelled"
        new = _run_to_end(bpy, runner, key)
        assert new is not None and len(new.data.polygons) > 1000
    finally:
        runner.cancel(key, wait=True)


def test_a_reconstruction_started_during_the_real_load_step_works(scene, bpy_module, fresh, tmp_path):
    bpy = bpy_module
    runner = ext("runner")
    src = _sphere(bpy, tmp_path)
    _mark_prepared(fresh)
    assert fresh.start(ext("prefs").prepare_folder()) and fresh.status().kind == "load"
    key = runner.start(bpy.context, src, Options(method="nkf", resolution=48, device="cpu"))
    try:
        new = _run_to_end(bpy, runner, key)
        assert new is not None and len(new.data.polygons) > 1000
        assert fresh.wait(30)
        assert fresh.status().state in ("done", "cancelled"), fresh.status()
    finally:
        runner.cancel(key, wait=True)


def test_the_preparation_writes_the_bundled_bytecode(scene, bpy_module, held, monkeypatch, tmp_path):
    prepare = ext("prepare")
    folder, files = prepare.bundled_files()  # sys.path: the project's editable nkf_model is left out
    where = prepare.blender_wheel_folder(ext("prefs").prepare_folder())
    assert folder == where and prepare.bundled_files(paths=[str(where)]) == (folder, files)
    # The test zip bundles only the nkf_model wheel, unpacked into Blender's extension site-packages.
    assert folder is not None and folder.is_relative_to(os.environ["BLENDER_USER_RESOURCES"])
    assert {f.relative_to(folder).parts[0] for f in files} == {"nkf_model"}
    assert folder / "nkf_model" / "pipeline" / "warmup.py" in files
    caches = [Path(importlib.util.cache_from_source(str(f))) for f in files]
    for c in caches:
        c.unlink(missing_ok=True)
    held.release.set()
    labels = []
    real_set = prepare._set
    monkeypatch.setattr(prepare, "_set", lambda **kw: (labels.append(kw.get("label")), real_set(**kw)))
    monkeypatch.setattr(prepare, "compile_bundled", held.real_compile)  # the real one, not the recorder
    assert prepare.start(tmp_path, force=True) and prepare.wait(60)
    st = prepare.status()
    assert st.state == "done" and st.note == "", st
    assert all(c.is_file() for c in caches)
    assert f"bytecode 0 of {len(files):,} files" in labels and "bytecode written" in labels
    assert prepare.is_prepared(tmp_path)


def _fake_wheel_folder(tmp_path) -> tuple[Path, Path]:
    """An extension folder whose manifest lists one wheel, and the site-packages it unpacked to:
    two modules, one of which cannot have bytecode (its ``__pycache__`` is a file)."""
    ext_dir = tmp_path / "ext"
    ext_dir.mkdir()
    (ext_dir / "blender_manifest.toml").write_text('wheels = ["./wheels/demo_pkg-1.2-py3-none-any.whl"]\n')
    site = tmp_path / "site-packages"
    for pkg in ("demo_pkg", "demo_pkg/sub"):
        (site / pkg).mkdir(parents=True)
        (site / pkg / "__init__.py").write_text("X = 1\n")
    (site / "demo_pkg" / "sub" / "__pycache__").write_text("")  # not a folder: no bytecode here
    info = site / "demo_pkg-1.2.dist-info"
    info.mkdir()
    (info / "RECORD").write_text("demo_pkg/__init__.py,,\ndemo_pkg/sub/__init__.py,,\n"
                                 "demo_pkg-1.2.dist-info/RECORD,,\n../../bin/demo,,\n")
    other = site / "other_pkg"
    other.mkdir()
    (other / "__init__.py").write_text("Y = 2\n")  # another extension's wheel: left alone
    return ext_dir, site


def test_bytecode_it_cannot_write_is_a_note_not_a_failure(fresh, tmp_path):
    ext_dir, site = _fake_wheel_folder(tmp_path)
    folder, files = fresh.bundled_files(ext_dir, [str(tmp_path / "missing"), str(site)])
    assert folder == site
    assert files == [site / "demo_pkg" / "__init__.py", site / "demo_pkg" / "sub" / "__init__.py"]
    note = fresh.compile_bundled(ext_dir=ext_dir, paths=[str(site)])
    assert note.startswith("bytecode not written for 1 of 2 files"), note
    assert "sub/__init__.py" in note
    assert Path(importlib.util.cache_from_source(str(site / "demo_pkg" / "__init__.py"))).is_file()
    assert not (other := site / "other_pkg" / "__pycache__").exists(), other


def test_a_read_only_wheel_folder_is_skipped_and_the_preparation_done(scene, held, monkeypatch, tmp_path):
    prepare = ext("prepare")
    ext_dir, site = _fake_wheel_folder(tmp_path)
    # root ignores permissions: say the folder is read-only the way the code asks
    real_access = os.access
    monkeypatch.setattr(prepare.os, "access", lambda p, mode: False if Path(p) == site else real_access(p, mode))
    monkeypatch.setattr(prepare, "compile_bundled",
                        lambda **kw: held.real_compile(**{**kw, "ext_dir": ext_dir, "paths": [str(site)]}))
    held.release.set()
    assert prepare.start(tmp_path / "cache", force=True) and prepare.wait(30)
    st = prepare.status()
    assert st.state == "done" and st.note == f"{site} is read-only: bytecode not written", st
    assert not (site / "demo_pkg" / "__pycache__").exists()
    assert prepare.is_prepared(tmp_path / "cache")


FRESH_PROCESS = r"""
import json, sys, threading, time
from pathlib import Path
import bpy
import addon_utils

zip_path, pkg = sys.argv[1], sys.argv[2]
res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=False)
assert res == {"FINISHED"}, res
import importlib
mod = addon_utils.enable(pkg, default_set=True)
assert mod is not None
prepare = importlib.import_module(pkg + ".prepare")
prefs = importlib.import_module(pkg + ".prefs")
folder = Path(prefs.prepare_folder())
(folder / prepare.MARKER).write_text(prepare._key() + "\n")  # a later session: prepared

imports = []
HEAVY = ("numba", "scipy", "skimage", "nkf_model.pipeline.reconstruct", "nkf_model.pipeline.warmup")
def hook(event, args):
    if event == "import" and args[0] in HEAVY:
        imports.append([args[0], threading.current_thread().name])
sys.addaudithook(hook)
heavy_before = [m for m in HEAVY if m in sys.modules]

t0 = time.perf_counter()
again = mod._start_prepare()  # what the timer does a second after enabling in the UI
tick = time.perf_counter() - t0
st = prepare.status()
t0 = time.perf_counter()
addon_utils.disable(pkg, default_set=True)  # at once: the worker is still importing the solver
disable = time.perf_counter() - t0
print(json.dumps({"again": again, "kind": st.kind, "state_at_tick": st.state, "tick_s": tick,
                  "disable_s": disable, "state": prepare.status().state, "imports": imports,
                  "heavy_before": heavy_before,
                  "alive": [t.name for t in threading.enumerate() if t.name == prepare.THREAD_NAME]}))
"""


def test_the_timer_starts_the_load_step_without_loading_the_solver_on_the_main_thread(extension_zip, tmp_path):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender-user"))
    run = subprocess.run([sys.executable, "-c", FRESH_PROCESS, str(extension_zip), PKG],
                         capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    print(f"timer tick {got['tick_s']:.3f} s, disabling while loading {got['disable_s']:.2f} s")
    assert got["heavy_before"] == []  # enabling loaded none of it
    assert got["again"] == 0.5 and got["kind"] == "load" and got["state_at_tick"] == "running"
    threads = {name for _, name in got["imports"]}
    assert threads == {"nkf-prepare"}, got["imports"]  # the solver loads on the worker, never on the main thread
    assert {m for m, _ in got["imports"]} >= {"numba", "nkf_model.pipeline.reconstruct"}
    assert got["state"] == "cancelled" and got["alive"] == []
    assert got["disable_s"] < 60
