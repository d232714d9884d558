"""File > Import > Point Cloud in the real ``bpy`` with the real extension: LAS/LAZ, E57, XYZ, PCD
through nkf_model's readers; attributes named as Blender's PLY import names them; map coordinates
recentred with the offset on the object and written back by the map-coordinates export; E57 scanner
positions as empties that orient estimated normals; a bad file adds nothing."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from blender_helpers import ext, read_vectors
from recording_layout import RecordingLayout

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pointcloud_files import pcd_bytes, sphere, write_e57, write_las  # noqa: E402

IMPORT = "import_scene.nkf_point_cloud"
MAP = np.array([4_500_000.0, 5_400_000.0, 250.0])


def _import(bpy, path, **kw):
    before = set(bpy.data.objects)
    assert bpy.ops.import_scene.nkf_point_cloud(filepath=str(path), **kw) == {"FINISHED"}
    return [o for o in bpy.data.objects if o not in before]


def _values(data, name, key="value", width=1):
    attr = data.attributes[name]
    buf = np.empty(len(attr.data) * width, dtype=np.float32 if attr.data_type != "INT" else np.int32)
    attr.data.foreach_get(key, buf)
    return buf.reshape(-1, width) if width > 1 else buf


def test_registered_with_menu_and_drag_and_drop(scene, bpy_module):
    bpy = bpy_module
    assert hasattr(bpy.types, "IMPORT_SCENE_OT_nkf_point_cloud")
    assert hasattr(bpy.types, "EXPORT_MESH_OT_nkf_map_coordinates")
    fh = bpy.types.IO_FH_nkf_point_cloud
    assert fh.bl_import_operator == IMPORT
    assert set(fh.bl_file_extensions.split(";")) == {".las", ".laz", ".e57", ".xyz", ".pts", ".txt", ".csv",
                                                     ".pcd", ".ply"}
    imp = ext("importer")
    assert imp._menu_import in bpy.types.TOPBAR_MT_file_import.draw._draw_funcs
    assert imp._menu_export in bpy.types.TOPBAR_MT_file_export.draw._draw_funcs
    layout = RecordingLayout()  # checks the operator exists and the call is valid
    imp._menu_import(SimpleNamespace(layout=layout), bpy.context)
    assert "UNDO" in bpy.types.IMPORT_SCENE_OT_nkf_point_cloud.bl_options


def test_laz_as_point_cloud_in_map_coordinates(scene, bpy_module, tmp_path):
    bpy = bpy_module
    p, _ = sphere(2000, seed=1, radius=15.0)
    xyz = np.round((p + MAP) / 1e-4) * 1e-4
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(2000, 3))
    cls = rng.choice([2, 6], size=2000)
    path = write_las(tmp_path / "city.laz", xyz, rgb=rgb * 257, intensity=np.arange(2000), classification=cls)
    (ob,) = _import(bpy, path)
    assert ob.name == "city" and ob.type == "POINTCLOUD" and len(ob.data.points) == 2000
    assert bpy.context.view_layer.objects.active == ob
    offset = np.array(ob["nkf_offset"], dtype=np.float64)
    pos = read_vectors(ob.data, "position").astype(np.float64)
    assert np.abs(pos).max() < 50  # near the origin: float32 keeps sub-millimetre detail
    assert np.abs(pos + offset - xyz).max() < 1e-3
    col = ob.data.attributes["Col"]
    assert col.data_type == "FLOAT_COLOR" and col.domain == "POINT"
    buf = np.empty(2000 * 4, dtype=np.float32)
    col.data.foreach_get("color_srgb", buf)
    np.testing.assert_array_equal(np.rint(buf.reshape(-1, 4)[:, :3] * 255), rgb)
    np.testing.assert_array_equal(_values(ob.data, "intensity"), np.arange(2000))
    np.testing.assert_array_equal(_values(ob.data, "classification"), cls)
    assert ".select_vert" not in ob.data.attributes
    assert [m for m in bpy.data.meshes if m.users == 0] == []  # the converted mesh is not left behind
    # The class filter, as a vertex-only mesh.
    (m,) = _import(bpy, path, as_mesh=True, classes="6")
    assert m.type == "MESH" and len(m.data.vertices) == int((cls == 6).sum())


def test_xyz_with_normals_feeds_the_panel(scene, bpy_module, tmp_path):
    bpy = bpy_module
    p, n = sphere(500, seed=2)
    np.savetxt(tmp_path / "obj.xyz", np.c_[p, n])
    (ob,) = _import(bpy, tmp_path / "obj.xyz", as_mesh=True)
    np.testing.assert_allclose(read_vectors(ob.data, "normal"), n, atol=1e-6)
    info = ext("source").describe(ob)
    assert info.count == 500 and info.normals == "'normal' attribute" and info.problem == ""
    assert not np.any(ob["nkf_offset"])


def test_e57_scanners_orient_and_the_result_exports_in_map_coordinates(scene, bpy_module, tmp_path):
    bpy = bpy_module
    a, _ = sphere(1500, seed=3, radius=2.0)
    t1, t2 = MAP + [8.0, 0, 0], MAP + [-8.0, 0, 0]
    s1, s2 = a[a[:, 0] > -0.3] + MAP, a[a[:, 0] < 0.3] + MAP
    path = write_e57(tmp_path / "site.e57", [{"xyz": s1 - t1, "translation": t1},
                                            {"xyz": s2 - t2, "translation": t2}])
    objs = _import(bpy, path)
    cloud = next(o for o in objs if o.type == "POINTCLOUD")
    empties = [o for o in objs if o.type == "EMPTY"]
    assert len(empties) == 2 and all(e.parent == cloud and e.get("nkf_scanner") for e in empties)
    offset = np.array(cloud["nkf_offset"])
    got = sorted(tuple(np.array(e.matrix_world.translation) + offset) for e in empties)
    np.testing.assert_allclose(got, sorted([tuple(t2), tuple(t1)]), atol=1e-3)
    assert bpy.context.scene.camera is None
    bpy.context.view_layer.objects.active = cloud
    settings = bpy.context.scene.nkf_settings
    settings.orientation, settings.normals_mode = "VIEWPOINT", "ESTIMATE"
    layout = RecordingLayout()
    bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
    shown = layout.joined()
    assert "Viewpoints: the 2 scanner position(s) of the scan" in shown and "needs a scene camera" not in shown
    vp = ext("runner").viewpoint(bpy.context, cloud)
    np.testing.assert_allclose(sorted(map(tuple, vp + offset)), sorted([tuple(t2), tuple(t1)]), atol=1e-3)
    bpy.context.view_layer.objects.active = cloud
    res = bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=48, orientation="VIEWPOINT",
                                         normals_mode="ESTIMATE")
    assert res == {"FINISHED"}
    result = bpy.context.view_layer.objects.active
    assert result.name == "site_nkf" and np.allclose(result["nkf_offset"], offset)
    out = tmp_path / "site_mesh.ply"
    assert bpy.ops.export_mesh.nkf_map_coordinates(filepath=str(out)) == {"FINISHED"}
    from plyfile import PlyData

    el = PlyData.read(str(out))["vertex"]
    assert el["x"].dtype == np.float64
    v = np.stack([el[c] for c in "xyz"], axis=1)
    r = np.linalg.norm(v - MAP, axis=1)
    assert np.abs(r - 2.0).max() < 0.1  # the sphere, back in map coordinates (outward normals found)


def test_pcd_and_several_files_at_once(scene, bpy_module, tmp_path):
    bpy = bpy_module
    p, _ = sphere(300, seed=4)
    (tmp_path / "a.pcd").write_bytes(pcd_bytes({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}, "binary"))
    np.savetxt(tmp_path / "b.xyz", p)
    before = set(bpy.data.objects)
    res = bpy.ops.import_scene.nkf_point_cloud(directory=str(tmp_path), files=[{"name": "a.pcd"}, {"name": "b.xyz"}])
    assert res == {"FINISHED"}
    assert sorted(o.name for o in bpy.data.objects if o not in before) == ["a", "b"]


@pytest.mark.parametrize("case", ["truncated", "text_line", "classes", "second_file_bad"])
def test_a_bad_file_adds_nothing(scene, bpy_module, tmp_path, case):
    bpy = bpy_module
    p, _ = sphere(3000, seed=5)
    data = write_las(tmp_path / "a.laz", p + MAP).read_bytes()
    (tmp_path / "t.laz").write_bytes(data[: len(data) // 2])
    lines = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in p[:100]]
    (tmp_path / "m.xyz").write_text("\n".join(lines[:10] + ["hello"] + lines[10:]) + "\n")
    kw, match = {
        "truncated": ({"filepath": str(tmp_path / "t.laz")}, "truncated or corrupt LAZ data"),
        "text_line": ({"filepath": str(tmp_path / "m.xyz")}, "line 11 is not a row of numbers"),
        "classes": ({"filepath": str(tmp_path / "a.laz"), "classes": "ground"}, "Classes: classification codes"),
        "second_file_bad": ({"directory": str(tmp_path), "files": [{"name": "a.laz"}, {"name": "m.xyz"}]},
                            "line 11 is not a row of numbers"),
    }[case]
    snapshot = {f.name: f.read_bytes() for f in tmp_path.iterdir()}
    n_objects, n_meshes, n_clouds = len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.pointclouds)
    with pytest.raises(RuntimeError, match=match) as info:
        bpy.ops.import_scene.nkf_point_cloud(**kw)
    assert len(str(info.value).strip().splitlines()) == 1
    assert (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.pointclouds)) == (n_objects, n_meshes, n_clouds)
    assert {f.name: f.read_bytes() for f in tmp_path.iterdir()} == snapshot
