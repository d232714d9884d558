"""method="nkf" in reconstruct() and on the command line."""

from __future__ import annotations

import numpy as np
import pytest
from nkf_helpers import tiny_weights
from shapes import sphere_points

import nkf_model
from nkf_model.cli import main
from nkf_model.errors import WeightsError
from nkf_model.io.files import read_mesh
from nkf_model.kernel.weights import has_default_weights
from nkf_model.options import DEFAULT_METHOD_REASON, SETTING, SHIPPED_WEIGHTS, gate_passed, weights_gate
from nkf_model.pipeline.reconstruct import DEFAULT_METHOD
from nkf_model.train.metrics import chamfer_l1, sample_surface


def _closed_and_outward(m):
    f = m.faces.astype(np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    v = m.vertices.astype(np.float64)
    volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    return bool(np.all(counts == 2)), volume


def test_zero_features_give_the_splines_mesh(tmp_path, sphere500):
    w = tiny_weights(tmp_path / "zero.safetensors", gate=0.0)
    p, n = sphere500
    a = nkf_model.reconstruct(p, n, method="splines", resolution=40, device="cpu")
    b = nkf_model.reconstruct(p, n, method="nkf", weights=w, resolution=40, device="cpu")
    assert a.faces.shape == b.faces.shape
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-5)
    assert b.stats["method"] == "nkf" and "features" in b.stats["timings"]


def test_nkf_reports_the_features_stage(tmp_path, sphere500):
    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    calls = []
    nkf_model.reconstruct(*sphere500, method="nkf", weights=w, resolution=32, device="cpu",
                          progress=lambda f, s: calls.append((f, s)))
    stages = [s for _, s in calls]
    assert "features" in stages and stages.index("augment") < stages.index("features") < stages.index("solve")
    fr = [f for f, _ in calls]
    assert fr == sorted(fr) and fr[-1] == 1.0


def test_large_input_uses_the_scalable_solver_with_features(tmp_path):
    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    p, n = sphere_points(1500, seed=3)
    m = nkf_model.reconstruct(p, n, method="nkf", weights=w, resolution=40, device="cpu", max_centres=1000)
    assert m.stats["solver"] == "pou"
    closed, volume = _closed_and_outward(m)
    assert closed and volume > 0
    m = nkf_model.reconstruct(p, n, method="nkf", weights=w, resolution=40, device="cpu", max_centres=1000,
                              solver="falkon")
    assert m.stats["solver"] == "falkon"
    closed, volume = _closed_and_outward(m)
    assert closed and volume > 0


def test_bad_weights_raise_a_clear_error(tmp_path, sphere500):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights at all")
    with pytest.raises(WeightsError, match="not a valid safetensors file"):
        nkf_model.reconstruct(*sphere500, method="nkf", weights=bad)
    with pytest.raises(WeightsError, match="does not exist"):
        nkf_model.reconstruct(*sphere500, method="nkf", weights=tmp_path / "missing.safetensors")


def test_default_method_follows_the_shipped_weights_gate():
    # nkf is the default only for shipped weights that passed the gate on held-out sources (issue 23).
    passed = has_default_weights() and gate_passed(weights_gate(SHIPPED_WEIGHTS))
    assert DEFAULT_METHOD == ("nkf" if passed else "splines")
    assert SETTING["method"].default == DEFAULT_METHOD
    assert DEFAULT_METHOD_REASON in SETTING["method"].description


@pytest.mark.skipif(not has_default_weights(), reason="this checkout ships no trained weights")
def test_shipped_weights_reconstruct_a_closed_sphere(sphere500):
    p, n = sphere500
    m = nkf_model.reconstruct(p, n, method="nkf", resolution=64, device="cpu")
    closed, volume = _closed_and_outward(m)
    assert closed and volume > 0
    assert abs(volume - 4 / 3 * np.pi) < 0.15 * 4 / 3 * np.pi
    s, _ = sample_surface(m.vertices, m.faces, 20000, np.random.default_rng(0))
    assert np.abs(np.linalg.norm(s, axis=1) - 1.0).mean() < 0.01
    ref = sphere_points(20000, seed=9)[0]
    assert chamfer_l1(s, ref) < 0.02


