"""The nkf_model wheel bundled into the Blender extension holds what reconstruction needs and no
training or benchmark code."""

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# In a fresh process: setuptools refuses to load after the standard library's distutils, which other
# tests' imports may have loaded in this one.
BUILD = """
import sys
sys.path.insert(0, sys.argv[1])
from build_extension import build_wheel
print(build_wheel(__import__("pathlib").Path(sys.argv[2])))
"""


def test_bundled_wheel_leaves_out_training_and_benchmarks(tmp_path):
    run = subprocess.run([sys.executable, "-c", BUILD, str(ROOT / "scripts"), str(tmp_path)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    wheel = Path(run.stdout.strip().splitlines()[-1])
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
