"""The operator and the Python function on real imported point clouds: shape, placement, results."""

from __future__ import annotations

import math

import numpy as np
import pytest
from blender_helpers import (
    ext,
    fibonacci_sphere,
    import_ply,
    read_vectors,
    snapshot,
    world_vertices,
    write_ply,
)

RADIUS = 2.0
CENTER = (1.0, -2.0, 0.5)


@pytest.fixture
def sphere_ply(tmp_path):
    pts, nrm = fibonacci_sphere(400, RADIUS, CENTER)
    return write_ply(tmp_path / "sphere.ply", pts, nrm)


def _radial_error(vertices_world, center, radius) -> np.ndarray:
    return np.abs(np.linalg.norm(vertices_world - np.asarray(center), axis=1) - radius) / radius


def test_operator_reconstructs_imported_ply_sphere(scene, bpy_module, sphere_ply, capsys):
    bpy = bpy_module
    src = import_ply(bpy, sphere_ply)
    assert src.type == "MESH" and len(src.data.polygons) == 0
    before = snapshot(bpy)

    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=48) == {"FINISHED"}

    new = bpy.context.active_object
    assert new is not src and new.name == "sphere_nkf"
    assert new.select_get() and not src.select_get()
    assert list(new.users_collection) == list(src.users_collection)
    me = new.data
    assert len(me.polygons) > 1000 and all(len(p.vertices) == 3 for p in me.polygons[:50])
    smooth = np.zeros(len(me.polygons), dtype=bool)
    me.polygons.foreach_get("use_smooth", smooth)
    assert smooth.all()
    # Chamfer-style bounds against the true sphere, in world units.
    err = _radial_error(world_vertices(new), CENTER, RADIUS)
    assert err.max() < 0.02 and err.mean() < 0.005
    pts_world = world_vertices(src)
    from scipy.spatial import cKDTree

    d_src_to_mesh, _ = cKDTree(world_vertices(new)).query(pts_world)
    assert d_src_to_mesh.max() < 0.05 * RADIUS
    # Chamfer-L1 by the metrics module's protocol: 100k surface samples each side, unit box units.
    from nkf_model.train.metrics import chamfer_l1, sample_surface

    faces = np.empty(len(me.polygons) * 3, dtype=np.int32)
    me.attributes[".corner_vert"].data.foreach_get("value", faces)
    on_mesh, _ = sample_surface(world_vertices(new), faces.reshape(-1, 3), 100_000, np.random.default_rng(0))
    on_sphere, _ = fibonacci_sphere(100_000, RADIUS, CENTER)
    chamfer = chamfer_l1(on_mesh / (2 * RADIUS), on_sphere / (2 * RADIUS))
    assert chamfer < 0.004, chamfer  # 100k samples alone give about 0.0025
    # Watertight: every edge is shared by exactly two triangles.
    assert me.validate() is False  # nothing to fix
    edges = np.empty(len(me.edges) * 2, dtype=np.int32)
    me.edges.foreach_get("vertices", edges)
    assert len(me.vertices) - len(me.edges) + len(me.polygons) == 2  # Euler characteristic of a sphere
    # The source is untouched, and exactly one object and one mesh were added.
    after = snapshot(bpy)
    for key in before["objects"]:
        assert after[key] == before[key]
    assert after["objects"] == sorted(before["objects"] + ["sphere_nkf"])
    assert after["meshes"] == sorted(before["meshes"] + [me.name])
    out = capsys.readouterr().out
    assert "triangles" in out and "'sphere_nkf'" in out


def test_result_lines_up_under_translation_rotation_and_scale(scene, bpy_module, tmp_path):
    from mathutils import Euler, Matrix, Vector

    bpy = bpy_module
    local_pts, local_nrm = fibonacci_sphere(300, 1.0, (0.3, 0.1, -0.2))
    src = import_ply(bpy, write_ply(tmp_path / "ball.ply", local_pts, local_nrm))
    src.matrix_world = (
        Matrix.Translation(Vector((120.0, -40.0, 7.5)))
        @ Euler((0.4, -1.1, 2.3)).to_matrix().to_4x4()
        @ Matrix.Diagonal(Vector((2.0, 0.5, 1.5, 1.0)))
    )
    bpy.context.view_layer.update()
    src_matrix = [list(r) for r in src.matrix_world]

    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=40) == {"FINISHED"}
    new = bpy.context.active_object
    assert [list(r) for r in new.matrix_world] == src_matrix
    assert [list(r) for r in src.matrix_world] == src_matrix
    # Local coordinates: the mesh is the unit sphere the points were sampled from.
    local = read_vectors(new.data, "position").astype(np.float64)
    err = _radial_error(local, (0.3, 0.1, -0.2), 1.0)
    assert err.max() < 0.03
    # World coordinates: the new object's world-space surface, mapped back through the *source's*
    # matrix, is the sphere the points came from; and every source point has a mesh vertex nearby.
    m_src = np.array(src.matrix_world, dtype=np.float64)
    w = world_vertices(new)
    back = (w - m_src[:3, 3]) @ np.linalg.inv(m_src[:3, :3]).T
    assert _radial_error(back, (0.3, 0.1, -0.2), 1.0).max() < 0.03
    from scipy.spatial import cKDTree

    d, _ = cKDTree(w).query(world_vertices(src))
    assert d.max() < 0.1  # world units: a grid cell is about 0.05 local, scaled by up to 2


