"""The add-on's settings come from ``nkf_model.options`` (defaults, ranges, texts, validation) and
travel as one ``Options``; what .blend files store (property names, enum identifiers) stays."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest
from blender_helpers import ext, fibonacci_sphere, import_ply, write_ply
from recording_layout import RecordingLayout

from nkf_model.options import SCAN_MIN_PIECE, SCAN_TRIM, SETTING, Options

# Stored in .blend files: never renamed, never renumbered.
STORED_ENUMS = {
    "method": ["NKF", "SPLINES"],
    "device": ["AUTO", "CPU", "GPU"],
    "normals_mode": ["AUTO", "GIVEN", "ESTIMATE"],
    "orientation": ["OUTWARD", "UP", "VIEWPOINT"],
}
PROPERTY_NAMES = (
    "method", "regularization", "resolution", "max_points", "device",
    "normals_mode", "orientation", "use_scan", "trim", "min_piece", "use_close", "use_outliers", "use_colors",
    "use_new_object", "use_evaluated", "use_balloon_check",
)
# Blender property -> the core's setting it reads its texts and ranges from.
CORE = {
    "method": "method", "regularization": "lam", "resolution": "resolution", "max_points": "max_points",
    "device": "device", "normals_mode": "normals_mode", "orientation": "orientation", "trim": "trim",
    "min_piece": "min_piece", "use_close": "close", "use_outliers": "outliers",
    "use_balloon_check": "balloon_check",
}


def _rnas(bpy):
    return {
        "scene": bpy.types.Scene.bl_rna.properties["nkf_settings"].fixed_type.properties,
        "operator": bpy.ops.object.nkf_reconstruct.get_rna_type().properties,
    }


@pytest.fixture
def ball(scene, bpy_module, tmp_path):
    pts, nrm = fibonacci_sphere(400, 1.0)
    return import_ply(bpy_module, write_ply(tmp_path / "ball.ply", pts, nrm))


def test_property_names_and_enum_identifiers_are_what_blend_files_store(addon, bpy_module):
    assert ext("settings").PROPERTY_NAMES == PROPERTY_NAMES
    for where, props in _rnas(bpy_module).items():
        assert set(PROPERTY_NAMES) <= set(props.keys()), where
        for name, ids in STORED_ENUMS.items():
            items = props[name].enum_items
            assert [i.identifier for i in items] == ids, (where, name)
            assert [i.value for i in items] == list(range(len(ids))), (where, name)


def test_labels_tooltips_ranges_and_defaults_come_from_the_core(addon, bpy_module):
    for where, props in _rnas(bpy_module).items():
        for prop, name in CORE.items():
            s, p = SETTING[name], props[prop]
            assert p.name == s.label, (where, prop)
            assert s.description.partition("; None")[0] in p.description, (where, prop)
            assert "None" not in p.description, (where, prop)  # a Blender property cannot be None
            for item in getattr(p, "enum_items", ()):
                (choice,) = [c for c in s.choices if c.label == item.name]
                assert item.description.startswith(choice.description), (where, prop, item.identifier)
        lam, res = SETTING["lam"], SETTING["resolution"]
        assert props["regularization"].default == pytest.approx(lam.default, rel=1e-6)
        assert props["regularization"].hard_min == lam.low
        assert props["regularization"].soft_max == pytest.approx(lam.soft_high)
        assert props["resolution"].default == res.default
        assert (props["resolution"].hard_min, props["resolution"].hard_max) == (res.low, res.high)
        assert props["resolution"].soft_max == res.soft_high
        assert props["max_points"].soft_max == SETTING["max_points"].soft_high
        assert props["trim"].hard_min == SETTING["trim"].low
        assert props["trim"].soft_max == pytest.approx(SETTING["trim"].soft_high)
        assert (props["min_piece"].hard_min, props["min_piece"].hard_max) == (0.0, SETTING["min_piece"].high)
        assert props["device"].default == "AUTO" and props["normals_mode"].default == "AUTO"
        assert props["use_close"].default is SETTING["close"].default
        assert props["use_outliers"].default is SETTING["outliers"].default
        assert props["use_balloon_check"].default is SETTING["balloon_check"].default
        # Blender's own defaults, documented in nkf_blender.settings.
        assert props["max_points"].default == 100_000 and props["max_points"].hard_min == 0
        assert props["orientation"].default == "OUTWARD"
        assert (props["trim"].default, props["min_piece"].default) == pytest.approx((SCAN_TRIM, SCAN_MIN_PIECE))
        assert "0 uses all" in props["max_points"].description


def test_properties_map_to_one_options(scene, bpy_module):
    settings = ext("settings")
    s = bpy_module.context.scene.nkf_settings
    opts = settings.to_options(s)
    assert isinstance(opts, Options)
    assert opts.max_points == 100_000 and opts.orientation == "outward"
    assert opts.trim is None and opts.min_piece == 0.0 and opts.memory_budget is None  # Scan off
    s.method, s.regularization, s.resolution, s.max_points = "SPLINES", 1e-8, 77, 0
    s.device, s.normals_mode, s.orientation = "GPU", "ESTIMATE", "VIEWPOINT"
    s.use_scan, s.trim, s.min_piece, s.use_close, s.use_outliers = True, 2.5, 0.01, True, False
    s.use_balloon_check = False
    opts = settings.to_options(s, memory_budget=2**30)
    # Float properties hold float32: compare those with a tolerance, then everything exactly.
    assert (opts.lam, opts.trim, opts.min_piece) == pytest.approx((1e-8, 2.5, 0.01), rel=1e-6)
    assert opts.replace(lam=1e-8, trim=2.5, min_piece=0.01) == Options(
        method="splines", lam=1e-8, resolution=77, max_points=None, device="cuda", normals_mode="estimate",
        orientation="viewpoint", trim=2.5, min_piece=0.01, close=True, outliers=False, balloon_check=False,
        memory_budget=2**30,
    )
    s.max_points = 250
    assert settings.to_options(s).max_points == 250


def test_a_bad_setting_is_one_clear_error_in_the_panel_and_the_operator(bpy_module, ball):
    bpy = bpy_module
    settings, errors = ext("settings"), ext("errors")
    s = bpy.context.scene.nkf_settings
    s.max_points = 5
    with pytest.raises(errors.UserError, match=r"Max Points must be 0 \(all points\) or at least 10, got 5"):
        settings.to_options(s)
    layout = RecordingLayout()
    bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
    assert any("Max Points must be 0" in a for a in layout.alerts())
    assert not layout.operators("object.nkf_reconstruct")[0].enabled
    with pytest.raises(RuntimeError, match="Error: NKF: Max Points must be 0"):
        bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, max_points=5)
    s.max_points = 0
    s.use_scan, s.trim = True, 0.0  # the core's open lower bound
    with pytest.raises(errors.UserError, match="trim must be a positive number of point spacings"):
        settings.to_options(s)
    with pytest.raises(ext("errors").UserError, match="Max Points must be 0"):
        ext("api").reconstruct_object(ball, method="splines", max_points=3)
    assert [o.name for o in bpy.data.objects] == ["ball"]


def test_python_function_builds_the_same_options(bpy_module, ball, monkeypatch):
    runner = ext("runner")
    seen = []
    monkeypatch.setattr(runner, "run_sync", lambda context, obj, options, colors, **kw: seen.append((options, colors)))
    with pytest.raises(ext("errors").UserError, match="cancelled"):  # the stand-in builds nothing
        ext("api").reconstruct_object(
            ball, method="Neural Splines", regularization=1e-9, resolution=40, max_points=0, device="gpu",
            normals="Estimate", orientation="up", trim=3.0, min_piece=0.01, close=True, colors=False,
            memory_budget_gb=2,
        )
    assert seen == [(Options(method="splines", lam=1e-9, resolution=40, max_points=None, device="cuda",
                             normals_mode="estimate", orientation="up", trim=3.0, min_piece=0.01, close=True,
                             memory_budget=2 * 2**30), False)]


def test_job_takes_options_and_reconstruct_takes_the_max_points_subset(addon):
    from nkf_model.pipeline.stages import STAGE_LABELS

    job_mod = ext("job")
    assert job_mod.STAGE_LABELS is STAGE_LABELS
    pts, nrm = fibonacci_sphere(900, 1.0)
    job = job_mod.ReconstructJob(pts, nrm, Options(method="splines", resolution=24, max_points=300, device="cpu"))
    assert job.run().state == "done", job.error
    assert job.points_used == 300 and job.result.stats["subset"] == {"from": 900, "to": 300}
    assert "used a random 300 of 900 points (Max Points)" in job.notes
    whole = job_mod.ReconstructJob(pts, nrm, Options(method="splines", resolution=24, device="cpu")).run()
    assert whole.state == "done" and whole.points_used == 900 and not any("Max Points" in n for n in whole.notes)
    with pytest.raises(TypeError, match="nkf_model.options.Options"):
        job_mod.ReconstructJob(pts, nrm, {"method": "splines"})


def test_quick_method_check_agrees_with_the_real_one_and_imports_nothing(addon, monkeypatch):
    deps, methods = ext("deps"), ext("methods")
    methods.refresh()
    quick = methods.quick_status("nkf")
    assert quick[0] == methods.nkf_available()[0]
    assert methods.quick_status("splines") == (True, "")
    monkeypatch.setitem(sys.modules, "torch", None)  # as if PyTorch were not installed: NKF runs in NumPy
    deps.refresh()
    methods.refresh()
    try:
        assert methods.quick_status("nkf") == (True, "") == methods.nkf_available()
        methods.refresh()
        monkeypatch.setitem(sys.modules, "safetensors", None)  # without it the weights cannot be read
        deps.refresh()
        ok, why = methods.quick_status("nkf")
        assert not ok and why.startswith("safetensors is not installed") and "preferences" in why
        assert methods.quick_default() == "SPLINES"
    finally:
        monkeypatch.undo()
        deps.refresh()
        methods.refresh()
