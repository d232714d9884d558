"""Adjust and see (issue 21) with the real bpy: kept fits per source, results updated in place with
how they were made, Live, Lambda on a log scale, evaluated geometry, and the faults around them."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from blender_helpers import ext, fibonacci_sphere, import_ply, read_vectors, write_ply

N = 400


@pytest.fixture
def sphere(scene, bpy_module, tmp_path):
    pts, nrm = fibonacci_sphere(N, 2.0, (1.0, -2.0, 0.5))
    src = import_ply(bpy_module, write_ply(tmp_path / "sphere.ply", pts, nrm))
    ext("fitcache").CACHE.clear()
    ext("fitcache").CACHE.set_budget(1 << 30)
    yield src
    ext("live").stop()
    ext("fitcache").stop_factorizing(timeout=60)
    ext("fitcache").CACHE.clear()


def verts(ob):
    return read_vectors(ob.data, "position").astype(np.float64)


def run(bpy, **kw):
    settings = dict(method="SPLINES", resolution=32)
    settings.update(kw)
    assert bpy.ops.object.nkf_reconstruct(**settings) == {"FINISHED"}
    return bpy.context.active_object


def test_result_is_updated_in_place_and_remembers_how_it_was_made(sphere, bpy_module):
    bpy = bpy_module
    runner, fitcache = ext("runner"), ext("fitcache")
    res = run(bpy, regularization=1e-10)
    assert res.name == "sphere_nkf" and res["nkf_source"] == "sphere" and res["nkf_source_ref"] == sphere
    # Blender's float properties are single precision
    assert res["nkf_method"] == "splines" and res["nkf_lambda"] == pytest.approx(1e-10) and res["nkf_resolution"] == 32
    assert res["nkf_points"] == N and res["nkf_trim"] == -1.0 and res["nkf_seconds"] > 0
    assert len(fitcache.CACHE) == 1 and not runner.record(runner.key_of(sphere)).reused
    # the artist's changes to the result: name, material, modifier, collection
    res.name = "Blob"
    mat = bpy.data.materials.new("Clay")
    res.data.materials.append(mat)
    res.modifiers.new("Smooth", "SMOOTH")
    coll = bpy.data.collections.new("Results")
    bpy.context.scene.collection.children.link(coll)
    coll.objects.link(res)
    for c in list(res.users_collection):
        if c is not coll:
            c.objects.unlink(res)
    before_v, n_obj, n_mesh = verts(res), len(bpy.data.objects), len(bpy.data.meshes)
    bpy.context.view_layer.objects.active = sphere
    out = run(bpy, regularization=1e-4, resolution=40)
    assert out == res and out.name == "Blob"
    assert len(bpy.data.objects) == n_obj and len(bpy.data.meshes) == n_mesh  # no orphan data
    assert list(res.data.materials) == [mat] and [m.name for m in res.modifiers] == ["Smooth"]
    assert list(res.users_collection) == [coll]
    assert res["nkf_lambda"] == pytest.approx(1e-4) and res["nkf_resolution"] == 40
    assert verts(res).shape != before_v.shape or not np.array_equal(verts(res), before_v)
    rec = runner.record(runner.key_of(sphere))
    assert rec.reused and rec.updated
    # New Object: a second result; the next run updates the newest one
    bpy.context.view_layer.objects.active = sphere
    second = run(bpy, regularization=1e-4, resolution=40, use_new_object=True)
    assert second != res and second["nkf_source_ref"] == sphere
    bpy.context.view_layer.objects.active = sphere
    assert run(bpy, resolution=36) == second and res["nkf_resolution"] == 40


def test_kept_fit_gives_what_a_fresh_run_gives(sphere, bpy_module):
    bpy = bpy_module
    fitcache = ext("fitcache")
    res = run(bpy, regularization=1e-10, resolution=32)
    fit = fitcache.CACHE.fit_for(ext("runner").key_of(sphere))
    assert fit is not None
    fitcache.stop_factorizing(timeout=120)  # background eigendecomposition (may have finished)
    bpy.context.view_layer.objects.active = sphere
    kept = run(bpy, regularization=1e-5, resolution=44)
    assert kept == res
    fitcache.CACHE.clear()
    bpy.context.view_layer.objects.active = sphere
    fresh = run(bpy, regularization=1e-5, resolution=44, use_new_object=True)
    assert fresh != res
    a, b = verts(kept), verts(fresh)
    assert a.shape == b.shape
    assert np.abs(a - b).max() <= 1e-6 * 4.0  # the box's longest side is 4 (radius 2)


def test_deleted_result_then_api_gives_a_new_result(sphere, bpy_module):
    bpy = bpy_module
    api = ext("api")
    first = api.reconstruct_object(sphere, method="splines", resolution=32)
    left = first.data.name
    bpy.data.objects.remove(first)  # the script of the issue: no view-layer update in between
    again = api.reconstruct_object(sphere, method="splines", resolution=32)
    assert again.name == "sphere_nkf" and again["nkf_source_ref"] == sphere
    # the only mesh without users is the one the script's remove() left behind
    assert [m.name for m in bpy.data.meshes if m.users == 0] == [left]
    # the function updates the result in place too, unless new_object
    assert api.reconstruct_object(sphere, method="splines", resolution=40) == again
    assert again["nkf_resolution"] == 40
    other = api.reconstruct_object(sphere, method="splines", resolution=40, new_object=True)
    assert other != again and other["nkf_source_ref"] == sphere


def test_source_edited_or_deleted_forgets_the_fit(sphere, bpy_module):
    bpy = bpy_module
    runner, fitcache, result = ext("runner"), ext("fitcache"), ext("result")
    res = run(bpy)
    key = runner.key_of(sphere)
    assert fitcache.CACHE.fit_for(key) is not None
    # an edit of the source's points: the handler forgets the fit, and the next run fits again
    pos = read_vectors(sphere.data, "position")
    sphere.data.attributes["position"].data.foreach_set("vector", (pos * 1.1).ravel())
    sphere.data.update()
    bpy.context.view_layer.update()
    assert fitcache.CACHE.fit_for(key) is None
    bpy.context.view_layer.objects.active = sphere
    assert run(bpy) == res and not runner.record(key).reused
    # the source deleted: fit forgotten, the result says so, Re-run and Select Source refuse
    bpy.data.objects.remove(sphere)
    bpy.context.view_layer.update()
    assert len(fitcache.CACHE) == 0
    assert result.source_of(res) is None
    bpy.context.view_layer.objects.active = res
    with pytest.raises(RuntimeError, match="no longer exists"):
        bpy.ops.object.nkf_select_source()
    with pytest.raises(RuntimeError, match="no longer exists"):
        bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, source_name="sphere", target_name=res.name)


def test_loading_a_file_forgets_every_fit(sphere, bpy_module):
    bpy = bpy_module
    run(bpy)
    assert len(ext("fitcache").CACHE) == 1
    bpy.ops.wm.read_homefile(use_empty=True)
    assert len(ext("fitcache").CACHE) == 0


def test_cache_too_small_keeps_nothing_and_still_works(sphere, bpy_module):
    bpy = bpy_module
    fitcache = ext("fitcache")
    fitcache.CACHE.set_budget(1000)
    res = run(bpy)
    assert len(fitcache.CACHE) == 0 and res["nkf_points"] == N
    bpy.context.view_layer.objects.active = sphere
    assert run(bpy, resolution=36) == res


def test_select_source_and_rerun_from_the_result(sphere, bpy_module):
    bpy = bpy_module
    res = run(bpy)
    assert bpy.ops.object.nkf_select_source() == {"FINISHED"}
    assert bpy.context.active_object == sphere and sphere.select_get() and not res.select_get()
    bpy.context.view_layer.objects.active = res
    out = run(bpy, resolution=40, source_name=sphere.name, target_name=res.name)
    assert out == res and res["nkf_resolution"] == 40


def test_lambda_is_typed_and_shown_on_a_log_scale(scene):
    s = scene.nkf_settings
    s.lambda_text = "1e-6"
    assert s.regularization == pytest.approx(1e-6) and s.lambda_text == "1e-6"
    assert s.lambda_log == pytest.approx(-6.0)
    s.lambda_log = -8.0
    assert s.regularization == pytest.approx(1e-8) and s.lambda_text == "1e-8"
    s.lambda_text = "not a number"
    assert s.regularization == pytest.approx(1e-8)
    s.regularization = 0.0
    assert s.lambda_text == "0"
    assert "3,000 points" in type(s).bl_rna.properties["lambda_text"].description


def drive_live(live, timeout=120.0):
    """Call live.tick() as Blender's timer would, until it has nothing left to do."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        nxt = live.tick()
        if nxt is None:
            return
        time.sleep(nxt)
    raise AssertionError("Live did not settle")


