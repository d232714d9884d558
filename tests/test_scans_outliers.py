"""Real-scan robustness (issue 19): outlier points, floating pieces, dense normals, the range-scan simulator."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import nkf_model
from nkf_model.options import Options
from nkf_model.points.outliers import OUTLIER_MIN_POINTS, sparse_outliers
from nkf_model.surface.trim import clean_scan_mesh, piece_labels


def _sphere(n, rng, radius=0.4):
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return radius * p


def test_sparse_outliers_finds_spray_and_keeps_the_surface():
    rng = np.random.default_rng(0)
    surface = _sphere(30_000, rng)
    spray = rng.uniform(-0.6, 0.6, size=(300, 3))
    spray = spray[np.abs(np.linalg.norm(spray, axis=1) - 0.4) > 0.05]  # off the surface
    bad = sparse_outliers(np.concatenate([surface, spray]))
    assert bad[len(surface):].mean() > 0.95
    assert bad[: len(surface)].mean() < 0.002


def test_sparse_outliers_small_inputs_have_none():
    assert not sparse_outliers(np.random.default_rng(1).normal(size=(5, 3))).any()


def _two_pieces():
    # A big square (2 triangles, area 1) and a tiny one (area 1e-4), apart.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [3, 0, 0], [3.01, 0, 0], [3.01, 0.01, 0], [3, 0.01, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return v, f


def test_floaters_below_min_area_are_removed_and_the_largest_always_stays():
    v, f = _two_pieces()
    pts = v.copy()
    faces, kept, info = clean_scan_mesh(v, f, pts, 0.01, min_area=0.01)
    assert len(faces) == 2 and info.floaters_removed == 1 and info.small_piece_faces == 2
    assert piece_labels(len(kept), faces)[0] == 1
    faces, _, info = clean_scan_mesh(v, f, pts, 0.01, min_area=10.0)  # everything small: keep the largest
    assert len(faces) == 2 and info.floaters_removed == 1
    faces, _, info = clean_scan_mesh(v, f, pts, 0.01)
    assert len(faces) == 4 and info.floaters_removed == 0


def test_floaters_keep_pieces_above_their_share_of_the_area():
    # The tiny square is 1e-4 of the whole area: a share limit below that keeps it, one above drops it.
    v, f = _two_pieces()
    faces, _, info = clean_scan_mesh(v, f, v.copy(), 0.01, min_area=0.01, max_share=5e-5)
    assert len(faces) == 4 and info.floaters_removed == 0
    faces, _, info = clean_scan_mesh(v, f, v.copy(), 0.01, min_area=0.01, max_share=5e-3)
    assert len(faces) == 2 and info.floaters_removed == 1


def test_reconstruct_drops_outliers_and_floaters_from_dense_scans():
    rng = np.random.default_rng(2)
    surface = _sphere(OUTLIER_MIN_POINTS + 5_000, rng)
    normals = surface / np.linalg.norm(surface, axis=1, keepdims=True)
    # A small dense blob of stray returns outside the sphere (not sparse: it stays, and its tiny closed
    # surface must go as a floater), and uniform spray.
    blob = _sphere(150, rng, radius=0.02)
    spray = rng.uniform(-0.7, 0.7, size=(400, 3))
    spray = spray[np.abs(np.linalg.norm(spray, axis=1) - 0.4) > 0.05]
    junk = rng.normal(size=spray.shape)  # stray returns get arbitrary normals
    pts = np.concatenate([surface, blob + np.array([0.6, 0.0, 0.0]), spray])
    nrm = np.concatenate([normals, blob / 0.02, junk / np.linalg.norm(junk, axis=1, keepdims=True)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clean = nkf_model.reconstruct(pts, nrm, method="splines", resolution=64)
        kept = nkf_model.reconstruct(pts, nrm, method="splines", resolution=64, outliers=False)
    assert clean.stats["outliers"]["removed"] >= 0.9 * len(spray)
    assert clean.stats["trim"]["floaters_removed"] >= 1  # the blob
    assert kept.stats["outliers"] is None
    assert piece_labels(len(clean.vertices), clean.faces)[0] == 1
    r = np.linalg.norm(clean.vertices, axis=1)
    assert np.abs(r - 0.4).max() < 0.03
    # With the outliers kept, stray surface appears away from the sphere.
    r_kept = np.linalg.norm(kept.vertices, axis=1)
    assert np.abs(r_kept - 0.4).max() > 0.05


def test_outliers_setting_and_cli_flag():
    assert Options().outliers is True
    from nkf_model.cli import _parser as build_parser
    from nkf_model.cli import options_from_args

    args = build_parser().parse_args(["reconstruct", "in.ply", "out.ply", "--keep-outliers"])
    assert options_from_args(args).outliers is False
    args = build_parser().parse_args(["reconstruct", "in.ply", "out.ply"])
    assert options_from_args(args).outliers is True


def test_range_scan_simulator_occludes_misregisters_and_flags_outliers():
    pytest.importorskip("numba")
    from benchmarks.range_scans import range_scan

    # A closed box: six faces, 12 triangles, wound outwards.
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    exact = range_scan(v, f, views=6, pixels=64, noise=0.0, edge_outliers=0.0, spray=0.0, misregistration=0.0)
    on = ~exact.outlier
    # Without noise or misregistration every point lies on the box; nothing is seen from below.
    assert np.abs(np.abs(exact.points[on]).max(axis=1) - 0.5).max() < 1e-9
    assert (exact.points[:, 2] > -0.5 + 1e-9).any() and not np.any(np.isclose(exact.points[:, 2], -0.5)
                                                                      & (np.abs(exact.points[:, :2]) < 0.49).all(1))
    assert set(np.unique(exact.scan)) == set(range(6))
    noisy = range_scan(v, f, views=6, pixels=64, noise=0.0, edge_outliers=0.5, spray=0.01, misregistration=0.002)
    assert noisy.outlier.sum() > 0
    off = np.abs(np.abs(noisy.points[~noisy.outlier]).max(axis=1) - 0.5)
    first = noisy.scan[~noisy.outlier] == 0
    assert off[first].max() < 1e-9  # scan 0 stays registered
    assert off[~first].max() > 1e-4  # the others moved
    assert off[~first].max() < 0.002 * noisy.diagonal + 1e-9
