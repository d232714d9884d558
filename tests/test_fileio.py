"""PLY reading (ASCII and binary) and mesh writing (PLY, OBJ), atomically."""

from __future__ import annotations

import numpy as np
import pytest

from nkf_model.errors import OutputPathError, PointCloudFileError
from nkf_model.io.files import read_mesh, read_point_cloud, write_mesh, write_point_cloud


def test_point_cloud_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3))
    n = rng.normal(size=(50, 3))
    write_point_cloud(tmp_path / "c.ply", p, n)
    c = read_point_cloud(tmp_path / "c.ply")
    np.testing.assert_allclose(c.points, p.astype(np.float32))
    np.testing.assert_allclose(c.normals, n.astype(np.float32))
    assert c.colors is None


def test_ascii_ply_with_double_coordinates_and_colours(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        "1000000.125 2 3 255 0 10\n4 5 6 1 2 3\n"
    )
    c = read_point_cloud(path)
    # Large coordinates are recentred; the offset brings back the file's values exactly.
    assert c.offset[0] != 0 and c.absolute_points()[0, 0] == 1000000.125
    np.testing.assert_array_equal(c.absolute_points()[1], [4, 5, 6])
    assert c.normals is None
    np.testing.assert_array_equal(c.colors, [[255, 0, 10], [1, 2, 3]])


def test_mesh_round_trip_ply_and_obj(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    write_mesh(tmp_path / "m.ply", v, f, v)
    v2, f2 = read_mesh(tmp_path / "m.ply")
    np.testing.assert_allclose(v2, v)
    np.testing.assert_array_equal(f2, f)
    write_mesh(tmp_path / "m.obj", v, f)
    lines = (tmp_path / "m.obj").read_text().splitlines()
    assert [l for l in lines if l.startswith("f ")][0] == "f 1 3 2"


def test_write_is_atomic_when_interrupted(tmp_path, monkeypatch):
    target = tmp_path / "m.ply"
    target.write_bytes(b"old")
    import nkf_model.io.files as fio

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fio, "_write_ply_mesh", boom)
    with pytest.raises(KeyboardInterrupt):
        write_mesh(target, np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


def test_truncated_binary_ply(tmp_path):
    write_point_cloud(tmp_path / "c.ply", np.zeros((100, 3)), np.ones((100, 3)))
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(PointCloudFileError, match="not a valid PLY file"):
        read_point_cloud(tmp_path / "t.ply")


def test_ply_without_vertices_or_positions(tmp_path):
    (tmp_path / "e.ply").write_text(
        "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with pytest.raises(PointCloudFileError, match="no 'vertex' element"):
        read_point_cloud(tmp_path / "e.ply")
    (tmp_path / "q.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float q\nend_header\n1\n")
    with pytest.raises(PointCloudFileError, match="x/y/z"):
        read_point_cloud(tmp_path / "q.ply")


def test_output_path_checks(tmp_path):
    with pytest.raises(OutputPathError, match="unsupported output format"):
        write_mesh(tmp_path / "m.stl", np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(OutputPathError, match="does not exist"):
        write_mesh(tmp_path / "x" / "m.ply", np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(OutputPathError, match="is a folder"):
        (tmp_path / "d.ply").mkdir()
        write_mesh(tmp_path / "d.ply", np.zeros((3, 3)), np.array([[0, 1, 2]]))