def test_live_previews_then_updates_in_place(sphere, bpy_module):
    bpy = bpy_module
    live = ext("live")
    res = run(bpy, resolution=96)
    s = bpy.context.scene.nkf_settings
    s.method, s.resolution = "SPLINES", 96
    bpy.context.view_layer.objects.active = res
    s.live = True
    n_obj = len(bpy.data.objects)
    s.regularization = 1e-5  # a "drag": the first tick starts a preview at Resolution 64
    assert live.STATE.dirty
    live.tick()
    assert live.STATE.key is not None and not live.STATE.full
    seen = []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < 120:
        nxt = live.tick()
        seen.append(res["nkf_resolution"])
        if nxt is None:
            break
        time.sleep(nxt)
    assert 64 in seen and seen.index(64) < len(seen) - 1  # the preview came first
    assert res["nkf_resolution"] == 96 and res["nkf_lambda"] == pytest.approx(1e-5)
    assert len(bpy.data.objects) == n_obj and bpy.context.active_object == res
    assert ext("runner").record(ext("runner").key_of(sphere)).reused
    # a setting the fit depends on changed: Live says so and never starts a whole new fit
    s.max_points = 100
    s.resolution = 72
    assert live.tick() is None and live.STATE.key is None
    assert "no kept fit" in live.STATE.message and res["nkf_resolution"] == 96
    s.max_points = 0
    # the result deleted while Live is on: nothing to update, one message, no crash
    bpy.data.objects.remove(res)
    bpy.context.view_layer.objects.active = sphere
    s.resolution = 80
    drive_live(live)
    assert "Live needs" in live.STATE.message
    assert not [o for o in bpy.data.objects if o.get("nkf_resolution") == 80]


