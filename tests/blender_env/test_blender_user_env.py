"""The add-on as a Blender user gets it: the self-contained linux-x64 zip, installed into a Python
that has only ``bpy`` (5.0.1, and 4.2.0, the oldest version the manifest claims), enabled, and used
to reconstruct the sample with Neural Splines and NKF on the CPU, with no PyTorch, no network and
no "Install Dependencies". Any dependency missing from the zip fails here.

The environments are made once and cached (``user_env.py``); each step runs in a fresh process
(``user_env_driver.py``) with Blender's user folders in a temporary directory.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
import user_env

ROOT = Path(__file__).resolve().parents[2]
DRIVER = Path(__file__).with_name("user_env_driver.py")
SAMPLE = ROOT / "nkf_model" / "data" / "sample.ply"

pytestmark = pytest.mark.skipif(
    not (sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64")),
    reason="the self-contained zip tested here is the linux-x64 one",
)


def _build_extension_module():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import build_extension
    finally:
        sys.path.pop(0)
    return build_extension


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    stage = tmp_path_factory.mktemp("stage") / "extension"
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "build_extension.py"), "--platforms", "linux-x64",
         "--output-dir", str(out), "--stage-dir", str(stage)],
        capture_output=True, text=True, cwd=ROOT,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    zips = sorted(out.glob("*.zip"))
    assert [z.name for z in zips] == ["nkf_blender-0.1.0-linux_x64.zip"]
    return zips[0]


def test_zip_bundles_every_dependency_for_its_platform_and_no_numpy(linux_zip):
    be = _build_extension_module()
    with zipfile.ZipFile(linux_zip) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    wheels = sorted(n.removeprefix("wheels/") for n in names if n.endswith(".whl"))
    assert manifest["platforms"] == ["linux-x64"]
    assert sorted(w.removeprefix("./wheels/") for w in manifest["wheels"]) == wheels
    for pin in be.BUNDLED + ("nkf-model==0.1.0",):
        name, version = pin.split("==")
        assert any(be._canon(w.split("-")[0]) == be._canon(name) and w.split("-")[1] == version for w in wheels), pin
    assert len(wheels) == len(be.BUNDLED) + 1
    assert not [w for w in wheels if w.lower().startswith(("numpy-", "torch-"))]
    for w in wheels:  # only this platform's wheels (or pure Python ones)
        tags = w.removesuffix(".whl").split("-")[-1]
        assert tags == "any" or all(re.match(r"manylinux.*x86_64$", t) for t in tags.split(".")), w


def _step(py: Path, step: str, zip_path: Path, user: Path, out: Path, methods: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "NUMBA_"))}
    env["BLENDER_USER_RESOURCES"] = str(user)
    res = out / f"{step}.json"
    cmd = [str(py), str(DRIVER), step, str(zip_path), str(SAMPLE), str(res)] + ([methods] if methods else [])
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=out, env=env, timeout=1800)
    assert run.returncode == 0, f"{step} failed:\n{run.stdout[-4000:]}\n{run.stderr[-4000:]}"
    return json.loads(res.read_text())


@pytest.mark.parametrize("version", ["5.0.1", "4.2.0"])
def test_blender_user_installs_enables_and_reconstructs(version, linux_zip, tmp_path):
    py = user_env.ensure(version)
    user = tmp_path / "user"
    user.mkdir()
    got = _step(py, "install", linux_zip, user, tmp_path)  # also checks that no dependency is there
    assert got["blender"].startswith(version.rsplit(".", 1)[0])
    assert got["heavy_after_install"] == []
    got = _step(py, "enable", linux_zip, user, tmp_path)
    assert got["heavy_after_enable"] == []
    prepared = version == "5.0.1"  # 5.0: the UI's first-time preparation, then warm runs
    got = _step(py, "reconstruct-prepared" if prepared else "reconstruct", linux_zip, user, tmp_path, "SPLINES,NKF")
    assert [r["method"] for r in got["runs"]] == ["SPLINES", "NKF"]
    assert all(r["report"].endswith(("thread", "threads")) for r in got["runs"]), got["runs"]
    assert "/extensions/" in got["nkf_model_path"]  # the bundled copy, not the project's
    if prepared:
        assert got["prepare_state"] == "done"
        markers = list(user.rglob("prepared.txt"))
        assert len(markers) == 1 and "numba 0.68.1" in markers[0].read_text()
    if prepared:  # another SciPy first on the path: one line naming it, its folder and the fix
        got = _step(py, "shadowed", linux_zip, user, tmp_path)
        assert got["report"].startswith(
            f"Error: NKF: cannot import scipy: another copy of it, in {got['other']}, comes before the add-on's "
            "own on Python's search path and fails (ImportError: numpy.core.multiarray failed to import)"
        ), got["report"]
        assert "\n" not in got["report"] and got["scene_unchanged"], got
        # What a PyTorch install stopped halfway leaves: named by Check Again; the CPU still works.
        got = _step(py, "torch-halfway", linux_zip, user, tmp_path)
        assert got["check_report"] == (f"Warning: NKF: cannot import torch from {got['site']} (ImportError: "
                                       "libtorch_cpu.so: cannot open shared object file: No such file or directory)"
                                       ), got["check_report"]
        assert got["splines"]["report"].endswith(("thread", "threads")), got["splines"]
        assert got["gpu_report"] in (
            "Error: NKF: device 'cuda' was asked for, but this computer has no NVIDIA driver (no CUDA device); "
            "use 'cpu' or 'auto'",
        ) or got["gpu_report"].startswith(
            "Error: NKF: device 'cuda' was asked for, but PyTorch cannot be imported: cannot import torch (PyTorch) "
            f"from {got['site']} (ImportError: libtorch_cpu.so"), got["gpu_report"]

