"""Every bad input ends in one clear report and changes nothing."""

from __future__ import annotations

import numpy as np
import pytest
from blender_helpers import ext, fibonacci_sphere, import_ply, snapshot, world_vertices, write_ply


def _expect_error(bpy, pattern: str, op_args=None, api_args=None) -> None:
    """Run the operator and the Python function: both fail with ``pattern``, nothing changes."""
    before = snapshot(bpy)
    with pytest.raises(RuntimeError, match=pattern) as info:
        bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, **(op_args or {}))
    # A report from execute(), or (no usable active object) the operator's poll() message.
    assert str(info.value).startswith(("Error: NKF: ", "Operator bpy.ops.object.nkf_reconstruct.poll() "))
    assert "\n" not in str(info.value).strip()  # one line, no traceback
    assert snapshot(bpy) == before
    obj = bpy.context.active_object
    if obj is not None:
        with pytest.raises(ext("errors").UserError, match=pattern):
            ext("api").reconstruct_object(obj, method="splines", resolution=32, **(api_args or {}))
        assert snapshot(bpy) == before


def test_nothing_active(scene, bpy_module):
    bpy = bpy_module
    bpy.ops.mesh.primitive_cube_add()
    bpy.context.view_layer.objects.active = None
    _expect_error(bpy, "No active object")


def test_empty_mesh(scene, bpy_module):
    bpy = bpy_module
    ob = bpy.data.objects.new("empty_mesh", bpy.data.meshes.new("empty_mesh"))
    bpy.context.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    _expect_error(bpy, "'empty_mesh' has no points")


def test_camera(scene, bpy_module):
    bpy = bpy_module
    bpy.ops.object.camera_add()
    _expect_error(bpy, "is a camera object; select a mesh or point cloud")


def test_point_cloud_without_normals_in_given_mode(scene, bpy_module, tmp_path):
    bpy = bpy_module
    pts, _ = fibonacci_sphere(200, 1.0)
    import_ply(bpy, write_ply(tmp_path / "bare.ply", pts))
    _expect_error(bpy, "'bare' has no normals, and Normals is set to Given: choose Auto or Estimate",
                  op_args={"normals_mode": "GIVEN"}, api_args={"normals": "given"})


def _mesh_with_normals(bpy, name, pts, nrm):
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(pts))
    me.attributes["position"].data.foreach_set("vector", np.asarray(pts, np.float32).ravel())
    me.attributes.new("normal", "FLOAT_VECTOR", "POINT").data.foreach_set(
        "vector", np.asarray(nrm, np.float32).ravel()
    )
    ob = bpy.data.objects.new(name, me)
    bpy.context.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    ob.select_set(True)
    return ob


def test_mesh_with_nan_coordinates(scene, bpy_module):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(300, 1.0)
    pts[5:] = np.nan  # only five usable points remain
    _mesh_with_normals(bpy, "nan_cloud", pts, nrm)
    _expect_error(bpy, r"5 usable points of 300; at least 10 are needed \(dropped 295 points with NaN")


def test_a_few_nan_points_are_dropped_with_a_warning_and_the_source_kept(scene, bpy_module, capsys):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(300, 1.0)
    pts[:7, 1] = np.nan
    src = _mesh_with_normals(bpy, "some_nan", pts, nrm)
    before = snapshot(bpy)
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    out = capsys.readouterr().out
    assert "Warning: NKF: dropped 7 points with NaN or infinite coordinates" in out
    assert before["some_nan"] == snapshot(bpy)["some_nan"]  # NaNs and all, untouched
    new = bpy.context.active_object
    assert new.name == "some_nan_nkf" and np.isfinite(world_vertices(new)).all()
    assert src.name == "some_nan"


def test_bad_settings_from_python_are_clear(scene, bpy_module, tmp_path):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(200, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "ok.ply", pts, nrm))
    before = snapshot(bpy)
    api, errors = ext("api"), ext("errors")
    with pytest.raises(errors.UserError, match="lambda must be a finite number >= 0"):
        api.reconstruct_object(src, method="splines", regularization=-1.0)
    with pytest.raises(errors.UserError, match="device must be"):
        api.reconstruct_object(src, method="splines", device="tpu")
    with pytest.raises(errors.UserError, match="expected a bpy.types.Object"):
        api.reconstruct_object(None)
    # The operator's own properties refuse out-of-range values before anything runs.
    with pytest.raises(TypeError):
        bpy.ops.object.nkf_reconstruct(method="MARCHING")
    assert snapshot(bpy) == before