def test_evaluated_geometry_or_the_original(sphere, bpy_module):
    bpy = bpy_module
    mod = sphere.modifiers.new("Array", "ARRAY")
    mod.count = 2
    mod.relative_offset_displace = (3.0, 0.0, 0.0)
    res = run(bpy, use_evaluated=True, use_new_object=True)
    assert res["nkf_points"] == 2 * N
    bpy.context.view_layer.objects.active = sphere
    orig = run(bpy, use_evaluated=False, use_new_object=True)
    assert orig["nkf_points"] == N


def test_panel_shows_the_result_with_rerun_and_live(sphere, bpy_module):
    from recording_layout import RecordingLayout

    bpy = bpy_module
    res = run(bpy)
    layout = RecordingLayout()
    ext("panel").draw_panel(layout, bpy.context)
    text = layout.joined()
    assert "Result of 'sphere'" in text and "Lambda 1e-10" in text and "Resolution 32" in text
    buttons = {i.text: i for i in layout.operators()}
    assert buttons["Re-run"].enabled and buttons["Re-run"].op_props["target_name"] == res.name
    assert buttons["Re-run"].op_props["source_name"] == "sphere" and "Select Source" in buttons
    assert {"live", "lambda_text", "lambda_log", "use_evaluated", "use_new_object"} <= set(layout.props())
    assert [i.text for i in layout.items if i.kind == "menu"] == ["NKF Presets"]
    assert "regularization" not in layout.props()
    assert "splines, Lambda" in text and "balloon check" not in text
    # A learned-kernel result whose balloon check fell back says which kernel made its mesh.
    nkf_opts = ext("settings").to_options(bpy.context.scene.nkf_settings).replace(method="nkf")
    check = {"learned_reach": 0.33, "data_free_reach": 0.0, "used": "splines"}
    ext("result").stamp(res, sphere, "sphere", nkf_opts, {"balloon_check": check, "solver": "dense"}, 1.0,
                        points_used=N, colors=False)
    assert res["nkf_used"] == "splines" and res["nkf_method"] == "nkf"
    layout = RecordingLayout()
    ext("panel").draw_panel(layout, bpy.context)
    assert "nkf (used splines: balloon check), Lambda" in layout.joined()
    bpy.data.objects.remove(sphere)
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = res
    layout = RecordingLayout()
    ext("panel").draw_panel(layout, bpy.context)
    assert "no longer exists" in layout.joined()
    assert not {i.text: i for i in layout.operators()}["Re-run"].enabled


