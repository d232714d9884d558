"""``nkf reconstruct`` on LAS/LAZ, E57, XYZ and PCD: map coordinates round trip, E57 scanner
positions as viewpoints, class filters, the output's permissions, and bad inputs (one line, exit 1,
no output)."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest
from plyfile import PlyData
from pointcloud_files import pcd_bytes, sphere, write_e57, write_las
from scipy.spatial import cKDTree

from nkf_model.cli import main
from nkf_model.io.files import write_point_cloud

MAP = np.array([4_500_000.0, 5_400_000.0, 250.0])
FAST = ["--resolution", "48", "--device", "cpu", "--method", "splines"]


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def ply_vertices(path) -> np.ndarray:
    el = PlyData.read(str(path))["vertex"]
    assert el["x"].dtype == np.float64 or np.abs(el["x"]).max() < 1e4
    return np.stack([np.asarray(el[c], np.float64) for c in "xyz"], axis=1)


def test_laz_in_map_coordinates_lands_within_a_millimetre(tmp_path, capsys):
    p, _ = sphere(800, seed=1, radius=10.0)
    p = np.round(p, 3)  # millimetres: the LAZ (scale 0.1 mm) and the PLY hold the same values
    write_point_cloud(tmp_path / "local.ply", p)
    write_las(tmp_path / "map.laz", p + MAP, scale=1e-4)
    code, _, err = run(["reconstruct", tmp_path / "local.ply", tmp_path / "local_mesh.ply", *FAST], capsys)
    assert code == 0, err
    code, out, err = run(["reconstruct", tmp_path / "map.laz", tmp_path / "map_mesh.ply", *FAST], capsys)
    assert code == 0, err
    assert "read " in out and "LAZ 1.2 point format 3: 800 points" in out and "offset 4500000 5400000" in out
    local = ply_vertices(tmp_path / "local_mesh.ply")
    mapped = ply_vertices(tmp_path / "map_mesh.ply")
    assert np.abs(mapped).max() > 4e6  # written in map coordinates, as doubles
    d_ab = cKDTree(local).query(mapped - MAP)[0]
    d_ba = cKDTree(mapped - MAP).query(local)[0]
    assert max(d_ab.max(), d_ba.max()) < 1e-3, (d_ab.max(), d_ba.max())
    # And the mesh lies on the sphere it came from, in map coordinates.
    r = np.linalg.norm(mapped - MAP, axis=1)
    assert np.abs(r - 10.0).max() < 0.2


def test_obj_in_map_coordinates_keeps_millimetres(tmp_path, capsys):
    p, _ = sphere(500, seed=2, radius=5.0)
    write_las(tmp_path / "m.las", p + MAP)
    code, _, err = run(["reconstruct", tmp_path / "m.las", tmp_path / "m.obj", *FAST], capsys)
    assert code == 0, err
    v = np.array([[float(t) for t in line.split()[1:4]] for line in (tmp_path / "m.obj").read_text().splitlines()
                  if line.startswith("v ")])
    r = np.linalg.norm(v - MAP, axis=1)
    assert np.abs(r - 5.0).max() < 0.1  # float32 positions would be off by up to 0.25 m here


def test_e57_scanner_positions_orient_the_normals(tmp_path, capsys):
    a, _ = sphere(600, seed=3, radius=1.0)
    # Two scanners outside a unit sphere, each seeing the half facing it (in its own frame).
    t1, t2 = np.array([4.0, 0, 0]), np.array([-4.0, 0, 0])
    s1 = a[a[:, 0] > -0.2]
    s2 = a[a[:, 0] < 0.2]
    path = write_e57(tmp_path / "two.e57", [{"xyz": s1 - t1, "translation": t1}, {"xyz": s2 - t2, "translation": t2}])
    code, out, err = run(["reconstruct", path, tmp_path / "m.ply", *FAST], capsys)
    assert code == 0, err
    assert "orienting estimated normals towards its 2 scanner positions" in err
    assert "E57: " in out and "2 scans" in out
    v = ply_vertices(tmp_path / "m.ply")
    assert np.abs(np.linalg.norm(v, axis=1) - 1.0).max() < 0.1


def test_classes_filter_and_text_and_pcd(tmp_path, capsys):
    p, n = sphere(600, seed=4, radius=2.0)
    junk = np.random.default_rng(0).uniform(-5, 5, size=(300, 3))  # "vegetation" to leave out
    cls = np.r_[np.full(600, 6), np.full(300, 5)]
    write_las(tmp_path / "c.laz", np.r_[p, junk] + MAP, classification=cls)
    code, out, err = run(["reconstruct", tmp_path / "c.laz", tmp_path / "c.ply", "--classes", "2,6", *FAST], capsys)
    assert code == 0, err
    assert "600 points" in out and "300 points of other classes left out" in out
    r = np.linalg.norm(ply_vertices(tmp_path / "c.ply") - MAP, axis=1)
    assert np.abs(r - 2.0).max() < 0.1
    np.savetxt(tmp_path / "s.xyz", np.c_[p, n])
    code, out, err = run(["reconstruct", tmp_path / "s.xyz", tmp_path / "s.ply", *FAST], capsys)
    assert code == 0, err and "normals" in out and "estimating" not in err
    (tmp_path / "s.pcd").write_bytes(pcd_bytes({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "normal_x": n[:, 0],
                                                "normal_y": n[:, 1], "normal_z": n[:, 2]}, "binary_compressed"))
    code, out, err = run(["reconstruct", tmp_path / "s.pcd", tmp_path / "p.ply", *FAST], capsys)
    assert code == 0, err
    assert "PCD (binary_compressed): 600 points, normals" in out and "estimating" not in err


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_output_honours_the_umask(tmp_path, capsys, mask):
    p, n = sphere(300, seed=5)
    write_point_cloud(tmp_path / "a.ply", p, n)
    old = os.umask(mask)
    try:
        code, _, err = run(["reconstruct", tmp_path / "a.ply", tmp_path / "m.ply", *FAST, "--quiet"], capsys)
    finally:
        os.umask(old)
    assert code == 0, err
    assert stat.S_IMODE((tmp_path / "m.ply").stat().st_mode) == 0o666 & ~mask


def test_replacing_a_file_keeps_its_permissions(tmp_path, capsys):
    p, n = sphere(300, seed=6)
    write_point_cloud(tmp_path / "a.ply", p, n)
    out = tmp_path / "m.obj"
    out.write_text("old")
    out.chmod(0o640)
    code, _, err = run(["reconstruct", tmp_path / "a.ply", out, *FAST, "--quiet"], capsys)
    assert code == 0, err
    assert stat.S_IMODE(out.stat().st_mode) == 0o640 and out.read_text() != "old"


def bad(tmp_path, capsys, src, match, out_name="out.ply", extra=()):
    before = src.read_bytes()
    out = tmp_path / out_name
    code, stdout, err = run(["reconstruct", src, out, *FAST, "--quiet", *extra], capsys)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("nkf: error: "), err
    assert match in lines[0] and "Traceback" not in err
    assert not out.exists() and list(tmp_path.glob("*.part")) == []
    assert src.read_bytes() == before
    return lines[0]


def test_bad_inputs_one_line_no_output(tmp_path, capsys):
    p, _ = sphere(400, seed=7)
    data = write_las(tmp_path / "a.laz", p + MAP).read_bytes()
    (tmp_path / "t.laz").write_bytes(data[: len(data) // 2])
    line = bad(tmp_path, capsys, tmp_path / "t.laz", "truncated or corrupt LAZ data")
    assert "t.laz" in line
    raw = bytearray((write_las(tmp_path / "b.las", p)).read_bytes())
    raw[104] = 42
    (tmp_path / "u.las").write_bytes(bytes(raw))
    bad(tmp_path, capsys, tmp_path / "u.las", "unsupported LAS point format 42")
    write_e57(tmp_path / "none.e57", [])
    bad(tmp_path, capsys, tmp_path / "none.e57", "holds no 3D scans")
    lines = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in p]
    (tmp_path / "m.xyz").write_text("\n".join(lines[:100] + ["scan paused"] + lines[100:]) + "\n")
    bad(tmp_path, capsys, tmp_path / "m.xyz", "line 101 is not a row of numbers")
    (tmp_path / "v.xyz").write_text("\n".join(lines[:50] + [lines[50] + " 1 2"] + lines[51:]) + "\n")
    bad(tmp_path, capsys, tmp_path / "v.xyz", "line 51 has 5 columns, the lines before have 3")
    good = pcd_bytes({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}, "binary")
    (tmp_path / "f.pcd").write_bytes(good.replace(b"TYPE F F F", b"TYPE F F X"))
    bad(tmp_path, capsys, tmp_path / "f.pcd", "unsupported PCD field layout: field 'z' TYPE X SIZE 4")
    (tmp_path / "e.xyz").write_text("")
    bad(tmp_path, capsys, tmp_path / "e.xyz", "holds no points")
    bad(tmp_path, capsys, tmp_path / "a.laz", "--classes takes classification codes", extra=["--classes", "x"])
    bad(tmp_path, capsys, tmp_path / "a.laz", "column names apply to text files", extra=["--columns", "x y z"])


def test_no_space_for_the_output(tmp_path, capsys, monkeypatch):
    import shutil as real_shutil

    import nkf_model.io.files as fio

    p, n = sphere(300, seed=8)
    write_point_cloud(tmp_path / "a.ply", p, n)
    usage = real_shutil.disk_usage(tmp_path)

    class NoRoom:
        @staticmethod
        def disk_usage(path):
            return type(usage)(usage.total, usage.total - 1000, 1000)

    monkeypatch.setattr(fio, "shutil", NoRoom)
    line = bad(tmp_path, capsys, tmp_path / "a.ply", "not enough space in")
    assert "MiB are free" in line


def test_a_write_that_fails_midway_leaves_nothing(tmp_path, capsys, monkeypatch):
    import errno

    import nkf_model.io.files as fio

    p, n = sphere(300, seed=9)
    write_point_cloud(tmp_path / "a.ply", p, n)

    def full(fh, *args):
        fh.write(b"ply\n" * 1000)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(fio, "_write_ply_mesh", full)
    bad(tmp_path, capsys, tmp_path / "a.ply", "cannot be written (No space left on device)")


def test_columns_option_for_text(tmp_path, capsys):
    p, n = sphere(500, seed=10, radius=2.0)
    np.savetxt(tmp_path / "odd.txt", np.c_[np.arange(500), n, p])  # id nx ny nz x y z: no guess fits
    code, _, err = run(["reconstruct", tmp_path / "odd.txt", tmp_path / "o.ply", *FAST, "--quiet"], capsys)
    assert code == 1 and "cannot tell what its 7 columns are" in err and "--columns" in err
    code, out, err = run(["reconstruct", tmp_path / "odd.txt", tmp_path / "o.ply", *FAST,
                          "--columns", "_ nx ny nz x y z"], capsys)
    assert code == 0, err
    assert "TXT text: 500 points, normals" in out and "estimating" not in err
    r = np.linalg.norm(ply_vertices(tmp_path / "o.ply"), axis=1)
    assert np.abs(r - 2.0).max() < 0.1
