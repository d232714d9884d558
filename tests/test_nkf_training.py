"""Training the learned kernel: data, loss, a few optimisation steps, checkpoints and the CLI."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from nkf_helpers import TINY, box_mesh, icosphere

from nkf_model.kernel.feature_net import FeatureNet
from nkf_model.train import metrics
from nkf_model.train.examples import AugmentSpec, CacheSpec, make_example, samples_from_mesh, validation_example
from nkf_model.train.kernel_training import (
    CHECKPOINT,
    FitSpec,
    example_field,
    example_loss,
    field_iou,
    load_config,
    read_checkpoint,
)

SMALL_CACHE = CacheSpec(n_surface=3000, n_volume=1024, n_near=1024)
SMALL_AUG = AugmentSpec(n_min=120, n_max=200, n_mode=150, n_volume=256, n_near=256, n_surface=128)


@pytest.fixture(scope="module")
def two_meshes():
    return [samples_from_mesh(*icosphere(2), SMALL_CACHE, 1), samples_from_mesh(*box_mesh(), SMALL_CACHE, 2)]


def test_cached_samples_are_consistent(two_meshes):
    s = two_meshes[0]
    r = np.linalg.norm(s["surf_pts"], axis=1)
    assert np.allclose(r, 0.45, atol=0.01)  # on the (faceted) sphere
    assert np.all(np.sum(s["surf_pts"] * s["surf_nrm"], axis=1) > 0)  # outward normals
    inside = np.linalg.norm(s["vol_pts"], axis=1) < 0.44
    outside = np.linalg.norm(s["vol_pts"], axis=1) > 0.46
    assert s["vol_occ"][inside].all() and not s["vol_occ"][outside].any()


def test_examples_are_in_the_unit_box_with_labels(two_meshes):
    rng = np.random.default_rng(0)
    for _ in range(6):
        ex = make_example(two_meshes[1], rng, SMALL_AUG)
        assert 120 <= len(ex.points) <= 200
        ext = ex.points.max(axis=0) - ex.points.min(axis=0)
        assert abs(ext.max() - 1.0) < 1e-9  # normalised like reconstruct() normalises its input
        assert np.allclose(np.linalg.norm(ex.normals, axis=1), 1.0)
        assert np.all(np.abs(ex.queries) <= 0.55 + 1e-12)
        assert set(np.unique(ex.occupancy)) <= {0.0, 1.0} and 0 < ex.occupancy.mean() < 1


def test_samples_without_a_normal_are_never_drawn(two_meshes):
    # A degenerate spot of a procedural shape once gave a zero normal; the example made from it had NaN
    # normals and the training run ended on an index error.
    s = dict(two_meshes[1])
    nrm = s["surf_nrm"].copy()
    nrm[::3] = 0.0
    nrm[1::7] = np.nan
    s["surf_nrm"] = nrm
    rng = np.random.default_rng(3)
    for _ in range(6):
        ex = make_example(s, rng, SMALL_AUG)
        assert np.all(np.isfinite(ex.points)) and np.all(np.isfinite(ex.normals))
        assert np.allclose(np.linalg.norm(ex.normals, axis=1), 1.0)


def test_half_surface_inputs_are_one_sided(two_meshes):
    ex = validation_example(two_meshes[0], 300, 0.0, True, seed=5)
    assert ex.half and len(ex.points) == 300
    # All input normals point into one hemisphere (the kept side of the sphere).
    d = ex.normals.mean(axis=0)
    assert np.all(ex.normals @ d > -0.05)


def test_zero_features_reproduce_neural_splines(two_meshes):
    net = FeatureNet(dataclasses.replace(TINY, point_weights=False))
    with torch.no_grad():
        net.gate.zero_()
    ex = validation_example(two_meshes[0], 200, 0.0, False, seed=1)
    with torch.no_grad():
        f_nkf = example_field(net, ex, 1e-10, ex.queries).numpy()
        f_ns = example_field(net, ex, 1e-10, ex.queries, use_features=False).numpy()
    np.testing.assert_allclose(f_nkf, f_ns, rtol=1e-9, atol=1e-9)
    assert field_iou(f_ns, ex.queries, ex.occupancy) > 0.9


@pytest.fixture
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny convolutions: a second OpenMP thread only adds waiting
    yield
    torch.set_num_threads(n)


def test_a_few_steps_lower_the_loss(two_meshes, one_thread):
    torch.manual_seed(0)
    net = FeatureNet(dataclasses.replace(TINY, point_weights=True))
    fit = FitSpec()
    rng = np.random.default_rng(1)
    batch = [make_example(two_meshes[i], rng, SMALL_AUG) for i in range(2)]

    def total():
        return sum(example_loss(net, ex, fit)[0] for ex in batch) / len(batch)

    opt = torch.optim.Adam(net.parameters(), lr=2e-2)
    with torch.no_grad():
        before = float(total())
    for _ in range(10):
        opt.zero_grad()
        loss = total()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
        opt.step()
    with torch.no_grad():
        after = float(total())
    # The same two examples before and after: the loss is deterministic, so any drop is real.
    assert after < before - 0.01, (before, after)


@pytest.mark.parametrize("name", ["nkf.toml", "nkf-gpu.toml"])
def test_shipped_configs_load(name):
    cfg = load_config(f"configs/{name}")
    assert cfg.fit.lam > 0 and cfg.model.feature_dim >= 1 and cfg.train.steps > 0


def test_config_errors_are_clear(tmp_path, capsys):
    from nkf_model.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[model]\nwidth_of_everything = 3\n")
    assert main(["train", "--config", str(bad), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "width_of_everything" in err[0]
    assert main(["train", "--config", str(tmp_path / "none.toml")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_winding_number_in_torch_matches_the_compiled_loop():
    # The PyTorch path (used to build the training cache on a GPU) runs the same formula.
    v, f = icosphere(2)
    rng = np.random.default_rng(3)
    q = np.concatenate([rng.uniform(-0.6, 0.6, (400, 3)), rng.normal(size=(100, 3)) * 0.01 + v[:100] * 0.999])
    np.testing.assert_allclose(metrics.winding_number(v, f, q, device="cpu"), metrics.winding_number(v, f, q),
                               atol=1e-9)
    w = metrics.winding_number(v, f, q, device="cpu")
    assert w.max() > 0.99 and w.min() < 0.01


def test_metrics_winding_agrees_for_the_test_meshes():
    v, f = box_mesh()
    q = np.array([[0.0, 0.0, 0.0], [0.39, 0.24, 0.14], [0.41, 0.0, 0.0]])
    assert list(metrics.occupancy(v, f, q)) == [True, True, False]


def test_train_cli_stops_checkpoints_and_resumes(tmp_path):
    """`nkf train` on two corpus meshes: stop after 2 steps, resume to 4, and --stop-after 0."""
    from nkf_model.cli import main
    from nkf_model.kernel.weights import load_weights
    from nkf_model.train import corpus

    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(
        "[model]\ngrid = 4\npointnet_width = 4\nunet_width = 2\nunet_levels = 2\nfeature_dim = 2\n"
        "point_weights = false\n"
        f'[data]\nholdout = 1\nlimit = 2\ncache = "{tmp_path / "cache"}"\n'
        "[cache]\nn_surface = 1000\nn_volume = 256\nn_near = 256\n"
        "[augment]\nn_min = 60\nn_max = 80\nn_mode = 70\nn_volume = 64\nn_near = 64\nn_surface = 32\n"
        "[train]\nsteps = 4\nbatch = 1\nval_every = 2\ncheckpoint_every = 2\nthreads = 1\ndevice = \"cpu\"\n"
        "[[validation]]\npoints = 80\nnoise = 0.0\nhalf = false\n"
    )
    out = tmp_path / "run"
    assert main(["train", "--config", str(cfg), "--out", str(out), "--max-steps", "2", "--quiet"]) == 0
    state = read_checkpoint(out / CHECKPOINT)
    assert state["step"] == 2
    assert main(["train", "--config", str(cfg), "--out", str(out), "--resume", "--stop-after", "0", "--quiet"]) == 0
    assert read_checkpoint(out / CHECKPOINT)["step"] == 2  # no time: no step
    assert main(["train", "--config", str(cfg), "--out", str(out), "--resume", "--quiet"]) == 0
    assert read_checkpoint(out / CHECKPOINT)["step"] == 4
    log = (out / "train.log").read_text()
    assert "resumed at step 2" in log and "stopped at step 4" in log
    load_weights(out / "nkf.safetensors")  # the best weights so far load as weights
    assert main(["train", "--config", str(cfg), "--out", str(out), "--quiet"]) == 1  # would overwrite a run
