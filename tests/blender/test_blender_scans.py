"""Scans in Blender: unoriented points, viewpoint orientation, open surfaces, colours, the estimate
and the memory budget. Real ``bpy``, the real extension, real ``nkf_model``; small inputs at low
resolutions so that each test takes seconds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from blender_helpers import PKG, ext, fibonacci_sphere, import_ply, read_vectors, snapshot, world_vertices, write_ply
from recording_layout import RecordingLayout

from nkf_model.options import Options

RECONSTRUCT = "object.nkf_reconstruct"


def draw(bpy) -> RecordingLayout:
    layout = RecordingLayout()
    bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
    return layout


def _radial_error(v, center, radius) -> np.ndarray:
    return np.abs(np.linalg.norm(v - np.asarray(center), axis=1) - radius) / radius


def _faces(me) -> np.ndarray:
    f = np.empty(len(me.polygons) * 3, dtype=np.int32)
    me.attributes[".corner_vert"].data.foreach_get("value", f)
    return f.reshape(-1, 3)


def _boundary_edges(me) -> int:
    """Edges used by exactly one triangle (0 for a closed surface)."""
    f = _faces(me)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


def _colors(me, name="Col") -> np.ndarray:
    attr = me.color_attributes[name]
    buf = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color_srgb", buf)
    return np.rint(buf.reshape(-1, 4)[:, :3] * 255).astype(int)


@pytest.fixture
def budget_pref(addon, bpy_module):
    """The add-on's preferences; the memory budget is put back to automatic afterwards."""
    prefs = bpy_module.context.preferences.addons[PKG].preferences
    yield prefs
    prefs.memory_budget = 0.0


def test_scan_defaults_are_nkf_models(addon, bpy_module):
    from nkf_model.options import SCAN_MIN_PIECE, SCAN_TRIM

    props = bpy_module.context.scene.nkf_settings.bl_rna.properties
    assert (props["trim"].default, props["min_piece"].default) == pytest.approx((SCAN_TRIM, SCAN_MIN_PIECE))


def test_unoriented_point_cloud_reconstructs_with_estimated_normals(scene, bpy_module, tmp_path, capsys):
    bpy = bpy_module
    pts, _ = fibonacci_sphere(400, 1.0, (0.5, 0.0, 0.0))
    src = import_ply(bpy, write_ply(tmp_path / "bare.ply", pts))
    layout = draw(bpy)
    assert "No normals: they will be estimated (outward)" in layout.joined()
    assert layout.operators(RECONSTRUCT)[0].enabled
    before = snapshot(bpy)
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    new = bpy.context.active_object
    assert new.name == "bare_nkf"
    assert _radial_error(world_vertices(new), (0.5, 0.0, 0.0), 1.0).max() < 0.05
    assert snapshot(bpy)["bare"] == before["bare"]  # the source is untouched
    assert "normals estimated (oriented outward)" in capsys.readouterr().out
    assert "normals estimated" in ext("runner").last_run(src).message


def test_viewpoint_orientation_uses_the_camera_in_the_objects_frame(scene, bpy_module, tmp_path):
    from mathutils import Euler, Matrix, Vector

    bpy = bpy_module
    pts, _ = fibonacci_sphere(800, 1.0)
    cap = pts[pts[:, 2] > 0.3]  # an open cap around local +z, seen from above (local)
    src = import_ply(bpy, write_ply(tmp_path / "cap.ply", cap))
    # Upside down and far away in the world: local +z is world -z.
    src.matrix_world = Matrix.Translation(Vector((10.0, 0.0, 0.0))) @ Euler((np.pi, 0.0, 0.0)).to_matrix().to_4x4()
    bpy.context.view_layer.update()
    before = snapshot(bpy)
    with pytest.raises(RuntimeError, match="Orientation is Viewpoint but the scene has no camera"):
        bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, orientation="VIEWPOINT")
    assert snapshot(bpy) == before

    cam = bpy.data.objects.new("scanner", bpy.data.cameras.new("scanner"))
    bpy.context.collection.objects.link(cam)
    cam.location = (10.0, 0.0, -5.0)  # below in the world = above the cap in its own frame
    bpy.context.scene.camera = cam
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = src
    assert ext("runner").viewpoint(bpy.context, src) == pytest.approx(np.array([[0.0, 0.0, 5.0]]), abs=1e-5)
    res = bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, orientation="VIEWPOINT", use_scan=True)
    assert res == {"FINISHED"}
    new = bpy.context.active_object
    me = new.data
    me.update()
    # The surface faces the scanner: vertex normals on top of the cap point up in local coordinates.
    local = read_vectors(me, "position")
    nrm = np.empty(len(me.vertices) * 3, dtype=np.float32)
    me.vertex_normals.foreach_get("vector", nrm)
    top = local[:, 2] > 0.9
    assert top.sum() > 10
    assert nrm.reshape(-1, 3)[top, 2].mean() > 0.8


