"""A package that does not import ends in one line naming it, the folder it came from and what to
do: another copy first on Python's path (a user site-packages, PYTHONPATH, another add-on), the
add-on's bundled copy damaged, or a package missing. The imports here are real: a stand-in SciPy
that fails the way one built for another NumPy does, imported while the real one is set aside."""

from __future__ import annotations

import importlib
import sys

import pytest
from blender_helpers import ext

BROKEN = "raise ImportError('numpy.core.multiarray failed to import')\n"


def _bundle(tmp_path):
    """An extension folder whose manifest lists a SciPy wheel, and the folder Blender unpacked it to."""
    ext_dir = tmp_path / "extension"
    ext_dir.mkdir()
    (ext_dir / "blender_manifest.toml").write_text(
        'wheels = ["./wheels/scipy-1.16.3-cp311-cp311-manylinux_2_27_x86_64.whl"]\n')
    site = tmp_path / "extensions-site-packages"
    (site / "scipy").mkdir(parents=True)
    (site / "scipy" / "__init__.py").write_text("")
    (site / "scipy-1.16.3.dist-info").mkdir()
    return ext_dir, site


def _package(folder, text=BROKEN):
    (folder / "scipy").mkdir(parents=True, exist_ok=True)
    (folder / "scipy" / "__init__.py").write_text(text)
    return folder


def _import_scipy_from(monkeypatch, paths) -> ImportError:
    """Import ``scipy`` for real with ``paths`` first on sys.path; the real SciPy is put back after."""
    monkeypatch.delitem(sys.modules, "scipy", raising=False)
    for p in reversed(paths):
        monkeypatch.syspath_prepend(str(p))
    importlib.invalidate_caches()
    with pytest.raises(ImportError) as info:
        importlib.import_module("scipy")
    return info.value


def test_another_scipy_first_on_the_path_is_named_with_its_folder(addon, monkeypatch, tmp_path):
    imf = ext("import_failure")
    ext_dir, site = _bundle(tmp_path)
    other = _package(tmp_path / "user-site")
    exc = _import_scipy_from(monkeypatch, [other, site])
    msg = imf.explain(exc, paths=[str(other), str(site)], ext_dir=ext_dir)
    assert msg.startswith(f"cannot import scipy: another copy of it, in {other.resolve()}, comes before "
                          "the add-on's own on Python's search path and fails "
                          "(ImportError: numpy.core.multiarray failed to import); remove it there"), msg
    assert "\n" not in msg


def test_a_damaged_bundled_copy_says_reinstall(addon, monkeypatch, tmp_path):
    imf = ext("import_failure")
    ext_dir, site = _bundle(tmp_path)
    _package(site)
    exc = _import_scipy_from(monkeypatch, [site])
    msg = imf.explain(exc, paths=[str(site)], ext_dir=ext_dir)
    assert msg == (f"cannot import the add-on's bundled scipy from {site.resolve()} "
                   "(ImportError: numpy.core.multiarray failed to import); reinstall the add-on"), msg


def test_a_missing_package(addon, tmp_path):
    imf = ext("import_failure")
    ext_dir, site = _bundle(tmp_path)
    (ext_dir / "blender_manifest.toml").write_text(
        'wheels = ["./wheels/scipy-1.16.3-cp311-cp311-manylinux_2_27_x86_64.whl", '
        '"./wheels/scikit_image-0.25.2-cp311-cp311-manylinux_2_17_x86_64.whl"]\n')
    with pytest.raises(ModuleNotFoundError) as info:
        importlib.import_module("skimage_not_there")
    missing = info.value
    missing.name = "skimage"  # a bundled package gone from the folder (its wheel is in the manifest)
    msg = imf.explain(missing, paths=[str(site)], ext_dir=ext_dir)
    assert msg.startswith(f"the Python package skimage is missing from the add-on's bundled packages in "
                          f"{site.resolve()}"), msg
    assert msg.endswith("reinstall the add-on")
    missing.name = "threadpoolctl"  # not in the manifest: the bundle never had it
    msg = imf.explain(missing, paths=[str(site)], ext_dir=ext_dir)
    assert msg.startswith("the Python package threadpoolctl is missing ("), msg
    assert msg.endswith("install the dependencies in the add-on preferences"), msg
    msg = imf.explain(missing, paths=[str(site)], ext_dir=tmp_path / "no-manifest")
    assert msg.endswith("install the dependencies in the add-on preferences"), msg


def test_no_bundle_names_the_folder(addon, monkeypatch, tmp_path):
    imf = ext("import_failure")
    other = _package(tmp_path / "somewhere")
    exc = _import_scipy_from(monkeypatch, [other])
    msg = imf.explain(exc, paths=[str(other)], ext_dir=tmp_path / "no-manifest")
    assert msg.startswith(f"cannot import scipy from {other.resolve()} (ImportError: "), msg


def test_a_job_that_fails_to_import_reports_the_explanation(addon, monkeypatch, tmp_path):
    """The worker's failure path: the job's one line is the explanation, state failed."""
    import numpy as np

    from nkf_model.options import Options

    job_mod = ext("job")
    other = _package(tmp_path / "user-site")
    exc = _import_scipy_from(monkeypatch, [other])
    job = job_mod.ReconstructJob(np.zeros((10, 3)), None, Options())
    job._fail(exc)
    assert job.state == job_mod.FAILED
    assert job.error.startswith(f"cannot import scipy from {other.resolve()} (ImportError: numpy.core"), job.error



def test_gpu_with_a_half_installed_pytorch_names_it_and_its_folder(addon, monkeypatch, tmp_path):
    """What a PyTorch install stopped halfway leaves: a ``torch`` folder whose import fails. Asked
    for the GPU, the job's one line says PyTorch cannot be imported, from where, and what to do."""
    import numpy as np

    from nkf_model.kernel import engines
    from nkf_model.options import Options

    other = tmp_path / "site-packages"
    (other / "torch").mkdir(parents=True)
    (other / "torch" / "__init__.py").write_text(
        "raise ImportError('libtorch_cpu.so: cannot open shared object file: No such file or directory')\n")
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    monkeypatch.syspath_prepend(str(other))
    monkeypatch.setattr(engines, "cuda_driver_present", lambda: True)
    with pytest.raises(engines.MethodUnavailableError) as info:
        engines.select_engine("cuda")
    job_mod = ext("job")
    job = job_mod.ReconstructJob(np.zeros((10, 3)), None, Options())
    job._fail(info.value)
    assert job.state == job_mod.FAILED
    assert job.error == (
        f"device 'cuda' was asked for, but PyTorch cannot be imported: cannot import torch (PyTorch) from "
        f"{other.resolve()} (ImportError: libtorch_cpu.so: cannot open shared object file: No such file or "
        "directory); install GPU support (PyTorch) again in the add-on preferences, or remove that copy if "
        "another program put it there"), job.error
