"""The ``nkf`` command line end to end, and every bad input: one line on stderr, no traceback,
a non-zero exit, and no output file left behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shapes import sphere_points

from nkf_model.cli import main
from nkf_model.io.files import read_mesh, write_point_cloud

SAMPLE = Path(__file__).resolve().parent.parent / "nkf_model" / "data" / "sample.ply"


def write_ascii_ply(path, pts, nrm=None, extra_header=""):
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if nrm is not None else [])
    rows = pts if nrm is None else np.concatenate([pts, nrm], axis=1)
    with open(path, "w") as fh:
        fh.write("ply\nformat ascii 1.0\n" + extra_header + f"element vertex {len(pts)}\n")
        fh.writelines(f"property float {p}\n" for p in props)
        fh.write("end_header\n")
        for r in rows:
            fh.write(" ".join(f"{x:.7g}" for x in r) + "\n")


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def cloud(tmp_path):
    p, n = sphere_points(400, radius=2.0, center=(10.0, 0.0, -5.0), seed=1)
    path = tmp_path / "cloud.ply"
    write_point_cloud(path, p, n)
    return path


def test_reconstruct_binary_ply_to_ply(cloud, tmp_path, capsys):
    out = tmp_path / "mesh.ply"
    code, stdout, err = run(["reconstruct", cloud, out, "--resolution", "48", "--device", "cpu"], capsys)
    assert code == 0, err
    v, f = read_mesh(out)
    assert len(f) > 1000
    # In the input's frame.
    r = np.linalg.norm(v - [10.0, 0.0, -5.0], axis=1)
    assert np.abs(r - 2.0).max() < 0.05
    assert "400 points" in stdout and "triangles" in stdout
    for stage in ("read", "solve", "evaluate", "mesh", "write"):
        assert stage in stdout
    assert list(tmp_path.glob("*.part")) == []


def test_reconstruct_ascii_ply_to_obj(tmp_path, capsys):
    p, n = sphere_points(300, seed=2)
    src = tmp_path / "ascii.ply"
    write_ascii_ply(src, p, n, extra_header="comment made by a test\n")
    out = tmp_path / "mesh.obj"
    code, _, err = run(["reconstruct", src, out, "--resolution", "32", "--quiet"], capsys)
    assert code == 0, err
    text = out.read_text().splitlines()
    verts = np.array([list(map(float, l.split()[1:])) for l in text if l.startswith("v ")])
    faces = [l for l in text if l.startswith("f ")]
    assert len(verts) > 100 and len(faces) > 100
    assert np.abs(np.linalg.norm(verts, axis=1) - 1).max() < 0.05
    assert any(l.startswith("vn ") for l in text)


def test_quiet_prints_nothing(cloud, tmp_path, capsys):
    code, out, err = run(["reconstruct", cloud, tmp_path / "m.ply", "--resolution", "32", "--quiet"], capsys)
    assert code == 0 and out == "" and err == ""


def test_progress_bar_and_max_points(cloud, tmp_path, capsys):
    code, out, err = run(["reconstruct", cloud, tmp_path / "m.ply", "--resolution", "32", "--max-points", "150"],
                         capsys)
    assert code == 0
    assert "using a random 150 of 400 points (--max-points)" in err
    assert "150 points" in out
    assert "solve" in err and "%" in err  # the progress bar


def test_module_entry_point_and_console_script(cloud, tmp_path):
    out = tmp_path / "m.ply"
    r = subprocess.run([sys.executable, "-m", "nkf_model", "reconstruct", str(cloud), str(out),
                        "--resolution", "24", "--quiet"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert out.exists()
    exe = Path(sys.executable).parent / "nkf"
    if exe.exists():
        r = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and r.stdout.startswith("nkf ")


def test_sample_reconstructs(tmp_path, capsys):
    out = tmp_path / "sample.ply"
    code, stdout, err = run(["reconstruct", SAMPLE, out, "--resolution", "48", "--quiet"], capsys)
    assert code == 0, err
    v, f = read_mesh(out)
    assert len(f) > 1000


def bad_case(tmp_path, name):
    """Build the input for one bad case; returns (args, expected text in the error line)."""
    out = tmp_path / "out.ply"
    p, n = sphere_points(200, seed=3)
    src = tmp_path / "in.ply"
    if name == "missing file":
        return [tmp_path / "nope.ply", out], "no such file"
    if name == "folder as input":
        return [tmp_path, out], "is a folder"
    if name == "corrupt file":
        src.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
                        b"property float y\nproperty float z\nend_header\n" + b"\x00" * 50)
        return [src, out], "not a valid PLY file"
    if name == "not a ply":
        src.write_text("hello, this is not a point cloud\n")
        return [src, out], "not a valid PLY file"
    if name == "unreadable file":
        write_point_cloud(src, p, n)
        os.chmod(src, 0)
        return [src, out], "permission denied"
    if name == "no normals":
        write_ascii_ply(src, p)
        return [src, out, "--normals", "given"], "normals are required"
    if name == "few points":
        write_point_cloud(src, p[:7], n[:7])
        return [src, out], "at least 10 are needed"
    if name == "all identical":
        write_point_cloud(src, np.ones((30, 3)), n[:30])
        return [src, out], "usable point"
    if name == "on a line":
        t = np.linspace(0, 1, 40)[:, None]
        write_point_cloud(src, t * [1.0, 2.0, 3.0], n[:40])
        return [src, out], "line"
    if name == "on a plane":
        q = p.copy()
        q[:, 2] = 0.0
        write_point_cloud(src, q, n)
        return [src, out], "plane"
    if name == "nan everywhere":
        write_point_cloud(src, np.full((50, 3), np.nan), n[:50])
        return [src, out], "0 usable points"
    if name == "resolution":
        write_point_cloud(src, p, n)
        return [src, out, "--resolution", "4000"], "resolution must be between"
    if name == "negative lambda":
        write_point_cloud(src, p, n)
        return [src, out, "--lam", "-1"], "lambda must be"
    if name == "missing folder":
        write_point_cloud(src, p, n)
        return [src, tmp_path / "no" / "such" / "dir" / "m.ply"], "does not exist"
    if name == "read-only folder":
        write_point_cloud(src, p, n)
        ro = tmp_path / "ro"
        ro.mkdir()
        os.chmod(ro, 0o500)
        return [src, ro / "m.ply"], "not writable"
    if name == "folder cannot hold files":
        write_point_cloud(src, p, n)
        return [src, "/proc/nkf-test-mesh.ply"], "cannot be written"
    if name == "parent is a file":
        write_point_cloud(src, p, n)
        return [src, src / "m.ply"], "is not a folder"
    if name == "dangling link":
        (tmp_path / "link.ply").symlink_to(tmp_path / "gone.ply")
        return [tmp_path / "link.ply", out], "no such file"
    if name == "unknown format":
        write_point_cloud(src, p, n)
        return [src, tmp_path / "m.stl"], "unsupported output format"
    if name == "nkf without weights":
        write_point_cloud(src, p, n)
        return [src, out, "--method", "nkf"], "nkf"
    raise AssertionError(name)


CASES = ["missing file", "folder as input", "corrupt file", "not a ply", "unreadable file", "no normals",
         "few points", "all identical", "on a line", "on a plane", "nan everywhere", "resolution",
         "negative lambda", "missing folder", "read-only folder", "folder cannot hold files", "parent is a file",
         "dangling link", "unknown format"]


@pytest.mark.parametrize("name", CASES)
def test_bad_input_one_line_no_output(tmp_path, capsys, name):
    if name in ("unreadable file", "read-only folder") and os.geteuid() == 0:
        pytest.skip("root ignores file permissions")
    args, expected = bad_case(tmp_path, name)
    code, out, err = run(["reconstruct", *args, "--quiet"], capsys)
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("nkf: error:") and expected in lines[0], lines[0]
    assert "Traceback" not in err
    made = (".ply", ".obj", ".stl", ".part")
    outs = [p for p in tmp_path.rglob("*") if p.suffix in made and p.name not in ("in.ply", "link.ply")]
    assert outs == []


def test_debug_shows_the_exception(tmp_path, capsys):
    with pytest.raises(ValueError):
        main(["reconstruct", str(tmp_path / "nope.ply"), str(tmp_path / "o.ply"), "--debug"])


def test_nan_rows_warned_on_stderr(tmp_path, capsys):
    p, n = sphere_points(300, seed=4)
    p[:3] = np.nan
    src = tmp_path / "in.ply"
    write_point_cloud(src, p, n)
    code, out, err = run(["reconstruct", src, tmp_path / "o.ply", "--resolution", "32"], capsys)
    assert code == 0
    assert "warning: dropped 3 points with NaN or infinite coordinates" in err


def test_unknown_option_exits_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", "a.ply", "b.ply", "--bogus"])
    assert e.value.code == 2


def test_existing_output_survives_a_failed_run(tmp_path, capsys):
    out = tmp_path / "keep.ply"
    out.write_bytes(b"precious")
    src = tmp_path / "in.ply"
    write_point_cloud(src, np.ones((30, 3)), np.ones((30, 3)))
    code, _, _ = run(["reconstruct", src, out, "--quiet"], capsys)
    assert code != 0
    assert out.read_bytes() == b"precious"


def test_close_flag_reaches_the_reconstruction(tmp_path, capsys):
    # Half a sphere: the open rim's inside runs into the grid's bounds unless --close caps it.
    p, n = sphere_points(800, radius=1.0, seed=2)
    keep = p[:, 2] > 0
    src = tmp_path / "half.ply"
    write_point_cloud(src, p[keep], n[keep])
    counts = []
    for extra in ([], ["--close"]):
        out = tmp_path / f"half{len(extra)}.ply"
        code, _, _ = run(["reconstruct", src, out, "--resolution", "32", "--quiet", *extra], capsys)
        assert code == 0
        _, f = read_mesh(out)
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).astype(np.int64), axis=1)
        _, c = np.unique(e[:, 0] * (int(f.max()) + 1) + e[:, 1], return_counts=True)
        counts.append(int((c == 1).sum()))
    assert counts[0] > 0 and counts[1] == 0