def test_trim_cuts_the_closed_blob_of_an_open_hemisphere(scene, bpy_module, tmp_path):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(900, 1.0)
    keep = pts[:, 2] > 0.0
    src = import_ply(bpy, write_ply(tmp_path / "dome.ply", pts[keep], nrm[keep]))

    def run(**kwargs):
        bpy.context.view_layer.objects.active = src
        assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, **kwargs) == {"FINISHED"}
        me = bpy.context.active_object.data
        return len(me.polygons), float(read_vectors(me, "position")[:, 2].min())

    closed_faces, closed_low = run()
    scan_faces, scan_low = run(use_scan=True)  # trim 4 point spacings, drop pieces under 0.2 %
    tight_faces, tight_low = run(use_scan=True, trim=1.5)
    loose_faces, loose_low = run(use_scan=True, trim=30.0, min_piece=0.0)
    # The untrimmed surface closes the dome far below its rim (z = 0); trimming cuts that away.
    assert closed_low < -0.4
    assert scan_faces < 0.95 * closed_faces and scan_low > closed_low + 0.1
    assert tight_faces < scan_faces and tight_low > scan_low and tight_low > -0.25
    # Nothing is 30 spacings away: the value reaches the core, and the surface stays closed below.
    # (Not the same faces as the untrimmed run: trimming turns off the closed-surface far field.)
    assert loose_low < -0.4 and loose_faces > 0.95 * closed_faces > scan_faces
    # Off by default: a plain run is not trimmed.
    assert ext("settings").to_options(bpy.context.scene.nkf_settings).trim is None


def _red_blue_sphere(n=500):
    pts, nrm = fibonacci_sphere(n, 1.0)
    rgb = np.where(pts[:, 2:3] > 0, [[255, 0, 0]], [[0, 0, 255]]).astype(np.uint8)
    return pts, nrm, rgb


def _check_red_blue(new):
    me = new.data
    attr = me.color_attributes.get("Col")
    assert attr is not None and attr.domain == "POINT" and attr.data_type == "BYTE_COLOR"
    assert me.color_attributes.active_color_name == "Col" and me.color_attributes.default_color_name == "Col"
    col = _colors(me)
    z = read_vectors(me, "position")[:, 2]
    assert len(col) == len(z)
    # Near the equator a vertex mixes its 8 nearest points; away from it, each side is pure.
    assert (col[z > 0.3] == [255, 0, 0]).all() and (z > 0.3).sum() > 100
    assert (col[z < -0.3] == [0, 0, 255]).all() and (z < -0.3).sum() > 100
    assert (col[:, 1] == 0).all()


def test_ply_colours_land_on_the_right_vertices(scene, bpy_module, tmp_path):
    bpy = bpy_module
    pts, nrm, rgb = _red_blue_sphere()
    src = import_ply(bpy, write_ply(tmp_path / "painted.ply", pts, nrm, rgb))
    assert src.data.attributes["Col"].data_type == "FLOAT_COLOR"  # what PLY import makes
    assert "Colours: 'Col' (carried onto the mesh)" in draw(bpy).joined()
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    _check_red_blue(bpy.context.active_object)
    # Colours off: no colour attribute.
    bpy.context.view_layer.objects.active = src
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, use_colors=False) == {"FINISHED"}
    assert len(bpy.context.active_object.data.color_attributes) == 0


