"""Long training runs: the data worker, exact resume, and committing the run folder."""

from __future__ import annotations

import subprocess
import types
from pathlib import Path

import pytest
import torch

from nkf_model.kernel.feature_net import FeatureNet
from nkf_model.train.kernel_training import CHECKPOINT, Trainer, load_config, read_checkpoint, write_checkpoint


def _config(tmp_path: Path, workers: int) -> Path:
    cfg = tmp_path / f"tiny-{workers}.toml"
    cfg.write_text(
        "[model]\ngrid = 4\npointnet_width = 4\nunet_width = 2\nunet_levels = 2\nfeature_dim = 2\n"
        "point_weights = false\nconst_channel = true\n"
        f'[data]\nsplit = "sources"\nlimit = 2\nval_per_kind = 1\np_procedural = 0.5\ncache = "{tmp_path / "cache"}"\n'
        "[cache]\nn_surface = 1000\nn_volume = 256\nn_near = 256\n"
        "[procedural]\nn_surface = 800\nn_volume = 256\nn_near = 256\ngrid = 40\n"
        "[augment]\nn_min = 60\nn_max = 90\nn_mode = 70\nn_volume = 64\nn_near = 64\nn_surface = 32\np_partial = 0.5\n"
        f"[train]\nsteps = 4\nbatch = 2\nwarmup = 2\nval_every = 2\ncheckpoint_every = 2\nthreads = 1\n"
        f'workers = {workers}\ndevice = "cpu"\n'
        "[[validation]]\npoints = 80\nnoise = 0.0\nhalf = false\n"
    )
    return cfg


def test_worker_and_resume_give_the_same_run_as_one_session(tmp_path):
    """4 steps in one go with the data worker == 2 steps, then --resume for 2, made in-process."""
    from nkf_model.cli import main
    from nkf_model.train import corpus

    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["train", "--config", str(_config(tmp_path, 1)), "--out", str(a), "--quiet"]) == 0
    cfg0 = str(_config(tmp_path, 0))
    assert main(["train", "--config", cfg0, "--out", str(b), "--max-steps", "2", "--quiet"]) == 0
    assert read_checkpoint(b / CHECKPOINT)["step"] == 2
    with open(b / "metrics.csv", "a") as fh:  # a step logged after the checkpoint, before the session ended
        fh.write("train,3,1.0,1.0,0.5,0.4,0.1,0.001,0,,,\n")
    assert main(["train", "--config", cfg0, "--out", str(b), "--resume", "--quiet"]) == 0
    steps = [int(r.split(",")[1]) for r in (b / "metrics.csv").read_text().splitlines() if r.startswith("train,")]
    assert steps == [1, 2, 3, 4]
    sa = read_checkpoint(a / CHECKPOINT)
    sb = read_checkpoint(b / CHECKPOINT)
    assert sa["step"] == sb["step"] == 4
    assert sa["cpu"] > 0 and sb["cpu"] > 0
    for k in sa["model"]:
        assert torch.equal(sa["model"][k], sb["model"][k]), k
    for k in sa["optimizer"]["state"]:
        for name, v in sa["optimizer"]["state"][k].items():
            assert torch.equal(v, sb["optimizer"]["state"][k][name])
    # ... and the weights did change over the 4 steps (same seed: the same initial network)
    torch.manual_seed(0)
    init_state = FeatureNet(load_config(cfg0).model).state_dict()
    assert any(not torch.equal(init_state[k], sa["model"][k]) for k in sa["model"])
    log = (b / "train.log").read_text()
    assert "resumed at step 2" in log and "held-out mean IoU by kind" in log and "CPU hours" in log


def _git(cwd, *args):
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout


def test_commit_takes_only_the_run_folder(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    _git(repo, "config", "user.email", "t@example.com")
    _git(repo, "config", "user.name", "t")
    (repo / "other.txt").write_text("x")
    _git(repo, "add", "other.txt")
    _git(repo, "commit", "-q", "-m", "first")
    (repo / "other.txt").write_text("someone else's staged change")
    _git(repo, "add", "other.txt")
    out = repo / "training" / "run"
    out.mkdir(parents=True)
    (out / CHECKPOINT).write_bytes(b"abc")
    (out / "train.log").write_text("log\n")
    logged = []
    tr = types.SimpleNamespace(out=out, step=7, cpu=3600.0, best=0.5, log=logged.append)
    assert Trainer.commit(tr) is True
    files = _git(repo, "show", "--name-only", "--format=%s", "HEAD").split("\n")
    assert files[0].startswith("Training run training/run: step 7, 1.00 CPU hours")
    assert sorted(f for f in files[1:] if f) == [f"training/run/{CHECKPOINT}", "training/run/train.log"]
    assert _git(repo, "diff", "--cached", "--name-only").split() == ["other.txt"]  # still staged, not committed
    # Nothing new: git commit has nothing to do, which is reported, not raised.
    assert Trainer.commit(tr) is False and "commit failed" in logged[-1]
    # Outside a repository
    tr.out = tmp_path / "elsewhere"
    tr.out.mkdir()
    assert Trainer.commit(tr) is False and "not in a git repository" in logged[-1]


def test_a_checkpoint_accepts_settings_added_later_only_at_their_defaults():
    import json

    from nkf_model.train.kernel_training import config_matches

    cfg = load_config("configs/nkf-sources.toml").to_dict()
    assert config_matches(json.loads(json.dumps(cfg)), cfg)
    older = json.loads(json.dumps(cfg))
    del older["train"]["checkpoint_minutes"]  # written before the setting existed
    assert not config_matches(older, cfg)  # the run uses 5, not the default 0
    cfg0 = dict(cfg, train=dict(cfg["train"], checkpoint_minutes=0.0))
    assert config_matches(older, cfg0)
    changed = json.loads(json.dumps(cfg))
    changed["augment"]["noise_max"] = 0.02
    assert not config_matches(changed, cfg)
    removed = json.loads(json.dumps(cfg))
    removed["data"]["retired_setting"] = 1
    assert not config_matches(removed, cfg)


def test_checkpoint_is_safetensors_and_round_trips_the_optimizer(tmp_path):
    """No pickle: the checkpoint is a safetensors file whose model and Adam state come back exactly."""
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(4, 3)).square().sum().backward()
        opt.step()
    path = tmp_path / CHECKPOINT
    write_checkpoint(path, {"model": net.state_dict(), "optimizer": opt.state_dict(), "step": 3, "best": 0.5,
                            "elapsed": 1.5, "cpu": 2.0, "config": "{}"})
    assert path.read_bytes()[8:9] == b"{"  # a safetensors header (8-byte length, then JSON), not a pickle
    state = read_checkpoint(path)
    assert (state["step"], state["best"], state["elapsed"], state["cpu"], state["config"]) == (3, 0.5, 1.5, 2.0, "{}")
    net2 = torch.nn.Linear(3, 2)
    opt2 = torch.optim.Adam(net2.parameters(), lr=1e-3)
    net2.load_state_dict(state["model"])
    opt2.load_state_dict(state["optimizer"])
    for k, v in net.state_dict().items():
        assert torch.equal(v, net2.state_dict()[k])
    a, b = opt.state_dict(), opt2.state_dict()
    assert a["param_groups"] == b["param_groups"]
    for k in a["state"]:
        for name, v in a["state"][k].items():
            assert torch.equal(v, b["state"][k][name]), name
