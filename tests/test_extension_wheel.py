"""The nkf_model wheel bundled into the Blender extension holds what reconstruction needs and no
training or benchmark code."""

import importlib.util
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _build_extension_module():
    spec = importlib.util.spec_from_file_location("build_extension", ROOT / "scripts" / "build_extension.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bundled_wheel_leaves_out_training_and_benchmarks(tmp_path):
    wheel = _build_extension_module().build_wheel(tmp_path)
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        record = next(n for n in names if n.endswith(".dist-info/RECORD"))
        listed = [line.split(",")[0] for line in z.read(record).decode().splitlines()]
    assert not [n for n in names if n.startswith("nkf_model/train/") or n.startswith("benchmarks/")]
    assert not [n for n in listed if n.startswith("nkf_model/train/")]
    for needed in ("nkf_model/options.py", "nkf_model/pipeline/reconstruct.py", "nkf_model/surface/mesh.py",
                   "nkf_model/weights/nkf_default.safetensors", "nkf_model/weights/MODEL_CARD.md"):
        assert needed in names and needed in listed
    assert set(listed) == set(names)  # RECORD lists exactly the files the wheel holds