def test_mesh_with_faces_uses_vertex_normals_and_point_cloud_object_works(scene, bpy_module):
    bpy = bpy_module
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.5, location=(0, 0, 3), segments=32, ring_count=16)
    uv = bpy.context.active_object
    assert ext("source").describe(uv).normals == "vertex normals"
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=40) == {"FINISHED"}
    new = bpy.context.active_object
    err = _radial_error(world_vertices(new), (0, 0, 3), 1.5)
    assert err.max() < 0.03

    # A PointCloud object (converted from a mesh with a `normal` point attribute).
    pts, nrm = fibonacci_sphere(300, 0.5)
    me = bpy.data.meshes.new("pc_src")
    me.vertices.add(len(pts))
    me.attributes["position"].data.foreach_set("vector", pts.astype(np.float32).ravel())
    normal = me.attributes.new("normal", "FLOAT_VECTOR", "POINT")
    normal.data.foreach_set("vector", nrm.astype(np.float32).ravel())
    ob = bpy.data.objects.new("cloud", me)
    bpy.context.collection.objects.link(ob)
    for o in bpy.context.view_layer.objects.selected:
        o.select_set(False)
    bpy.context.view_layer.objects.active = ob
    ob.select_set(True)
    assert bpy.ops.object.convert(target="POINTCLOUD") == {"FINISHED"}
    cloud = bpy.context.active_object
    assert cloud.type == "POINTCLOUD"
    assert ext("source").describe(cloud).count == 300
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    new = bpy.context.active_object
    assert new.name == "cloud_nkf" and new.type == "MESH"
    assert _radial_error(world_vertices(new), (0, 0, 0), 0.5).max() < 0.04


def test_python_function_returns_the_new_object_without_touching_selection_of_source(
    scene, bpy_module, sphere_ply
):
    bpy = bpy_module
    src = import_ply(bpy, sphere_ply)
    other = bpy.data.objects.new("empty", None)
    bpy.context.collection.objects.link(other)
    bpy.context.view_layer.objects.active = other  # the function does not need src to be active
    api = ext("api")
    new = api.reconstruct_object(src, method="splines", resolution=32, regularization=1e-9)
    assert isinstance(new, bpy.types.Object) and new.name == "sphere_nkf"
    assert bpy.context.view_layer.objects.active == new
    assert _radial_error(world_vertices(new), CENTER, RADIUS).max() < 0.03
    with pytest.raises(api.UserError, match="resolution must be between"):
        api.reconstruct_object(src, method="splines", resolution=4)
    with pytest.raises(ValueError, match="method must be"):
        api.reconstruct_object(src, method="poisson")


def test_invoke_in_background_runs_synchronously_and_max_points_subsamples(
    scene, bpy_module, tmp_path, capsys
):
    bpy = bpy_module
    assert bpy.app.background
    pts, nrm = fibonacci_sphere(900, 1.0)
    src = import_ply(bpy, write_ply(tmp_path / "dense.ply", pts, nrm))
    res = bpy.ops.object.nkf_reconstruct("INVOKE_DEFAULT", method="SPLINES", resolution=32, max_points=250)
    assert res == {"FINISHED"}
    new = bpy.context.active_object
    assert new.name == "dense_nkf"
    rec = ext("runner").last_run(src)
    assert rec.state == "done" and rec.points == 250 and rec.triangles == len(new.data.polygons)
    assert "used a random 250 of 900 points" in rec.message
    out = capsys.readouterr().out
    assert "used a random 250 of 900 points" in out
    assert "NKF: solve" in out  # headless progress, one line per stage


def test_nkf_method_runs_or_says_clearly_why_not(scene, bpy_module, sphere_ply):
    bpy = bpy_module
    src = import_ply(bpy, sphere_ply)
    available, why = ext("methods").nkf_available()
    if available:
        assert bpy.ops.object.nkf_reconstruct(method="NKF", resolution=32) == {"FINISHED"}
        assert bpy.context.active_object.name == "sphere_nkf"
    else:
        assert why
        with pytest.raises(RuntimeError) as info:
            bpy.ops.object.nkf_reconstruct(method="NKF", resolution=32)
        assert why in str(info.value)
        assert bpy.context.active_object == src
        assert [o.name for o in bpy.data.objects] == ["sphere"]


def test_large_coordinates_keep_precision(scene, bpy_module, tmp_path):
    bpy = bpy_module
    far = (2.0e5, -1.0e5, 5.0e4)
    pts, nrm = fibonacci_sphere(300, 3.0, far)
    src = import_ply(bpy, write_ply(tmp_path / "far.ply", pts, nrm))
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    new = bpy.context.active_object
    err = _radial_error(world_vertices(new), far, 3.0)
    # float32 spacing at 2e5 is 0.016, i.e. 0.5 % of the radius: the error stays at that level.
    assert err.max() < 0.04 and math.isfinite(err.mean())
    assert src.name == "far"


def test_mesh_in_edit_mode_is_read_with_its_unsaved_edits(scene, bpy_module):
    import bmesh

    bpy = bpy_module
    bpy.ops.mesh.primitive_ico_sphere_add(radius=1.0, subdivisions=3)
    ob = bpy.context.active_object
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(ob.data)
    for v in bm.verts:
        v.co *= 2.0  # an edit not yet written to the mesh data
    bmesh.update_edit_mesh(ob.data)
    assert bpy.types.VIEW3D_PT_nkf.poll(bpy.context)
    assert bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=32) == {"FINISHED"}
    new = bpy.data.objects["Icosphere_nkf"]
    assert _radial_error(world_vertices(new), (0, 0, 0), 2.0).max() < 0.04
    assert ob.mode == "EDIT"
    bpy.ops.object.mode_set(mode="OBJECT")
