"""The dependency check imports for real, in a separate process, and names what fails: a package
that is found but cannot be imported (a partly unpacked wheel, a missing library), or one whose
import crashes Python, is reported by name and Blender keeps running."""

from __future__ import annotations

from blender_helpers import ext


def _packages(tmp_path):
    (tmp_path / "brokenpkg").mkdir()
    (tmp_path / "brokenpkg" / "__init__.py").write_text(
        "raise ImportError('libgfortran.so.5: cannot open shared object file')\n")
    (tmp_path / "crashpkg").mkdir()
    (tmp_path / "crashpkg" / "__init__.py").write_text("import os\nos._exit(3)\n")
    return str(tmp_path)


def test_verify_names_each_failure(addon, monkeypatch, tmp_path):
    deps = ext("deps")
    assert deps.verify() == {}  # everything the reconstruction imports, imported for real
    monkeypatch.syspath_prepend(_packages(tmp_path))
    got = deps.verify(["brokenpkg", "crashpkg", "threadpoolctl"])
    assert got == {
        "brokenpkg": "ImportError: libgfortran.so.5: cannot open shared object file",
        "crashpkg": "importing it crashed Python (exit status 3)",
    }


def test_check_button_reports_a_package_that_does_not_import(addon, bpy_module, monkeypatch, tmp_path, capsys):
    deps = ext("deps")
    monkeypatch.syspath_prepend(_packages(tmp_path))
    monkeypatch.setitem(deps.IMPORTS, "scipy", "brokenpkg")  # scipy is found, but "its import" fails
    assert bpy_module.ops.nkf.check_dependencies() == {"FINISHED"}
    out = capsys.readouterr().out
    import scipy

    where = ext("import_failure").origin("scipy")  # the folder the import uses, named for the user
    assert where is not None and str(where) in scipy.__file__
    assert f"NKF: cannot import scipy from {where} (ImportError: libgfortran.so.5: cannot open shared object file)" in out