def _write_cloud(path, p, n):
    from plyfile import PlyData, PlyElement

    arr = np.zeros(len(p), dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate("xyz"):
        arr[k] = p[:, i]
        arr["n" + k] = n[:, i]
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))


def test_cli_weights(tmp_path, capsys, sphere500):
    src = tmp_path / "in.ply"
    _write_cloud(src, *sphere500)
    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    out = tmp_path / "out.ply"
    code = main(["reconstruct", str(src), str(out), "--method", "nkf", "--weights", str(w), "--resolution", "32",
                 "--quiet", "--device", "cpu"])
    assert code == 0 and out.exists()
    v, f = read_mesh(out)
    assert len(f) > 100
    capsys.readouterr()
    out2 = tmp_path / "out2.ply"
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x00" * 64)
    code = main(["reconstruct", str(src), str(out2), "--method", "nkf", "--weights", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out2.exists()
    assert len(err) == 1 and err[0].startswith("nkf: error:") and str(bad) in err[0]


@pytest.mark.parametrize("const", [False, True])
def test_feature_scale_multiplies_only_the_learned_features(tmp_path, const):
    from dataclasses import replace

    from nkf_helpers import TINY

    from nkf_model.fit.augment import augment
    from nkf_model.kernel.neural_spline import homogeneous, ns_kernel
    from nkf_model.kernel.weights import load_weights

    model = load_weights(tiny_weights(tmp_path / "w.safetensors", gate=0.3, config=replace(TINY, const_channel=const)))
    p, n = sphere_points(400, radius=0.4, seed=1)
    xa, y = augment(p, n, 0.01)
    full = model.prepare(xa, y)
    half = model.prepare(xa, y, feature_scale=0.5)
    none = model.prepare(xa, y, feature_scale=0.0)
    learned = slice(1 if const else 0, None)
    assert np.abs(full.phi(xa)[:, learned]).max() > 1e-3  # the features are not zero to begin with
    np.testing.assert_allclose(half.phi(xa)[:, learned], 0.5 * full.phi(xa)[:, learned], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(half.phi(xa)[:, :1 if const else 0], full.phi(xa)[:, :1 if const else 0])
    # Scale 0: the same kernel as zero learned features (the constant kept), in fewer numbers.
    zero = full.phi(xa).copy()
    zero[:, learned] = 0.0
    np.testing.assert_allclose(ns_kernel(none.a, none.a), ns_kernel(homogeneous(xa, zero), homogeneous(xa, zero)),
                               rtol=1e-10)
    assert none.a.shape[1] == (5 if const else 4)
    with pytest.raises(ValueError, match="feature_scale"):
        model.prepare(xa, y, feature_scale=1.5)


def test_dense_clean_input_fades_the_learned_features(tmp_path):
    # Above the training sizes (NKF_TRAINED_POINTS) the learned features are kept in proportion to the
    # estimated noise: clean dense input gets (almost) none, noisy dense input all, small input all.
    from nkf_helpers import box_mesh

    from nkf_model.pipeline.reconstruct import NKF_TRAINED_POINTS

    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    v, f = box_mesh()
    p, n = sample_surface(v, f, NKF_TRAINED_POINTS + 500, np.random.default_rng(4))
    clean = nkf_model.reconstruct(p, n, method="nkf", weights=w, resolution=32, device="cpu")
    assert clean.stats["feature_scale"] < 0.1
    noisy = p + np.random.default_rng(5).normal(scale=0.004, size=p.shape)  # 0.005 of the unit box
    m = nkf_model.reconstruct(noisy, n, method="nkf", weights=w, resolution=32, device="cpu")
    assert m.stats["feature_scale"] == 1.0
    small = nkf_model.reconstruct(p[:NKF_TRAINED_POINTS], n[:NKF_TRAINED_POINTS], method="nkf", weights=w,
                                  resolution=32, device="cpu")
    assert small.stats["feature_scale"] == 1.0
    assert nkf_model.reconstruct(p[:500], n[:500], method="splines", resolution=32).stats["feature_scale"] is None
