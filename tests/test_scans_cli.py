"""The command line for scans: --normals modes, hints, trimming, colours, reduction, estimate, budget."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData
from scan_shapes import hemisphere_points
from shapes import sphere_points

from nkf_model.cli import main
from nkf_model.io.files import read_mesh, write_point_cloud


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def files(tmp_path):
    p, n = sphere_points(800, radius=2.0, center=(10.0, 0.0, -5.0), seed=1)
    c = np.where(p[:, 2:3] > -5.0, [[250, 0, 0]], [[0, 0, 250]]).astype(np.uint8)
    with_normals = write_point_cloud(tmp_path / "with.ply", p, n, c)
    without = write_point_cloud(tmp_path / "without.ply", p, None, c)
    wrong = write_point_cloud(tmp_path / "wrong.ply", p, -n)  # normals pointing in
    return tmp_path, p, with_normals, without, wrong


def radius_error(path, center=(10.0, 0.0, -5.0), r=2.0):
    v, _ = read_mesh(path)
    return np.abs(np.linalg.norm(v - np.asarray(center), axis=1) - r).max()


def test_auto_estimates_missing_normals_and_says_so(files, capsys):
    tmp, _, _, without, _ = files
    code, out, err = run(["reconstruct", without, tmp / "a.ply", "--resolution", "40"], capsys)
    assert code == 0, err
    assert "has no normals: estimating them" in err
    assert "normals estimated" in out
    assert radius_error(tmp / "a.ply") < 0.08


def test_auto_uses_given_normals_silently(files, capsys):
    tmp, _, with_normals, _, _ = files
    code, out, err = run(["reconstruct", with_normals, tmp / "b.ply", "--resolution", "40", "--quiet"], capsys)
    assert code == 0 and "estimating" not in err


def test_given_requires_normals(files, capsys):
    tmp, _, _, without, _ = files
    code, out, err = run(["reconstruct", without, tmp / "c.ply", "--normals", "given", "--quiet"], capsys)
    assert code == 1 and "normals are required" in err and len(err.strip().splitlines()) == 1
    assert not (tmp / "c.ply").exists()


def signed_volume(path):
    v, f = read_mesh(path)
    v = v - v.mean(axis=0)
    return np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0


def test_estimate_ignores_the_files_normals(files, capsys):
    tmp, _, _, _, wrong = files
    code, _, err = run(["reconstruct", wrong, tmp / "d.ply", "--resolution", "40", "--quiet"], capsys)
    assert code == 0 and signed_volume(tmp / "d.ply") < 0  # the file's inward normals turn it inside out...
    code, _, err = run(["reconstruct", wrong, tmp / "e.ply", "--resolution", "40", "--normals", "estimate",
                        "--quiet"], capsys)
    assert code == 0, err  # ...estimating them instead repairs that
    assert signed_volume(tmp / "e.ply") > 0 and radius_error(tmp / "e.ply") < 0.08


def test_viewpoint_hint_and_colours(files, capsys):
    tmp, _, _, without, _ = files
    code, out, err = run(["reconstruct", without, tmp / "e.ply", "--resolution", "40", "--orient", "outward"],
                         capsys)
    assert code == 0, err
    el = PlyData.read(str(tmp / "e.ply"))["vertex"]
    rgb = np.stack([el["red"], el["green"], el["blue"]], axis=1)
    z = np.asarray(el["z"])
    assert (rgb[z > -4.0] == [250, 0, 0]).all() and (rgb[z < -6.0] == [0, 0, 250]).all()
    code, _, err = run(["reconstruct", without, tmp / "f.ply", "--resolution", "40", "--no-colors", "--quiet"],
                       capsys)
    assert code == 0 and "red" not in {p.name for p in PlyData.read(str(tmp / "f.ply"))["vertex"].properties}
    code, _, err = run(["reconstruct", without, tmp / "g.ply", "--orient", "viewpoint", "--quiet"], capsys)
    assert code == 1 and "viewpoint" in err


def test_scan_trims_an_open_hemisphere(tmp_path, capsys):
    p, _ = hemisphere_points(3000, seed=1)
    src = write_point_cloud(tmp_path / "hemi.ply", p)
    code, out, err = run(["reconstruct", src, tmp_path / "h.obj", "--resolution", "40", "--scan",
                          "--viewpoint", "0", "0", "3"], capsys)
    assert code == 0, err
    assert "triangles trimmed" in out
    rows = [line.split() for line in (tmp_path / "h.obj").read_text().splitlines() if line.startswith("v ")]
    zs = np.array([float(r[3]) for r in rows])
    assert zs.min() > -0.15  # the closed blob below the rim is gone


def test_dry_run_and_memory_budget(files, capsys):
    tmp, _, with_normals, _, _ = files
    code, out, err = run(["reconstruct", with_normals, tmp / "i.ply", "--dry-run"], capsys)
    assert code == 0 and "estimate: about" in out and not (tmp / "i.ply").exists()
    code, out, err = run(["reconstruct", with_normals, tmp / "i.ply", "--resolution", "1024",
                          "--memory-budget", "0.2", "--quiet"], capsys)
    assert code == 1 and "memory budget" in err and "resolution" in err
    assert not (tmp / "i.ply").exists()
    code, out, err = run(["reconstruct", with_normals, tmp / "i.ply", "--memory-budget", "-1"], capsys)
    assert code == 1 and "--memory-budget" in err


def test_reduce_to_is_reported(files, capsys):
    tmp, p, _, without, _ = files
    big = np.repeat(p, 2, axis=0) + np.random.default_rng(0).normal(scale=1e-3, size=(2 * len(p), 3))
    src = write_point_cloud(tmp / "big.ply", big)
    code, out, err = run(["reconstruct", src, tmp / "j.ply", "--resolution", "32", "--reduce-to", "1000"], capsys)
    assert code == 0, err
    assert "reducing to at most 1,000" in err and "reduced from 1,600" in out