def test_presets_set_the_scene_settings_and_user_presets_are_saved(scene, bpy_module):
    bpy = bpy_module
    pm = ext("preset_menu")
    s = scene.nkf_settings
    expect = {
        "Closed_Object": {"use_scan": False, "orientation": "OUTWARD", "method": "NKF", "resolution": 192},
        "Room_Scan": {"use_scan": True, "orientation": "VIEWPOINT", "method": "SPLINES", "resolution": 256},
        "Terrain": {"use_scan": True, "orientation": "UP", "trim": 4.0},
        "Sparse_Sketch": {"use_scan": False, "resolution": 96},
    }
    assert sorted(f[:-3] for f in os.listdir(pm.BUNDLED) if f.endswith(".py")) == sorted(expect)
    for name, values in expect.items():
        path = os.path.join(pm.BUNDLED, name + ".py")
        assert bpy.ops.script.execute_preset(filepath=path, menu_idname="NKF_MT_presets") == {"FINISHED"}
        assert {k: getattr(s, k) for k in values} == values, name
    assert s.regularization == pytest.approx(1e-6)  # Sparse Sketch, the last one: smoother
    s.resolution, s.lambda_text = 77, "3e-9"
    assert bpy.ops.nkf.preset_add(name="My Setup") == {"FINISHED"}
    mine = [os.path.join(d, "My_Setup.py") for d in pm.preset_dirs()[1:]]
    mine = [p for p in mine if os.path.isfile(p)]
    assert len(mine) == 1
    s.resolution, s.regularization = 128, 1e-10
    assert bpy.ops.script.execute_preset(filepath=mine[0], menu_idname="NKF_MT_presets") == {"FINISHED"}
    assert s.resolution == 77 and s.regularization == pytest.approx(3e-9)
    os.remove(mine[0])


