"""Fixtures for the Blender tests: the real ``bpy`` module and the real extension zip.

``BLENDER_USER_RESOURCES`` points at a temporary folder before ``bpy`` is imported (once per
process), so nothing is written into ``~/.config/blender``. The extension is built once per session
with Blender's own tool (``scripts/build_extension.py``), installed and enabled with
``bpy.ops.extensions.package_install_files``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from blender_helpers import PKG, ROOT, ext, nkf_threads

# Before any test module (or helper) of this folder imports bpy: Blender's user folders go to a
# temporary directory instead of ~/.config/blender.
_USER_DIR = None
if "bpy" not in sys.modules:
    _USER_DIR = tempfile.mkdtemp(prefix="nkf-blender-user-")
    os.environ["BLENDER_USER_RESOURCES"] = _USER_DIR


@pytest.fixture(scope="session")
def bpy_module():
    """``bpy``, imported once per process, with its user folders in a temporary directory."""
    assert os.environ.get("BLENDER_USER_RESOURCES"), "bpy was imported without BLENDER_USER_RESOURCES"
    import bpy

    yield bpy
    if _USER_DIR:
        shutil.rmtree(_USER_DIR, ignore_errors=True)


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    stage = tmp_path_factory.mktemp("stage") / "extension"
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "build_extension.py"), "--output-dir", str(out),
         "--stage-dir", str(stage), "--no-bundle"],  # this venv has the dependencies; tests/blender_env
        # installs the self-contained zip in a Python that has only bpy
        capture_output=True, text=True, cwd=ROOT,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    zips = list(out.glob("*.zip"))
    assert len(zips) == 1, zips
    return zips[0]


@pytest.fixture(scope="session")
def addon(bpy_module, extension_zip):
    """The extension, installed from the zip and enabled; disabled again at the end."""
    bpy = bpy_module
    res = bpy.ops.extensions.package_install_files(
        filepath=str(extension_zip), repo="user_default", enable_on_install=True
    )
    assert res == {"FINISHED"}
    assert PKG in bpy.context.preferences.addons
    yield ext()
    import addon_utils

    addon_utils.disable(PKG, default_set=True)
    assert not nkf_threads()


@pytest.fixture
def scene(addon, bpy_module):
    """An empty scene (the extension stays enabled); checks that no worker is left behind."""
    bpy = bpy_module
    bpy.ops.wm.read_homefile(use_empty=True)
    yield bpy.context.scene
    stuck = ext("runner").stop_all(timeout=10)
    assert not stuck, f"worker threads still running for {stuck}"
    assert not nkf_threads()