def test_byte_colours_of_a_point_cloud_object_are_read_too(scene, bpy_module):
    bpy = bpy_module
    pts, nrm, rgb = _red_blue_sphere()
    me = bpy.data.meshes.new("painted")
    me.vertices.add(len(pts))
    me.attributes["position"].data.foreach_set("vector", pts.astype(np.float32).ravel())
    me.attributes.new("normal", "FLOAT_VECTOR", "POINT").data.foreach_set("vector", nrm.astype(np.float32).ravel())
    rgba = np.ones((len(pts), 4), np.float32)
    rgba[:, :3] = rgb / 255.0
    me.color_attributes.new("scan_rgb", "BYTE_COLOR", "POINT").data.foreach_set("color_srgb", rgba.ravel())
    ob = bpy.data.objects.new("painted", me)
    bpy.context.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    ob.select_set(True)
    assert bpy.ops.object.convert(target="POINTCLOUD") == {"FINISHED"}
    cloud = bpy.context.active_object
    assert cloud.type == "POINTCLOUD" and ext("source").describe(cloud).colors == "scan_rgb"
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    _check_red_blue(bpy.context.active_object)


def test_panel_shows_the_estimate_for_the_object_and_settings(scene, bpy_module, tmp_path):
    import nkf_model

    bpy = bpy_module
    pts, nrm = fibonacci_sphere(400, 1.0)
    import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))
    s = bpy.context.scene.nkf_settings
    s.method = "SPLINES"
    s.resolution = 64
    text = draw(bpy).joined()
    expected = nkf_model.estimate(400, resolution=64).summary()
    assert f"Estimate: {expected}" in text and "dense solver, 400 points" in text
    s.max_points = 100
    s.normals_mode = "ESTIMATE"
    s.resolution = 256
    expected = nkf_model.estimate(100, resolution=256, estimate_normals=True).summary()
    assert expected != nkf_model.estimate(400, resolution=64).summary()
    assert f"Estimate: {expected}" in draw(bpy).joined()
    # The learned kernel's estimate is its own (slower kernel evaluations).
    s.method = "NKF"
    expected = nkf_model.estimate(100, resolution=256, estimate_normals=True, method="nkf").summary()
    assert f"Estimate: {expected}" in draw(bpy).joined()


def test_oversized_job_under_a_tiny_budget_is_refused_and_changes_nothing(
    scene, bpy_module, tmp_path, budget_pref
):
    bpy = bpy_module
    pts, nrm = fibonacci_sphere(400, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "ball.ply", pts, nrm))
    budget_pref.memory_budget = 0.05  # GB; any run needs more than 0.15 GB
    layout = draw(bpy)
    alert = " ".join(layout.alerts())
    assert "the memory budget is 0.05 GB" in alert and "lower Resolution" in alert
    assert not layout.operators(RECONSTRUCT)[0].enabled
    before = snapshot(bpy)
    with pytest.raises(RuntimeError, match=r"needs about [0-9.]+ GB but the memory budget is 0.05 GB: lower") as info:
        bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=512)
    assert str(info.value).startswith("Error: NKF: ") and "\n" not in str(info.value).strip()
    assert snapshot(bpy) == before
    assert ext("runner").running_count() == 0 and ext("runner").last_run(src) is None
    # The Python function takes its own budget, and the core refuses in the worker too.
    budget_pref.memory_budget = 0.0
    with pytest.raises(ext("errors").UserError, match="memory budget is 0.05 GB"):
        ext("api").reconstruct_object(src, method="splines", resolution=32, memory_budget_gb=0.05)
    assert snapshot(bpy) == before
    job_mod = ext("job")
    opts = Options(method="splines", resolution=32, memory_budget=2**20)
    job = job_mod.ReconstructJob(pts, nrm, opts).run()
    assert job.state == "failed" and "memory budget" in job.error and job.result is None


def test_watertight_caps_a_sheet_at_the_bounding_box(scene, bpy_module, tmp_path):
    bpy = bpy_module
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, size=(1500, 2))
    z = 0.1 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
    nrm = np.column_stack([-0.3 * np.cos(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]),
                           0.2 * np.sin(3 * xy[:, 0]) * np.sin(2 * xy[:, 1]), np.ones(len(z))])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    src = import_ply(bpy, write_ply(tmp_path / "sheet.ply", np.column_stack([xy, z]), nrm))

    def boundary_edges(**kwargs):
        bpy.context.view_layer.objects.active = src
        assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32, **kwargs) == {"FINISHED"}
        tri = np.array([p.vertices[:] for p in bpy.context.active_object.data.polygons], dtype=np.int64)
        e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        _, counts = np.unique(e[:, 0] * (int(tri.max()) + 1) + e[:, 1], return_counts=True)
        return int((counts == 1).sum())

    assert boundary_edges() > 0  # off by default: open where the sheet meets the box
    assert boundary_edges(use_close=True) == 0
    assert not ext("settings").to_options(bpy.context.scene.nkf_settings).close
