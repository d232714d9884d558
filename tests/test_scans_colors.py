"""Per-point colours carried onto the mesh and written to PLY/OBJ (issue 5)."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData
from shapes import sphere_points

import nkf_model
from nkf_model.io.files import read_point_cloud, write_mesh, write_point_cloud
from nkf_model.surface.colors import as_rgb8, transfer_colors


@pytest.fixture(scope="module")
def coloured_sphere():
    p, n = sphere_points(2000, seed=3)
    colors = np.where(p[:, 2:3] > 0, [[230, 20, 20]], [[20, 20, 230]]).astype(np.uint8)  # red top, blue bottom
    m = nkf_model.reconstruct(p, n, resolution=48, device="cpu", colors=colors)
    return p, n, colors, m


def test_colours_land_on_the_right_vertices(coloured_sphere):
    _, _, _, m = coloured_sphere
    assert m.colors is not None and m.colors.shape == (len(m.vertices), 3) and m.colors.dtype == np.uint8
    # Beyond the reach of the 8 nearest points (about 0.1 here) of the other half:
    top = m.vertices[:, 2] > 0.25
    bottom = m.vertices[:, 2] < -0.25
    assert (m.colors[top] == [230, 20, 20]).all()
    assert (m.colors[bottom] == [20, 20, 230]).all()
    # Near the equator the colours blend between the two.
    mid = np.abs(m.vertices[:, 2]) < 0.02
    assert ((m.colors[mid, 0] > 20) & (m.colors[mid, 0] < 230)).any()


def test_inverse_distance_weights():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    cols = np.array([[0.0, 0, 0], [255.0, 255, 255]])
    out = transfer_colors(np.array([[0.0, 0, 0], [0.25, 0, 0], [0.5, 0, 0]]), pts, cols, k=2)
    assert out[0].tolist() == [0, 0, 0]  # on top of a point: its colour
    # 1/d^2 weights: at 0.25 the weights are 16 and 16/9: 255 * (16/9) / (16 + 16/9) = 25.5
    assert out[1].tolist() == [26, 26, 26] or out[1].tolist() == [25, 25, 25]
    assert out[2].tolist() == [128, 128, 128] or out[2].tolist() == [127, 127, 127]


def test_float_and_rgba_colours_are_accepted():
    c = as_rgb8(np.array([[1.0, 0.5, 0.0, 1.0]]), 1)
    assert np.allclose(c, [[255, 127.5, 0]])
    with pytest.raises(nkf_model.InvalidPointCloudError):
        as_rgb8(np.zeros((3, 2)), 3)
    with pytest.raises(nkf_model.InvalidPointCloudError):
        as_rgb8(np.zeros((4, 3)), 3)


@pytest.mark.parametrize("ext", [".ply", ".obj"])
def test_colours_are_written(tmp_path, coloured_sphere, ext):
    _, _, _, m = coloured_sphere
    out = write_mesh(tmp_path / f"m{ext}", m.vertices, m.faces, m.normals, m.colors)
    if ext == ".ply":
        el = PlyData.read(str(out))["vertex"]
        for name in ("red", "green", "blue"):
            assert el[name].dtype == np.uint8
        got = np.stack([el["red"], el["green"], el["blue"]], axis=1)
        assert (got == m.colors).all()
    else:
        rows = [line.split() for line in out.read_text().splitlines() if line.startswith("v ")]
        rgb = np.array([[float(x) for x in r[4:7]] for r in rows])
        assert np.allclose(rgb * 255, m.colors, atol=0.01)


def test_coloured_point_cloud_round_trip(tmp_path):
    p, n = sphere_points(50)
    c = (np.arange(150) % 256).reshape(50, 3).astype(np.uint8)
    write_point_cloud(tmp_path / "c.ply", p, n, c)
    cloud = read_point_cloud(tmp_path / "c.ply")
    assert (cloud.colors == c).all() and np.allclose(cloud.normals, n, atol=1e-6)
    write_point_cloud(tmp_path / "nn.ply", p)
    assert read_point_cloud(tmp_path / "nn.ply").normals is None
