"""Enabling the extension is cheap: it loads none of the heavy packages (PyTorch, numba, SciPy,
scikit-image) and none of nkf_model's reconstruction code, only its settings, errors and stage list.
The panel's first draw loads nkf_model's time and memory model (NumPy only), no heavy package.

Runs in a fresh process (this one has long imported everything): the project's Python, Blender's
user folders in a temporary directory, the built zip installed, then enabled with a stopwatch.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from blender_helpers import PKG, ROOT

# Top-level packages and nkf_model subpackages that enabling must not import.
HEAVY_PACKAGES = ("torch", "numba", "scipy", "skimage")
HEAVY_NKF = ("nkf_model.pipeline", "nkf_model.normals", "nkf_model.kernel", "nkf_model.fit", "nkf_model.surface")
# Standard-library-only modules of nkf_model that the add-on reads its settings from.
LIGHT_NKF = ("nkf_model.pipeline", "nkf_model.pipeline.stages")

SCRIPT = r"""
import json, sys, time
from types import SimpleNamespace
import bpy
import addon_utils

zip_path, pkg, helpers = sys.argv[1], sys.argv[2], sys.argv[3]
res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=False)
assert res == {"FINISHED"}, res
before_enable = set(sys.modules)
t0 = time.perf_counter()
mod = addon_utils.enable(pkg, default_set=True)
took = time.perf_counter() - t0
assert mod is not None and pkg in bpy.context.preferences.addons, "the extension did not enable"
assert hasattr(bpy.types, "VIEW3D_PT_nkf") and "nkf_settings" in bpy.types.Scene.bl_rna.properties
default = bpy.ops.object.nkf_reconstruct.get_rna_type().properties["method"].default
enabled = sorted(sys.modules)

# The panel's first draw, with a point cloud and the default method (NKF where it can run).
sys.path.insert(0, helpers)
from recording_layout import RecordingLayout
bpy.ops.wm.read_homefile(use_empty=True)
bpy.ops.mesh.primitive_ico_sphere_add()
before = set(sys.modules)
t0 = time.perf_counter()
layout = RecordingLayout()
bpy.types.VIEW3D_PT_nkf.draw(SimpleNamespace(layout=layout), bpy.context)
draw_took = time.perf_counter() - t0
assert "Estimate:" in layout.joined(), layout.joined()
print(json.dumps({"seconds": took, "modules": enabled, "new": sorted(set(enabled) - before_enable),
                  "default_method": default, "draw_seconds": draw_took,
                  "draw_new": sorted(set(sys.modules) - before)}))
addon_utils.disable(pkg, default_set=True)
"""


def heavy(modules) -> list[str]:
    """The names in ``modules`` that enabling must not import."""
    out = []
    for name in modules:
        if name.split(".")[0] in HEAVY_PACKAGES:
            out.append(name)
        elif name not in LIGHT_NKF and any(name == p or name.startswith(p + ".") for p in HEAVY_NKF):
            out.append(name)
    return sorted(out)


def test_heavy_checker():
    assert heavy(["torch", "torch.nn", "scipy.spatial", "skimage", "numba.core", "numpy", "nkf_model",
                  "nkf_model.options", "nkf_model.errors", "nkf_model.pipeline", "nkf_model.pipeline.stages",
                  "nkf_model.pipeline.budget", "nkf_model.kernel", "nkf_model.normals.estimate", "torchvision"]) == [
        "nkf_model.kernel", "nkf_model.normals.estimate", "nkf_model.pipeline.budget", "numba.core", "scipy.spatial",
        "skimage", "torch", "torch.nn",
    ]


def test_enabling_imports_no_heavy_module(extension_zip, tmp_path):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender-user"))
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(extension_zip), PKG, str(ROOT / "tests" / "blender")],
        capture_output=True, text=True, env=env,
        timeout=300, cwd=tmp_path,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])
    print(f"enabling the extension took {report['seconds']:.3f} s and imported {len(report['new'])} modules; "
          f"default method {report['default_method']}")
    assert heavy(report["modules"]) == []
    assert "nkf_model.options" in report["modules"]  # the settings do come from the core
    drawn = report["draw_new"]
    print(f"the panel's first draw took {report['draw_seconds']:.3f} s and imported "
          f"{', '.join(m for m in drawn if m.startswith('nkf_model')) or 'no nkf_model module'}")
    assert [m for m in drawn if m.split(".")[0] in HEAVY_PACKAGES] == []
