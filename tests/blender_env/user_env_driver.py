"""Runs inside a Blender-like Python (a venv with only ``bpy`` and what it pulls in), never under
pytest: ``python user_env_driver.py STEP ZIP SAMPLE OUT_JSON [METHODS]``. ``BLENDER_USER_RESOURCES`` must
point at a temporary folder. Writes what it measured to ``OUT_JSON``; any failure is an exception
(exit status 1, traceback on stderr).

Steps (each a fresh process, as a user's Blender sessions are):

* ``install``: check that none of the add-on's dependencies is importable, install and enable the
  zip (``package_install_files``), list what enabling loaded;
* ``bare``: ``import bpy`` only (the baseline of ``enable``);
* ``enable``: ``import bpy`` and enable the installed add-on; time and modules loaded;
* ``reconstruct``: enable, import the sample PLY, run Reconstruct with each of ``METHODS``
  (comma-separated, default ``SPLINES,NKF,SPLINES,NKF``), check the meshes and the report;
  ``reconstruct-prepared`` first runs the add-on's first-time preparation (what the UI starts
  after enabling) and times it separately;
* ``shadowed``: a folder holding another SciPy, one that fails to import the way a SciPy built for
  another NumPy does, is put first on ``sys.path`` (as ``PYTHONPATH``, a user site-packages or
  another add-on would), then enable and Reconstruct: the report must name the package, that
  folder and the fix, and the scene must be as it was;
* ``torch-halfway``: what a PyTorch install that stopped halfway leaves in the add-on's own
  ``site-packages`` (a ``torch`` folder whose import fails, its ``.dist-info``): **Check Again** in
  the preferences must name it, Neural Splines on the CPU must still work, and a run on the GPU
  must fail with one line naming PyTorch and its folder.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import sys
import time

PKG = "bl_ext.user_default.nkf_blender"
DEPENDENCIES = ("scipy", "skimage", "numba", "llvmlite", "threadpoolctl", "safetensors", "nkf_model", "tqdm",
                "plyfile", "lazy_loader", "torch")
HEAVY = ("torch", "numba", "scipy", "skimage", "llvmlite", "nkf_model.pipeline.reconstruct", "nkf_model.kernel.engines")


def _heavy_loaded() -> list[str]:
    return sorted(m for m in HEAVY if m in sys.modules)


def _enable() -> dict:
    import addon_utils

    n0 = len(sys.modules)
    t0 = time.perf_counter()
    mod = addon_utils.enable(PKG, default_set=True)
    dt = time.perf_counter() - t0
    assert mod is not None, "the add-on did not enable"
    return {"enable_s": dt, "enable_modules": len(sys.modules) - n0, "heavy_after_enable": _heavy_loaded()}


def _reconstruct(bpy, sample: str, method: str) -> dict:
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.ply_import(filepath=sample)
    src = bpy.context.active_object
    assert src is not None and len(src.data.vertices) > 1000, "the sample did not import"
    t0 = time.perf_counter()
    res = bpy.ops.object.nkf_reconstruct(method=method, resolution=128, device="CPU")
    dt = time.perf_counter() - t0
    assert res == {"FINISHED"}, res
    out = bpy.data.objects.get(src.name + "_nkf")
    assert out is not None, "no result object"
    faces = len(out.data.polygons)
    assert faces > 10000, f"only {faces} faces"
    runner = importlib.import_module(f"{PKG}.runner")
    report = runner.summary(out, runner.key_of(out))
    assert " on CPU" in report, report
    return {"seconds": dt, "faces": faces, "report": report}


def main(step: str, zip_path: str, sample: str, out_json: str, methods: str = "SPLINES,NKF,SPLINES,NKF") -> None:
    assert os.environ.get("BLENDER_USER_RESOURCES"), "set BLENDER_USER_RESOURCES to a temporary folder"
    result: dict = {"step": step, "python": sys.version.split()[0]}
    if step == "install":
        present = [m for m in DEPENDENCIES if importlib.util.find_spec(m) is not None]
        assert not present, f"not a Blender-like environment: {present} importable before the install"
    t0 = time.perf_counter()
    import bpy

    result["import_bpy_s"] = time.perf_counter() - t0
    result["blender"] = bpy.app.version_string
    import numpy

    result["numpy"] = numpy.__version__
    if step == "install":
        t0 = time.perf_counter()
        res = bpy.ops.extensions.package_install_files(
            filepath=zip_path, repo="user_default", enable_on_install=True
        )
        result["install_s"] = time.perf_counter() - t0
        assert res == {"FINISHED"}, res
        assert PKG in bpy.context.preferences.addons, "installed but not enabled"
        result["heavy_after_install"] = _heavy_loaded()
    elif step == "bare":
        pass
    elif step == "enable":
        result.update(_enable())
    elif step in ("reconstruct", "reconstruct-prepared"):
        result.update(_enable())
        if step == "reconstruct-prepared":
            prep = importlib.import_module(f"{PKG}.prepare")
            prefs = importlib.import_module(f"{PKG}.prefs")
            t0 = time.perf_counter()
            prep.start(prefs.prepare_folder())  # what the add-on's timer does after enabling in the UI
            assert prep.wait(timeout=900), "the preparation did not finish"
            result["prepare_s"] = time.perf_counter() - t0
            result["prepare_state"] = prep.status().state
            assert prep.status().state == "done", prep.status()
        runs = []
        for method in methods.split(","):
            runs.append({"method": method, **_reconstruct(bpy, sample, method)})
        result["runs"] = runs
        assert "torch" not in sys.modules, "PyTorch was imported"
        assert importlib.util.find_spec("torch") is None
        import nkf_model

        result["nkf_model_path"] = os.path.dirname(nkf_model.__file__)
    elif step == "shadowed":
        other = os.path.join(os.path.dirname(os.path.abspath(out_json)), "other-site-packages")
        os.makedirs(os.path.join(other, "scipy"), exist_ok=True)
        with open(os.path.join(other, "scipy", "__init__.py"), "w") as fh:
            fh.write("raise ImportError('numpy.core.multiarray failed to import')\n")
        sys.path.insert(0, other)
        result["other"] = other
        result.update(_enable())
        bpy.ops.wm.read_homefile(use_empty=True)
        bpy.ops.wm.ply_import(filepath=sample)
        src = bpy.context.active_object
        before = sorted((o.name, len(o.data.vertices)) for o in bpy.data.objects)
        try:
            res = bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=64, device="CPU")
            result["report"] = f"no error: {res}"
        except RuntimeError as exc:
            result["report"] = str(exc).strip()
        result["scene_unchanged"] = sorted((o.name, len(o.data.vertices)) for o in bpy.data.objects) == before
        result["source"] = src.name
    elif step == "torch-halfway":
        import contextlib
        import io

        result.update(_enable())
        prefs = importlib.import_module(f"{PKG}.prefs")
        site = prefs.user_site(create=True)
        os.makedirs(os.path.join(site, "torch"), exist_ok=True)
        os.makedirs(os.path.join(site, "torch-2.13.0.dist-info"), exist_ok=True)
        with open(os.path.join(site, "torch", "__init__.py"), "w") as fh:
            fh.write("raise ImportError('libtorch_cpu.so: cannot open shared object file: No such file or directory')\n")
        result["site"] = site
        prefs.apply_paths(prefs.get_prefs(bpy.context))
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            result["check"] = sorted(bpy.ops.nkf.check_dependencies())
        result["check_report"] = out.getvalue().strip()
        result["splines"] = _reconstruct(bpy, sample, "SPLINES")
        try:
            res = bpy.ops.object.nkf_reconstruct(method="SPLINES", resolution=64, device="GPU")
            result["gpu_report"] = f"no error: {res}"
        except RuntimeError as exc:
            result["gpu_report"] = str(exc).strip()
    else:
        raise SystemExit(f"unknown step {step!r}")
    with open(out_json, "w") as fh:
        json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main(*sys.argv[1:6])