def test_reconstruct_selected_runs_each_source_and_skips_what_cannot_run(sphere, bpy_module, tmp_path, capsys):
    bpy = bpy_module
    batch = ext("batch")
    pts, nrm = fibonacci_sphere(300, 1.0, (6.0, 0.0, 0.0))
    other = import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))
    empty = bpy.data.objects.new("empty_cloud", bpy.data.meshes.new("empty_cloud"))
    bpy.context.scene.collection.objects.link(empty)
    s = bpy.context.scene.nkf_settings
    s.method, s.resolution = "SPLINES", 32
    for ob in (sphere, other, empty):
        ob.select_set(True)
    bpy.context.view_layer.objects.active = sphere
    assert [o.name for o in batch.eligible(bpy.context)] == ["sphere", "ball", "empty_cloud"]
    assert bpy.ops.object.nkf_reconstruct_selected() == {"FINISHED"}
    assert batch.BATCH.done["sphere"] == "done" and batch.BATCH.done["ball"] == "done"
    assert batch.BATCH.done["empty_cloud"].startswith("failed") and "no points" in batch.BATCH.done["empty_cloud"]
    made = {o["nkf_source"]: o for o in bpy.data.objects if "nkf_source" in o.keys()}
    assert set(made) == {"sphere", "ball"} and made["ball"]["nkf_points"] == 300
    assert "2 of 3 reconstructed" in capsys.readouterr().out
    # results are not sources of a new batch; a second batch updates the results in place
    for ob in (sphere, other, *made.values()):
        ob.select_set(True)
    bpy.context.view_layer.objects.active = sphere
    n = len(bpy.data.objects)
    assert [o.name for o in batch.eligible(bpy.context)] == ["sphere", "ball"]
    assert bpy.ops.object.nkf_reconstruct_selected() == {"FINISHED"}
    assert len(bpy.data.objects) == n


def test_file_loaded_during_a_job_cancels_it_and_adds_nothing(sphere, bpy_module):
    from nkf_model.options import Options

    bpy = bpy_module
    runner, fitcache = ext("runner"), ext("fitcache")
    key = runner.start(bpy.context, sphere, Options(method="splines", resolution=64, device="cpu"))
    bpy.ops.wm.read_homefile(use_empty=True)
    assert runner.poll(key) == "cancelled" and runner.running_count() == 0
    assert runner.finish(bpy.context, key) is None
    assert len(bpy.data.objects) == 0 and len(fitcache.CACHE) == 0


def test_escape_stops_a_live_update(sphere, bpy_module):
    from nkf_model.options import Options

    bpy = bpy_module
    live, runner = ext("live"), ext("runner")
    assert hasattr(bpy.types, "NKF_OT_live_escape")
    key = runner.start(bpy.context, sphere, Options(method="splines", resolution=128, device="cpu"))
    live.STATE.key, live.STATE.dirty = key, True

    class Event:
        type, value = "MOUSEMOVE", "NOTHING"

    modal = live.NKF_OT_live_escape.modal  # what the window's event loop calls (no events headless)
    assert modal(None, bpy.context, Event) == {"PASS_THROUGH"}
    Event.type, Event.value = "ESC", "PRESS"
    assert modal(None, bpy.context, Event) == {"FINISHED"}
    assert not live.STATE.dirty and "Esc" in live.STATE.message
    assert runner.cancel(key, wait=True) and runner.poll(key) == "cancelled"
    n = len(bpy.data.objects)
    live.STATE.key = None
    assert runner.finish(bpy.context, key) is None and len(bpy.data.objects) == n
    assert modal(None, bpy.context, Event) == {"FINISHED", "PASS_THROUGH"}  # nothing in flight: it ends


def _wait(runner, key, timeout=120.0):
    t0 = time.perf_counter()
    while runner.poll(key) == "running":
        assert time.perf_counter() - t0 < timeout
        time.sleep(0.05)
    return runner.poll(key)


def _orphan_meshes(bpy):
    return [m.name for m in bpy.data.meshes if m.users == 0]


