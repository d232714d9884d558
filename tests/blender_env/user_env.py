"""Blender-like Python environments: a venv holding only ``bpy`` and what its wheel pulls in
(NumPy, requests, zstandard, Cython, ...), made once and kept in a cache folder.

``NKF_BLENDER_ENVS`` sets the folder (default ``.blender-envs/`` in the repository, git-ignored).
Each environment records what was installed into it in a marker file; one whose marker does not
match (or that is half made) is made again. Making one downloads ``bpy`` (about 375 MB) from the
package registry.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("NKF_BLENDER_ENVS", ROOT / ".blender-envs"))
MARKER = ".nkf-blender-env"

# bpy version -> what to install. The manifest's blender_version_min is 4.2.0. Blender 4.2 ships
# NumPy 1.26 like 5.0 does, but the bpy 4.2 wheel leaves NumPy unpinned (pip would take 2.x).
SPECS = {
    "5.0.1": ("bpy==5.0.1",),
    "4.2.0": ("bpy==4.2.0", "numpy==1.26.4"),
}


def python_of(env: Path) -> Path:
    return env / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def ensure(version: str, cache: Path = CACHE) -> Path:
    """The Python of the environment for ``bpy==version``, made first if needed."""
    spec = SPECS[version]
    env = cache / f"bpy-{version}"
    marker = env / MARKER
    py = python_of(env)
    if py.is_file() and marker.is_file() and marker.read_text().strip() == " ".join(spec):
        return py
    if env.exists():
        shutil.rmtree(env)
    cache.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "venv", str(env)], check=True, capture_output=True)
    run = subprocess.run([str(py), "-m", "pip", "install", "--quiet", *spec], capture_output=True, text=True)
    if run.returncode != 0:
        shutil.rmtree(env, ignore_errors=True)
        raise RuntimeError(f"pip install {' '.join(spec)} failed:\n{run.stdout}{run.stderr}")
    marker.write_text(" ".join(spec) + "\n")
    return py
