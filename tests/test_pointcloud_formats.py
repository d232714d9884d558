"""Point-cloud readers by format (LAS/LAZ, E57, XYZ/PTS/TXT/CSV, PCD, PLY variants), the offset kept
for map coordinates, and every bad input: one PointCloudFileError line naming the file, the file
itself untouched."""

from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest
from pointcloud_files import lzf_compress, pack_rgb, pcd_bytes, sphere, write_e57, write_las

from nkf_model.errors import PointCloudFileError
from nkf_model.io.cloud import RECENTRE_ABOVE
from nkf_model.io.files import read_point_cloud
from nkf_model.io.pcd import lzf_decompress

MAP = np.array([4_500_000.0, 5_400_000.0, 250.0])  # a map projection's metres


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fails(path, match):
    """The read fails with one line that names the file, and the file is unchanged."""
    before = digest(path)
    with pytest.raises(PointCloudFileError, match=match) as info:
        read_point_cloud(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg or msg.startswith("reading ")
    assert digest(path) == before
    return msg


# ---- LAS / LAZ -------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_and_laz_in_map_coordinates(tmp_path, ext):
    p, _ = sphere(4000, seed=1, radius=20.0)
    xyz = np.round((p + MAP) / 1e-4) * 1e-4
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(4000, 3)) * 257  # 16-bit colours as the standard has them
    cls = rng.choice([1, 2, 6], size=4000)
    path = write_las(tmp_path / f"s{ext}", xyz, rgb=rgb, intensity=np.arange(4000) % 3000, classification=cls)
    c = read_point_cloud(path)
    assert c.points.dtype == np.float64 and c.points.shape == (4000, 3)
    assert np.abs(c.points).max() < 100  # recentred near the origin
    assert np.abs(c.offset).max() > RECENTRE_ABOVE
    assert np.abs(c.absolute_points() - xyz).max() < 1e-6  # the file's coordinates to well under 1 mm
    np.testing.assert_array_equal(c.colors, rgb // 257)
    np.testing.assert_array_equal(c.intensity, np.arange(4000) % 3000)
    np.testing.assert_array_equal(c.classification, cls)
    assert c.normals is None and c.viewpoints is None
    kind = "LAZ" if ext == ".laz" else "LAS"
    assert c.format == f"{kind} 1.2 point format 3"
    assert c.describe().startswith(f"{kind} 1.2 point format 3: 4,000 points, colours, intensity, classification")


def test_laz_is_compressed_and_classes_filter(tmp_path):
    p, _ = sphere(3000, seed=2, radius=5.0)
    cls = np.repeat([2, 6, 1], 1000)
    las = write_las(tmp_path / "a.las", p + MAP, classification=cls, point_format=6, version="1.4")
    laz = write_las(tmp_path / "a.laz", p + MAP, classification=cls, point_format=6, version="1.4")
    assert laz.stat().st_size < 0.6 * las.stat().st_size
    c = read_point_cloud(laz, classes=(2, 6))
    assert len(c.points) == 2000 and c.filtered == 1000 and set(np.unique(c.classification)) == {2, 6}
    np.testing.assert_allclose(c.absolute_points(), (p + MAP)[:2000], atol=1e-4)
    assert c.format == "LAZ 1.4 point format 6" and c.colors is None
    with pytest.raises(PointCloudFileError, match="no point of the classes asked for"):
        read_point_cloud(laz, classes=(9,))


def test_las_with_8bit_colours_in_16bit_fields(tmp_path):
    p, _ = sphere(500, seed=3)
    rgb = np.random.default_rng(1).integers(0, 256, size=(500, 3))
    c = read_point_cloud(write_las(tmp_path / "c.las", p, rgb=rgb))
    np.testing.assert_array_equal(c.colors, rgb)
    assert not np.any(c.offset)  # small coordinates are not moved


def test_bad_las_and_laz(tmp_path):
    p, _ = sphere(3000, seed=4)
    laz = write_las(tmp_path / "a.laz", p + MAP)
    data = laz.read_bytes()
    (tmp_path / "t.laz").write_bytes(data[: len(data) // 2])
    fails(tmp_path / "t.laz", "truncated or corrupt LAZ data")
    las = write_las(tmp_path / "a.las", p)
    raw = bytearray(las.read_bytes())
    (tmp_path / "t.las").write_bytes(bytes(raw[: len(raw) - 100]))
    fails(tmp_path / "t.las", "truncated")
    raw[104] = 42  # the point data format id
    (tmp_path / "u.las").write_bytes(bytes(raw))
    fails(tmp_path / "u.las", "unsupported LAS point format 42")
    (tmp_path / "x.las").write_text("x y z\n1 2 3\n")
    fails(tmp_path / "x.las", "not a readable LAS/LAZ file")
    write_las(tmp_path / "e.las", np.zeros((0, 3)), offset=(0, 0, 0))
    fails(tmp_path / "e.las", "holds no points")


def test_missing_library_says_what_to_install(tmp_path, monkeypatch):
    p, _ = sphere(100)
    path = write_las(tmp_path / "a.las", p)
    monkeypatch.setitem(sys.modules, "laspy", None)  # as if it were not installed
    with pytest.raises(PointCloudFileError, match=r"needs the Python package 'laspy'.*pip install laspy"):
        read_point_cloud(path)


# ---- E57 -------------------------------------------------------------------------------------


def test_e57_two_scans_with_poses(tmp_path):
    a, _ = sphere(2000, seed=5, radius=3.0)
    b, _ = sphere(1500, seed=6, radius=3.0)
    t1, t2 = MAP + [0, 0, 1.5], MAP + [10.0, -4.0, 1.5]
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90 degrees about z
    rgb = np.tile(np.array([[200, 10, 20]], np.uint8), (2000, 1))
    path = write_e57(tmp_path / "two.e57", [
        {"xyz": a, "translation": t1, "rgb": rgb, "intensity": np.linspace(0, 1, 2000)},
        {"xyz": b, "translation": t2, "rotation": q, "rgb": rgb[:1500], "intensity": np.linspace(0, 1, 1500)},
    ])
    c = read_point_cloud(path)
    assert c.scans == 2 and len(c.points) == 3500 and c.format == "E57"
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    want = np.concatenate([a + t1, b @ rot.T + t2])
    assert np.abs(c.absolute_points() - want).max() < 1e-6
    np.testing.assert_allclose(c.viewpoints + c.offset, [t1, t2], atol=1e-9)
    np.testing.assert_array_equal(c.colors[0], [200, 10, 20])
    assert c.intensity is not None and c.intensity.shape == (3500,)
    assert "2 scans" in c.describe() and "2 scanner positions" in c.describe()


def test_e57_invalid_points_are_skipped(tmp_path):
    a, _ = sphere(1000, seed=7)
    invalid = np.zeros(1000, bool)
    invalid[::10] = True
    c = read_point_cloud(write_e57(tmp_path / "v.e57", [{"xyz": a, "invalid": invalid}]))
    assert len(c.points) == 900 and c.skipped == 0  # invalid means no return: not a point, not an error
    np.testing.assert_allclose(c.points, a[~invalid])


def test_bad_e57(tmp_path):
    write_e57(tmp_path / "none.e57", [])
    fails(tmp_path / "none.e57", "holds no 3D scans")
    a, _ = sphere(5000, seed=8)
    data = write_e57(tmp_path / "a.e57", [{"xyz": a}]).read_bytes()
    (tmp_path / "t.e57").write_bytes(data[: len(data) // 2])
    fails(tmp_path / "t.e57", "not a readable E57 file")
    (tmp_path / "x.e57").write_bytes(b"not an e57 file at all" * 100)
    fails(tmp_path / "x.e57", "not a readable E57 file")


# ---- text ------------------------------------------------------------------------------------


def rows(*cols, fmt="%.9g", sep=" "):
    block = np.column_stack(cols)
    return "\n".join(sep.join(fmt % v for v in r) for r in block) + "\n"


def test_xyz_plain_and_with_normals(tmp_path):
    p, n = sphere(300, seed=9)
    (tmp_path / "a.xyz").write_text(rows(p))
    c = read_point_cloud(tmp_path / "a.xyz")
    np.testing.assert_allclose(c.points, p, atol=1e-8)
    assert c.normals is None and c.colors is None and c.format == "XYZ text"
    (tmp_path / "n.xyz").write_text(rows(p, n))
    c = read_point_cloud(tmp_path / "n.xyz")
    np.testing.assert_allclose(c.normals, n, atol=1e-8)
    assert c.colors is None


def test_pts_with_count_line_intensity_and_colours(tmp_path):
    p, _ = sphere(200, seed=10)
    rgb = np.random.default_rng(2).integers(0, 256, size=(200, 3))
    inten = np.random.default_rng(3).integers(-2048, 2048, size=200)
    (tmp_path / "s.pts").write_text("200\n" + rows(p, inten, rgb))
    c = read_point_cloud(tmp_path / "s.pts")
    np.testing.assert_array_equal(c.colors, rgb)
    np.testing.assert_array_equal(c.intensity, inten)
    (tmp_path / "bad.pts").write_text("250\n" + rows(p, inten, rgb))
    fails(tmp_path / "bad.pts", "first line says 250 points, the file holds 200 rows")


def test_csv_with_cloudcompare_header_and_semicolons(tmp_path):
    p, n = sphere(150, seed=11)
    rgb = np.random.default_rng(4).integers(0, 256, size=(150, 3))
    big = p + MAP
    (tmp_path / "cc.csv").write_text("//X,Y,Z,R,G,B,Nx,Ny,Nz\n" + rows(big, rgb, n, fmt="%.10f", sep=","))
    c = read_point_cloud(tmp_path / "cc.csv")
    assert np.abs(c.absolute_points() - big).max() < 1e-6 and np.any(c.offset)
    np.testing.assert_array_equal(c.colors, rgb)
    np.testing.assert_allclose(c.normals, n, atol=1e-9)
    (tmp_path / "semi.txt").write_text("# exported\nx;y;z;normal_x;normal_y;normal_z\n" + rows(p, n, sep=";"))
    c = read_point_cloud(tmp_path / "semi.txt")
    np.testing.assert_allclose(c.normals, n, atol=1e-8)
    assert c.format == "TXT text"


def test_text_colours_0_to_1_and_guessed_order(tmp_path):
    p, n = sphere(100, seed=12)
    rgb = np.random.default_rng(5).random((100, 3))
    (tmp_path / "c.xyz").write_text(rows(n * 0 + p, rgb, n))  # x y z r g b nx ny nz, no header
    c = read_point_cloud(tmp_path / "c.xyz")
    np.testing.assert_array_equal(c.colors, np.rint(rgb * 255).astype(np.uint8))
    np.testing.assert_allclose(c.normals, n, atol=1e-8)
    (tmp_path / "d.xyz").write_text(rows(p, n, rgb * 255 // 1))  # x y z nx ny nz r g b
    c = read_point_cloud(tmp_path / "d.xyz")
    np.testing.assert_allclose(c.normals, n, atol=1e-8)
    np.testing.assert_array_equal(c.colors, rgb * 255 // 1)


def test_text_columns_given(tmp_path):
    p, _ = sphere(50, seed=13)
    other = np.arange(50.0)
    (tmp_path / "g.txt").write_text(rows(other, p, other))
    fails(tmp_path / "g.txt", "cannot tell what its 5 columns are")
    c = read_point_cloud(tmp_path / "g.txt", columns="_ x y z classification")
    np.testing.assert_allclose(c.points, p, atol=1e-8)
    np.testing.assert_array_equal(c.classification, other.astype(np.uint8))
    c = read_point_cloud(tmp_path / "g.txt", columns="_ x y z classification", classes=[3, 4])
    assert len(c.points) == 2


def test_text_nan_rows_are_skipped_and_counted(tmp_path):
    p, _ = sphere(100, seed=14)
    p[[3, 50]] = np.nan
    (tmp_path / "n.xyz").write_text(rows(p))
    c = read_point_cloud(tmp_path / "n.xyz")
    assert len(c.points) == 98 and c.skipped == 2 and "2 rows with NaN" in c.describe()
    (tmp_path / "all.xyz").write_text("nan nan nan\nnan 1 2\n")
    fails(tmp_path / "all.xyz", "every point has NaN")


def test_bad_text_files(tmp_path):
    p, _ = sphere(40, seed=15)
    good = rows(p).splitlines()
    (tmp_path / "mid.xyz").write_text("\n".join(good[:20] + ["oops, a text line"] + good[20:]) + "\n")
    fails(tmp_path / "mid.xyz", "line 21 is not a row of numbers: 'oops, a text line'")
    (tmp_path / "var.xyz").write_text("\n".join(good[:10] + [good[10] + " 7"] + good[11:]) + "\n")
    fails(tmp_path / "var.xyz", "line 11 has 4 columns, the lines before have 3")
    (tmp_path / "empty.xyz").write_text("")
    fails(tmp_path / "empty.xyz", "holds no points")
    (tmp_path / "hdr.xyz").write_text("x y z\n")
    fails(tmp_path / "hdr.xyz", "holds no points")
    (tmp_path / "two.xyz").write_text("1 2\n3 4\n")
    fails(tmp_path / "two.xyz", "has 2 columns")
    (tmp_path / "bin.xyz").write_bytes(bytes(range(256)) * 4)
    fails(tmp_path / "bin.xyz", "not a text point cloud|no rows of numbers")
    (tmp_path / "h.csv").write_text("x,y,z,nx\n1,2,3\n")
    fails(tmp_path / "h.csv", "the header line names 4 columns, line 2 has 3")


def test_text_read_in_chunks_gives_the_same(tmp_path):
    from nkf_model.io.text import read_text

    p, n = sphere(1000, seed=16)
    (tmp_path / "k.xyz").write_text(rows(p + MAP, n, fmt="%.10f"))
    whole = read_text(tmp_path / "k.xyz")
    chunked = read_text(tmp_path / "k.xyz", chunk_lines=37)
    np.testing.assert_array_equal(whole.absolute_points(), chunked.absolute_points())
    np.testing.assert_array_equal(whole.normals, chunked.normals)
    good = rows(p).splitlines()
    (tmp_path / "late.xyz").write_text("\n".join(good[:900] + ["1 2"] + good[900:]) + "\n")
    with pytest.raises(PointCloudFileError, match="line 901 has 2 columns"):
        read_text(tmp_path / "late.xyz", chunk_lines=100)


# ---- PCD -------------------------------------------------------------------------------------


@pytest.mark.parametrize("compiled", [False, True])
def test_lzf_round_trip_and_overlapping_references(compiled):
    # A literal run "ab" then a reference of length 6 at distance 2: "abababab".
    assert lzf_decompress(bytes([1, ord("a"), ord("b"), (4 << 5) | 0, 1]), 8, compiled) == b"abababab"
    rng = np.random.default_rng(0)
    data = np.repeat(rng.integers(0, 5, 3000).astype(np.uint8), 3).tobytes() + bytes(1000) + rng.bytes(500)
    comp = lzf_compress(data)
    assert len(comp) < 0.8 * len(data)  # back references were used
    assert lzf_decompress(comp, len(data), compiled) == data
    with pytest.raises(ValueError):
        lzf_decompress(comp[:-5], len(data), compiled)
    with pytest.raises(ValueError, match="reference out of range"):
        lzf_decompress(bytes([(1 << 5) | 0, 5]), 3, compiled)  # refers before the start


@pytest.mark.parametrize("kind", ["ascii", "binary", "binary_compressed"])
def test_pcd_kinds(tmp_path, kind):
    p, n = sphere(400, seed=17)
    rgb = np.random.default_rng(6).integers(0, 256, size=(400, 3))
    fields = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "rgb": pack_rgb(rgb),
              "normal_x": n[:, 0], "normal_y": n[:, 1], "normal_z": n[:, 2], "curvature": np.zeros(400),
              "intensity": np.arange(400.0), "label": np.arange(400) % 7}
    path = tmp_path / f"c_{kind}.pcd"
    path.write_bytes(pcd_bytes(fields, kind, types={"label": "<u4"}))
    c = read_point_cloud(path)
    assert c.format == f"PCD ({kind})" and len(c.points) == 400
    np.testing.assert_allclose(c.points, p.astype(np.float32), atol=1e-6)
    np.testing.assert_allclose(c.normals, n.astype(np.float32), atol=1e-6)
    np.testing.assert_array_equal(c.colors, rgb)
    np.testing.assert_array_equal(c.intensity, np.arange(400.0))
    np.testing.assert_array_equal(c.classification, np.arange(400) % 7)
    assert c.viewpoints is None


def test_pcd_organised_with_nans_and_a_viewpoint(tmp_path):
    p, _ = sphere(60, seed=18)
    p[::6] = np.nan  # organised clouds mark missing returns with NaN
    path = tmp_path / "o.pcd"
    path.write_bytes(pcd_bytes({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}, "binary", width=10, height=6,
                               viewpoint="1 2 3 1 0 0 0"))
    c = read_point_cloud(path)
    assert len(c.points) == 50 and c.skipped == 10
    np.testing.assert_array_equal(c.viewpoints, [[1, 2, 3]])


def test_bad_pcd(tmp_path):
    p, _ = sphere(100, seed=19)
    xyz = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}
    good = pcd_bytes(xyz, "binary")
    (tmp_path / "half.pcd").write_bytes(good[:-200])
    fails(tmp_path / "half.pcd", "truncated: its header says 100 points")
    (tmp_path / "f2.pcd").write_bytes(good.replace(b"SIZE 4 4 4", b"SIZE 2 4 4"))
    fails(tmp_path / "f2.pcd", "unsupported PCD field layout: field 'x' TYPE F SIZE 2")
    (tmp_path / "cnt.pcd").write_bytes(good.replace(b"COUNT 1 1 1", b"COUNT 3 1 1"))
    fails(tmp_path / "cnt.pcd", "unsupported PCD field layout: field 'x' has COUNT 3")
    (tmp_path / "kind.pcd").write_bytes(good.replace(b"DATA binary", b"DATA binary_lz4"))
    fails(tmp_path / "kind.pcd", "unsupported PCD DATA kind 'binary_lz4'")
    (tmp_path / "noxyz.pcd").write_bytes(good.replace(b"FIELDS x y z", b"FIELDS a b c"))
    fails(tmp_path / "noxyz.pcd", "has no x/y/z fields")
    comp = bytearray(pcd_bytes(xyz, "binary_compressed"))
    comp[-40:] = bytes(40 * [0xFF])
    (tmp_path / "bad_lzf.pcd").write_bytes(bytes(comp))
    fails(tmp_path / "bad_lzf.pcd", "corrupt compressed data")
    text = pcd_bytes(xyz, "ascii").decode().splitlines()
    text[15] = "1.0 2.0"
    (tmp_path / "cols.pcd").write_text("\n".join(text) + "\n")
    fails(tmp_path / "cols.pcd", "line 16 has 2 values, the header's fields need 3")
    (tmp_path / "junk.pcd").write_bytes(b"\x00\xff" * 100)
    fails(tmp_path / "junk.pcd", "not a PCD file")


# ---- PLY variants and dispatch ---------------------------------------------------------------


@pytest.mark.parametrize("names", [("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z")])
def test_ply_normal_aliases(tmp_path, names):
    p, n = sphere(30, seed=20)
    props = "".join(f"property float {k}\n" for k in ("x", "y", "z", *names))
    props += "property float scalar_Intensity\nproperty ushort red\nproperty ushort green\nproperty ushort blue\n"
    body = "".join(" ".join(f"{v:.7g}" for v in (*a, *b)) + " 5 65535 0 257\n" for a, b in zip(p, n))
    path = tmp_path / "a.ply"
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex 30\n{props}end_header\n{body}")
    c = read_point_cloud(path)
    np.testing.assert_allclose(c.normals, n, atol=1e-6)
    np.testing.assert_array_equal(c.intensity, np.full(30, 5.0))
    np.testing.assert_array_equal(c.colors[0], [255, 0, 1])  # 16-bit colours scaled


def test_unknown_extension(tmp_path):
    (tmp_path / "a.obj").write_text("v 0 0 0\n")
    msg = fails(tmp_path / "a.obj", "unsupported point-cloud format '.obj'")
    for ext in (".las", ".laz", ".e57", ".xyz", ".pts", ".pcd", ".ply"):
        assert ext in msg


@pytest.mark.parametrize("kind", ["ascii", "binary", "binary_compressed"])
def test_pcd_read_in_chunks_gives_the_same(tmp_path, kind):
    from nkf_model.io.pcd import read_pcd

    p, n = sphere(500, seed=21)
    p[7] = np.nan
    fields = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "normal_x": n[:, 0], "normal_y": n[:, 1], "normal_z": n[:, 2]}
    path = tmp_path / "k.pcd"
    path.write_bytes(pcd_bytes(fields, kind))
    whole, chunked = read_pcd(path), read_pcd(path, chunk_size=37)
    assert len(chunked.points) == 499 and chunked.skipped == 1
    np.testing.assert_array_equal(whole.points, chunked.points)
    np.testing.assert_array_equal(whole.normals, chunked.normals)


def test_csv_with_quoted_header_names(tmp_path):
    p, _ = sphere(20, seed=22)
    (tmp_path / "q.csv").write_text('"X","Y","Z","Intensity"\n' + rows(p, np.arange(20.0), sep=","))
    c = read_point_cloud(tmp_path / "q.csv")
    np.testing.assert_allclose(c.points, p, atol=1e-8)
    np.testing.assert_array_equal(c.intensity, np.arange(20.0))


def test_text_with_bom_and_windows_line_ends(tmp_path):
    p, n = sphere(20, seed=23)
    text = "\ufeffx,y,z,nx,ny,nz\r\n" + rows(p, n, sep=",").replace("\n", "\r\n")
    (tmp_path / "w.csv").write_bytes(text.encode("utf-8"))
    c = read_point_cloud(tmp_path / "w.csv")
    np.testing.assert_allclose(c.normals, n, atol=1e-8)


def test_e57_colours_only_when_every_scan_has_them(tmp_path):
    a, _ = sphere(300, seed=24)
    rgb = np.full((150, 3), 7, np.uint8)
    c = read_point_cloud(write_e57(tmp_path / "m.e57", [{"xyz": a[:150], "rgb": rgb}, {"xyz": a[150:]}]))
    assert len(c.points) == 300 and c.colors is None and c.scans == 2