def test_undo_and_redo_during_a_job_update_the_right_object(sphere, bpy_module):
    """Undo and redo rebuild every object in memory while a job runs: the job's result goes to the
    object that stands for its target then (by ``session_uid``), or to a new one when undo took the
    target away; never to a stale or wrong object, no orphan data."""
    from nkf_model.options import Options

    bpy = bpy_module
    runner, result = ext("runner"), ext("result")
    bpy.ops.ed.undo_push(message="sphere only")
    res = run(bpy)
    res_name, res_uid = res.name, runner.key_of(res)
    bpy.ops.ed.undo_push(message="with its result")
    # 1. undo then redo while the job runs: the result comes back and is updated in place
    key = runner.start(bpy.context, sphere, Options(method="splines", resolution=48, device="cpu"))
    assert bpy.ops.ed.undo() == {"FINISHED"}
    assert bpy.data.objects.get(res_name) is None
    assert bpy.ops.ed.redo() == {"FINISHED"}
    back = bpy.data.objects[res_name]
    assert runner.key_of(back) == res_uid  # undo keeps session_uid: the job finds it again
    assert _wait(runner, key) == "done"
    ob = runner.finish(bpy.context, key)
    assert ob == bpy.data.objects[res_name] and ob["nkf_resolution"] == 48
    assert [o.name for o in bpy.data.objects if result.is_result(o)] == [res_name]
    assert _orphan_meshes(bpy) == []
    # 2. undo back to before the result existed while the job runs: a new result, not a stale one
    src = bpy.data.objects["sphere"]
    key = runner.start(bpy.context, src, Options(method="splines", resolution=40, device="cpu"))
    assert bpy.ops.ed.undo() == {"FINISHED"}  # to "sphere only" (the finish above pushed no step)
    assert bpy.data.objects.get(res_name) is None
    assert _wait(runner, key) == "done"
    ob = runner.finish(bpy.context, key)
    src = bpy.data.objects["sphere"]
    results = [o for o in bpy.data.objects if result.is_result(o)]
    assert results == [ob] and ob["nkf_resolution"] == 40 and ob["nkf_source_ref"] == src
    assert ob.name in bpy.context.view_layer.objects and ob.users_collection
    assert _orphan_meshes(bpy) == []
    # 3. the source deleted while its job runs: the result is placed where the source was
    bpy.ops.ed.undo_push(message="second result")
    m, src_data = src.matrix_world.copy(), src.data.name
    key = runner.start(bpy.context, src, Options(method="splines", resolution=36, device="cpu"))
    bpy.data.objects.remove(src)
    bpy.ops.ed.undo_push(message="source deleted")
    assert _wait(runner, key) == "done"
    ob = runner.finish(bpy.context, key)
    assert ob is not None and ob["nkf_resolution"] == 36 and result.source_of(ob) is None
    assert np.allclose(np.array(ob.matrix_world), np.array(m))
    assert _orphan_meshes(bpy) == [src_data]  # what remove() left of the source, nothing of ours


def test_source_deleted_while_a_live_update_runs(sphere, bpy_module):
    """The update in flight still lands on its own result (the mesh was computed from the points as
    they were), nothing else changes, and the next change says why Live cannot go on."""
    bpy = bpy_module
    live, result, fitcache = ext("live"), ext("result"), ext("fitcache")
    res = run(bpy, resolution=96)
    other = run(bpy, resolution=40, use_new_object=True)  # a second result of the same source
    other_mesh = other.data.name
    s = bpy.context.scene.nkf_settings
    s.method, s.resolution = "SPLINES", 96
    bpy.context.view_layer.objects.active = res
    s.live = True
    n_obj = len(bpy.data.objects)
    s.regularization = 1e-5
    live.tick()
    assert live.STATE.key is not None  # a preview job is in flight
    src_data = sphere.data.name
    bpy.data.objects.remove(sphere)
    bpy.context.view_layer.update()
    assert len(fitcache.CACHE) == 0  # the kept fit went with its source
    drive_live(live)
    assert res["nkf_lambda"] == pytest.approx(1e-5) and result.source_of(res) is None
    assert other.data.name == other_mesh and other["nkf_resolution"] == 40  # the other result untouched
    assert len(bpy.data.objects) == n_obj - 1
    assert _orphan_meshes(bpy) == [src_data]  # what remove() left of the source, nothing of ours
    s.resolution = 80  # the next change: no source, no fit: one message, nothing runs
    bpy.context.view_layer.objects.active = res
    drive_live(live)
    assert live.STATE.key is None and "Live needs" in live.STATE.message
    assert res["nkf_resolution"] != 80
