"""Bad input through the Python API: each case a clear ValueError subclass, never a crash."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from shapes import sphere_points

import nkf_model
from nkf_model import errors
from nkf_model.points.clean import clean_points


def test_errors_are_value_errors():
    for cls in (errors.InvalidParameterError, errors.TooFewPointsError, errors.DegenerateInputError,
                errors.MissingNormalsError, errors.PointCloudFileError, errors.OutputPathError):
        assert issubclass(cls, ValueError)
    assert not issubclass(nkf_model.Cancelled, ValueError)


def test_missing_normals():
    p, _ = sphere_points(50)
    with pytest.raises(errors.MissingNormalsError, match="normals are required"):
        nkf_model.reconstruct(p, None, normals_mode="given")


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_nonfinite_rows_are_dropped_with_a_count(bad):
    p, n = sphere_points(300, seed=1)
    p, n = p.copy(), n.copy()
    p[:5, 0] = float(bad)
    n[5:12, 1] = float(bad)
    n[12:15] = 0.0
    with pytest.warns(nkf_model.InputWarning) as rec:
        m = nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    text = " | ".join(str(w.message) for w in rec)
    assert "dropped 5 points with NaN or infinite coordinates" in text
    assert "dropped 10 points with NaN, infinite or zero-length normals" in text
    assert m.stats["points_used"] == 285
    assert np.isfinite(m.vertices).all()


def test_too_few_remain_after_dropping():
    p, n = sphere_points(30)
    p[:25] = np.nan
    with pytest.raises(errors.TooFewPointsError, match="5 usable points of 30"):
        nkf_model.reconstruct(p, n)


def test_fewer_than_ten_points():
    p, n = sphere_points(9)
    with pytest.raises(errors.TooFewPointsError, match="at least 10"):
        nkf_model.reconstruct(p, n)


def test_all_points_identical():
    p = np.ones((50, 3))
    n = np.tile([0.0, 0.0, 1.0], (50, 1))
    with pytest.raises(errors.TooFewPointsError):  # duplicates are dropped first: one point remains
        nkf_model.reconstruct(p, n)
    # Not exact duplicates but identical to float precision relative to their size.
    p2 = 1e6 + np.random.default_rng(0).normal(scale=1e-9, size=(50, 3))
    with pytest.raises(errors.DegenerateInputError, match="identical"):
        clean_points(p2, n)


def test_points_on_a_line():
    t = np.linspace(0, 1, 50)
    p = np.stack([t, 2 * t, -t], axis=1)
    n = np.tile([0.0, 0.0, 1.0], (50, 1))
    with pytest.raises(errors.DegenerateInputError, match="line"):
        nkf_model.reconstruct(p, n)


def test_points_on_a_plane():
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(size=(100, 2)), np.full(100, 3.0)]
    n = np.tile([0.0, 0.0, 1.0], (100, 1))
    with pytest.raises(errors.DegenerateInputError, match="plane"):
        nkf_model.reconstruct(p, n)


def test_duplicate_points_are_dropped():
    p, n = sphere_points(200, seed=2)
    p2 = np.concatenate([p, p[:40]])
    n2 = np.concatenate([n, n[:40]])
    with pytest.warns(nkf_model.InputWarning, match="dropped 40 points that duplicate another point"):
        m = nkf_model.reconstruct(p2, n2, resolution=32, device="cpu")
    assert m.stats["points_used"] == 200


def test_coordinates_around_a_million():
    p, n = sphere_points(300, radius=2.0, center=(1e6, 1e6, -1e6), seed=3)
    m = nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    r = np.linalg.norm(m.local_vertices.astype(np.float64) + (m.center - np.array([1e6, 1e6, -1e6])), axis=1)
    assert np.abs(r - 2.0).max() < 0.1


@pytest.mark.parametrize("kw,match", [
    (dict(resolution=8), "resolution must be between 16 and 1024"),
    (dict(resolution=5000), "resolution must be between"),
    (dict(resolution=64.5), "resolution must be an integer"),
    (dict(lam=-1.0), "lambda must be a finite number >= 0"),
    (dict(lam=float("nan")), "lambda"),
    (dict(lam="big"), "lambda must be a number"),
    (dict(method="poisson"), "method must be one of"),
    (dict(device="tpu"), "device must be"),
    (dict(eps=0.5), "eps"),
])
def test_bad_settings(kw, match):
    p, n = sphere_points(50)
    with pytest.raises(errors.InvalidParameterError, match=match):
        nkf_model.reconstruct(p, n, **kw)


@pytest.mark.parametrize("points,normals,match", [
    (np.zeros((10, 2)), np.zeros((10, 2)), r"shape \(N, 3\)"),
    (np.zeros((10, 3)), np.zeros((9, 3)), "differ in length"),
    (np.array([["a", "b", "c"]] * 10), np.zeros((10, 3)), "numeric"),
])
def test_bad_arrays(points, normals, match):
    with pytest.raises(errors.InvalidPointCloudError, match=match):
        nkf_model.reconstruct(points, normals)


def test_cuda_requested_without_a_gpu():
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    p, n = sphere_points(50)
    with pytest.raises(errors.MethodUnavailableError, match="no CUDA device"):
        nkf_model.reconstruct(p, n, device="cuda")


def test_inward_normals_still_give_a_surface_or_a_clear_error():
    """Flipped normals describe the complement; the result must still be a valid mesh or a clear
    NoSurfaceError, never a crash."""
    p, n = sphere_points(300, seed=7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            m = nkf_model.reconstruct(p, -n, resolution=32, device="cpu")
        except errors.NoSurfaceError:
            return
    assert len(m.faces) > 0
