"""Open surfaces: trimming far from the samples and removing small pieces (issue 5)."""

from __future__ import annotations

import numpy as np
import pytest
from scan_shapes import hemisphere_points
from scipy.spatial import cKDTree
from shapes import sphere_points

import nkf_model
from nkf_model.errors import InvalidParameterError
from nkf_model.surface.trim import clean_scan_mesh, piece_labels, remove_small_pieces


@pytest.fixture(scope="module")
def hemisphere():
    return hemisphere_points(3000, seed=2)


def test_untrimmed_open_hemisphere_closes_far_from_the_samples(hemisphere):
    p, n = hemisphere
    m = nkf_model.reconstruct(p, n, resolution=48, device="cpu")
    d, _ = cKDTree(p).query(m.vertices)
    assert d.max() > 0.2  # the closed surface runs far below the data
    assert m.stats["far_field"] is True  # closed output: the sign far away follows the winding number


def test_trim_removes_surface_far_from_samples(hemisphere):
    p, n = hemisphere
    m = nkf_model.reconstruct(p, n, resolution=48, device="cpu", trim=4.0)
    st = m.stats["trim"]
    assert st["trimmed_faces"] > 0 and st["threshold"] > 0
    assert m.stats["far_field"] is False  # an open scan has no inside: no winding-number far field
    assert m.stats["solver"] == "dense" and m.stats["pou"] is None  # the size's own solver, nothing more
    d, _ = cKDTree(p).query(m.vertices)
    assert d.max() <= st["threshold"] + 1e-6
    assert m.vertices[:, 2].min() > -0.1  # nothing left below the open rim
    # ...and the hemisphere itself is kept: every sample is near the trimmed mesh.
    back, _ = cKDTree(m.vertices).query(p)
    assert np.quantile(back, 0.99) < 0.05
    assert np.abs(np.linalg.norm(m.vertices, axis=1) - 1).max() < 0.05


def test_min_piece_removes_small_disconnected_pieces():
    big, nb = sphere_points(1500, seed=1)
    small, ns = sphere_points(200, radius=0.1, center=(2.0, 0.0, 0.0), seed=2)
    p, n = np.r_[big, small], np.r_[nb, ns]
    whole = nkf_model.reconstruct(p, n, resolution=64, device="cpu")
    assert piece_labels(len(whole.vertices), whole.faces.astype(np.int64))[0] == 2
    m = nkf_model.reconstruct(p, n, resolution=64, device="cpu", min_piece=0.01)
    assert m.stats["trim"]["pieces_removed"] == 1
    assert np.linalg.norm(m.vertices, axis=1).max() < 1.1  # only the big sphere is left


def test_clean_scan_mesh_by_hand():
    # Two triangles near the points, one far away.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]], float)
    f = np.array([[0, 1, 2], [1, 3, 2], [4, 5, 6]])
    pts = v[:4] + 0.01
    faces, kept, info = clean_scan_mesh(v, f, pts, spacing=0.1, trim=3.0)
    assert info.trimmed_faces == 1 and len(faces) == 2 and set(kept) == {0, 1, 2, 3}
    keep, count, removed = remove_small_pieces(v, f, 0.1)
    assert count == 2 and removed == 0  # the far triangle has 1/3 of the area
    keep, count, removed = remove_small_pieces(v, f, 0.4)
    assert removed == 1 and keep.tolist() == [True, True, False]


@pytest.mark.parametrize("kw", [dict(trim=0), dict(trim=-1.0), dict(trim="far"), dict(min_piece=1.0),
                                dict(min_piece=-0.1)])
def test_bad_clean_up_settings(kw):
    p, n = sphere_points(100)
    with pytest.raises(InvalidParameterError):
        nkf_model.reconstruct(p, n, **kw)


def test_flat_scan_is_accepted_when_trimming():
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-1, 1, size=(2000, 2)), np.zeros(2000)]
    n = np.tile([0.0, 0.0, 1.0], (2000, 1))
    with pytest.raises(nkf_model.DegenerateInputError):
        nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    m = nkf_model.reconstruct(p, n, resolution=32, device="cpu", trim=3.0)
    assert np.abs(m.vertices[:, 2]).max() < 0.05
