"""Weights files of the learned kernel: exact round trip, and clear errors for bad files."""

from __future__ import annotations

import json
import struct

import pytest
import torch
from nkf_helpers import TINY, tiny_net, tiny_weights

from nkf_model.errors import MethodUnavailableError, NKFInputError, WeightsError
from nkf_model.kernel.feature_net import FeatureConfig
from nkf_model.kernel.weights import DEFAULT_WEIGHTS, load_weights, read_weights, save_weights


def test_save_and_load_are_bit_exact(tmp_path):
    net = tiny_net(seed=7)
    path = save_weights(tmp_path / "w.safetensors", net, lam=3e-9, training={"steps": 5})
    model = load_weights(path)
    want = net.state_dict()
    got = model.net.state_dict()
    assert set(got) == set(want)
    for k in want:
        assert got[k].dtype == want[k].dtype
        assert torch.equal(got[k], want[k]), k
    assert model.config == TINY
    assert model.meta["lam_value"] == 3e-9
    assert json.loads(model.meta["training"]) == {"steps": 5}
    # The file holds tensors and strings only: the first 8 bytes give the JSON header's length.
    raw = path.read_bytes()
    header = json.loads(raw[8 : 8 + struct.unpack("<Q", raw[:8])[0]])
    assert header["__metadata__"]["format"] == "nkf-weights"


def _assert_clear(path, *words):
    with pytest.raises(WeightsError) as info:
        load_weights(path)
    msg = str(info.value)
    assert isinstance(info.value, NKFInputError) and isinstance(info.value, ValueError)
    assert str(path) in msg and "\n" not in msg
    for w in words:
        assert w in msg, msg
    return msg


def test_missing_file(tmp_path):
    _assert_clear(tmp_path / "nope.safetensors", "does not exist")


def test_directory(tmp_path):
    _assert_clear(tmp_path, "not a file")


def test_truncated_file(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _assert_clear(path, "not a valid safetensors file")


def test_corrupt_header(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors")
    data = bytearray(path.read_bytes())
    data[8:20] = b"\x00garbage!!\xff\xfe"
    path.write_bytes(bytes(data))
    _assert_clear(path, "not a valid safetensors file")


@pytest.mark.parametrize("content", [b"", b"ply\nformat ascii 1.0\nend_header\n", b"\x80\x04\x95pickle" * 10])
def test_not_safetensors(tmp_path, content):
    path = tmp_path / "w.safetensors"
    path.write_bytes(content)
    _assert_clear(path, "not a valid safetensors file")


def test_safetensors_of_something_else(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "other.safetensors"
    save_file({"x": torch.zeros(3)}, str(path))
    _assert_clear(path, "not NKF weights")


def _rewrite_metadata(path, **changes):
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), framework="pt") as fh:
        meta = dict(fh.metadata())
        tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    meta.update(changes)
    save_file(tensors, str(path), metadata=meta)


def test_config_that_does_not_match_the_tensors(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors")
    other = FeatureConfig(**{**TINY.to_dict(), "feature_dim": 4})
    _rewrite_metadata(path, config=json.dumps(other.to_dict()))
    _assert_clear(path, "does not match its stored configuration", "shape")


def test_config_with_missing_tensors(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors")
    other = FeatureConfig(**{**TINY.to_dict(), "unet_levels": 3})
    _rewrite_metadata(path, config=json.dumps(other.to_dict()))
    _assert_clear(path, "does not match its stored configuration")


def test_unreadable_config_and_version(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors")
    _rewrite_metadata(path, config="{not json")
    _assert_clear(path, "unreadable model configuration")
    path = tiny_weights(tmp_path / "v.safetensors")
    _rewrite_metadata(path, format_version="99")
    _assert_clear(path, "format version")
    path = tiny_weights(tmp_path / "u.safetensors")
    _rewrite_metadata(path, config=json.dumps({**TINY.to_dict(), "colour": "blue"}))
    _assert_clear(path, "unreadable model configuration")


def test_non_finite_tensor(tmp_path):
    net = tiny_net()
    with torch.no_grad():
        net.gate[0] = float("nan")
    path = save_weights(tmp_path / "w.safetensors", net, lam=1e-10)
    _assert_clear(path, "NaN")


def test_read_weights_returns_the_config(tmp_path):
    path = tiny_weights(tmp_path / "w.safetensors", lam=2e-10)
    tensors, meta, config = read_weights(path)
    assert config == TINY and float(meta["lam"]) == 2e-10 and "gate" in tensors


def test_shipped_weights_are_small_and_valid():
    if not DEFAULT_WEIGHTS.exists():
        with pytest.raises(MethodUnavailableError, match="no default weights"):
            load_weights()
        return
    assert DEFAULT_WEIGHTS.stat().st_size < 20 * 2**20
    model = load_weights()
    assert model.meta["format"] == "nkf-weights"
    assert json.loads(model.meta["training"])["step"] > 0


def test_method_available():
    import nkf_model

    assert nkf_model.method_available("splines") == (True, "")
    ok, why = nkf_model.method_available("nkf")
    assert ok == DEFAULT_WEIGHTS.exists()
    assert ok or "no default weights" in why
    assert nkf_model.method_available("magic")[0] is False
