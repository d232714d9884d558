"""Noise estimation and noise-aware regularisation of the partition-of-unity solves."""

from __future__ import annotations

import numpy as np
import pytest

import nkf_model
from nkf_model.fit.augment import augment, default_eps
from nkf_model.fit.partition_of_unity import fit_pou
from nkf_model.kernel.engines import cpu_engine
from nkf_model.kernel.neural_spline import homogeneous
from nkf_model.normals.estimate import median_spacing
from nkf_model.points.noise import NOISE_LAM_PER_RATIO, estimate_noise, noise_lam


def _sphere(n, noise, seed=0):
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return 0.5 * nrm + rng.normal(scale=noise, size=(n, 3)), nrm


def _cube_faces(n, noise, seed=0):
    """Points on the six faces of a cube of side 1 (flat parts and sharp edges), with normals."""
    rng = np.random.default_rng(seed)
    axis = rng.integers(0, 3, n)
    side = rng.choice([-0.5, 0.5], n)
    p = rng.uniform(-0.5, 0.5, size=(n, 3))
    p[np.arange(n), axis] = side
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = np.sign(side)
    return p + rng.normal(scale=noise, size=(n, 3)), nrm


@pytest.mark.parametrize("shape", [_sphere, _cube_faces])
def test_noise_estimate_tracks_the_noise(shape):
    clean = estimate_noise(*shape(10_000, 0.0))
    noisy = [estimate_noise(*shape(10_000, s)) for s in (0.0025, 0.005)]
    assert clean < 0.001  # curvature alone (radius 0.5 at 10,000 points)
    assert 0.6 * 0.0025 < noisy[0] < 1.1 * 0.0025
    assert 0.6 * 0.005 < noisy[1] < 1.1 * 0.005


def test_opposite_sheets_do_not_read_as_noise():
    # Two parallel planes 0.004 apart with opposite normals: a thin plate, not noise.
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.5, 0.5, size=(6000, 3))
    p[:, 2] = np.where(np.arange(6000) % 2 == 0, 0.002, -0.002)
    nrm = np.zeros((6000, 3))
    nrm[:, 2] = np.sign(p[:, 2])
    assert estimate_noise(p, nrm) < 1e-9


def test_noise_lam_never_lowers_lambda():
    assert noise_lam(0.0, 0.01, 1e-10) == 1e-10
    assert noise_lam(0.005, 0.01, 1e-10) == pytest.approx(NOISE_LAM_PER_RATIO * 0.25)
    assert noise_lam(0.005, 0.01, 1.0) == 1.0
    assert noise_lam(0.005, 0.0, 1e-10) == 1e-10  # no spacing (all points at one place): no floor


def test_noise_lam_depends_on_noise_relative_to_spacing():
    # The same cloud in other units, or the same noise at 4 times the density (half the spacing)
    assert noise_lam(0.05, 0.1, 0.0) == pytest.approx(noise_lam(0.005, 0.01, 0.0))
    assert noise_lam(0.005, 0.005, 0.0) == pytest.approx(4 * noise_lam(0.005, 0.01, 0.0))


def test_larger_patch_lambda_smooths_a_noisy_sphere():
    p, n = _sphere(6000, 0.005, seed=2)
    xa, y = augment(p, n, default_eps(len(p)))
    a = homogeneous(xa)
    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.linspace(0.44, 0.56, 121)

    def radial_error(lam_patch):
        f, info = fit_pou(p, a, y, 1e-10, cpu_engine(), patch_lam=lam_patch)
        assert info.patch_lam == lam_patch
        vals = f((radii[None, :, None] * d[:, None, :]).reshape(-1, 3)).reshape(len(d), len(radii))
        first = np.argmax(vals > 0, axis=1)  # the zero crossing along each ray
        return float(np.sqrt(np.mean((radii[first] - 0.5) ** 2)))

    assert radial_error(noise_lam(estimate_noise(p, n), median_spacing(p), 1e-10)) < 0.7 * radial_error(1e-10)


def test_reconstruct_reports_the_local_regularisation():
    p, n = _sphere(8000, 0.005, seed=4)
    m = nkf_model.reconstruct(p, n, resolution=64)
    assert m.stats["solver"] == "pou"
    assert m.stats["pou"]["patch_lam"] > 1e-5
    p, n = _cube_faces(8000, 0.0, seed=4)
    assert nkf_model.reconstruct(p, n, resolution=64).stats["pou"]["patch_lam"] < 1e-6


def test_the_learned_kernel_scales_the_local_regularisation_to_its_magnitude(tmp_path):
    from nkf_helpers import tiny_weights

    from nkf_model.pipeline.reconstruct import NKF_NOISE_LAM_FACTOR

    p, n = _sphere(8000, 0.005, seed=4)
    splines = nkf_model.reconstruct(p, n, method="splines", resolution=48).stats["pou"]["patch_lam"]
    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    m = nkf_model.reconstruct(p, n, method="nkf", weights=w, resolution=48, device="cpu")
    assert m.stats["solver"] == "pou"
    # Same points, same noise estimate; the tiny network's features add little to |a|^2.
    ratio = m.stats["pou"]["patch_lam"] / splines
    assert NKF_NOISE_LAM_FACTOR <= ratio < 1.5 * NKF_NOISE_LAM_FACTOR
