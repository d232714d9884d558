"""'Install Dependencies' in the add-on preferences, with real pip and local wheels only.

Nothing is downloaded: the wheels are made here, and pip runs with ``--no-index --find-links``
(the preferences' offline wheels folder). The package list is overridden through the operator's
hidden ``requirements`` property; the real list (torch==2.13.0 from PyTorch's CPU index, ...) is
checked as a command line without running it.
"""

from __future__ import annotations

import base64
import hashlib
import importlib
import importlib.machinery
import sys
import zipfile
from pathlib import Path

import numpy
import pytest
from blender_helpers import PKG, ext, nkf_threads
from recording_layout import RecordingLayout


def make_wheel(folder: Path, name: str, version: str, files: dict, requires=()) -> Path:
    """A minimal, valid pure-Python wheel (METADATA, WHEEL, RECORD)."""
    dist = f"{name}-{version}.dist-info"
    meta = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n" + "".join(
        f"Requires-Dist: {r}\n" for r in requires
    )
    wheel = "Wheel-Version: 1.0\nGenerator: nkf-test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    entries = {**files, f"{dist}/METADATA": meta, f"{dist}/WHEEL": wheel}
    record = []
    for path, text in entries.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{path},sha256={digest},{len(text.encode())}")
    record.append(f"{dist}/RECORD,,")
    out = folder / f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(out, "w") as zf:
        for path, text in entries.items():
            zf.writestr(path, text)
        zf.writestr(f"{dist}/RECORD", "\n".join(record) + "\n")
    return out


@pytest.fixture
def wheelhouse(tmp_path):
    """A package that depends on numpy, and a (fake) numpy of Blender's own version."""
    make_wheel(tmp_path, "nkf_fakedep", "1.0", {"nkf_fakedep/__init__.py": "VALUE = 42\n"},
               requires=["numpy"])
    fake = {"numpy/__init__.py": "raise ImportError('fake numpy')\n"}
    make_wheel(tmp_path, "numpy", numpy.__version__, fake)
    return tmp_path


@pytest.fixture
def prefs(addon, bpy_module):
    p = bpy_module.context.preferences.addons[PKG].preferences
    system = bpy_module.context.preferences.system
    online = system.use_online_access
    yield p
    p.wheel_dir = ""
    system.use_online_access = online
    sys.modules.pop("nkf_fakedep", None)


def test_refuses_without_online_access(bpy_module, prefs, capsys):
    bpy = bpy_module
    bpy.context.preferences.system.use_online_access = False
    assert not bpy.app.online_access
    site = Path(ext("prefs").user_site(create=True))
    before = sorted(p.name for p in site.iterdir())
    with pytest.raises(RuntimeError, match="online access is off, so nothing was downloaded"):
        bpy.ops.nkf.install_dependencies(variant="CPU")
    assert sorted(p.name for p in site.iterdir()) == before
    assert not nkf_threads()
    layout = RecordingLayout()
    ext("prefs").draw_preferences(prefs, layout, bpy.context)
    assert "Online access is off" in layout.joined()
    (button,) = layout.operators("nkf.install_dependencies")
    assert not button.enabled


def test_installs_local_wheels_into_the_user_folder_without_numpy(bpy_module, prefs, wheelhouse, capsys):
    bpy = bpy_module
    bpy.context.preferences.system.use_online_access = True
    prefs.wheel_dir = str(wheelhouse)
    numpy_file = numpy.__file__
    reqs = f"nkf_fakedep numpy=={numpy.__version__}"
    res = bpy.ops.nkf.install_dependencies(variant="CPU", requirements=reqs)
    assert res == {"FINISHED"}
    site = Path(ext("prefs").user_site())
    names = {p.name for p in site.iterdir()}
    assert "nkf_fakedep" in names and "nkf_fakedep-1.0.dist-info" in names
    assert not any(n.lower().startswith("numpy") for n in names)  # pip put it there; it was removed
    out = capsys.readouterr().out
    assert "removed numpy" in out and "Installed nkf_fakedep-1.0" in out
    assert str(site) in sys.path
    assert sys.path.index(str(site)) > sys.path.index(str(Path(numpy_file).parents[1]))  # Blender's first
    assert importlib.import_module("nkf_fakedep").VALUE == 42
    # A fresh search of sys.path (as a new `import numpy` would do) still finds Blender's numpy.
    assert importlib.machinery.PathFinder.find_spec("numpy", sys.path).origin == numpy_file
    assert ext("prefs").InstallState.ok is True
    assert not nkf_threads()
    # The preferences show the outcome.
    layout = RecordingLayout()
    ext("prefs").draw_preferences(prefs, layout, bpy.context)
    assert "Installed nkf_fakedep-1.0" in layout.joined()


def test_a_failing_pip_run_is_reported(bpy_module, prefs, wheelhouse):
    bpy = bpy_module
    prefs.wheel_dir = str(wheelhouse)
    with pytest.raises(RuntimeError, match="pip failed"):
        bpy.ops.nkf.install_dependencies(requirements="package-that-is-not-in-the-folder")
    assert ext("prefs").InstallState.ok is False


def test_the_real_install_command_pins_torch_and_blenders_numpy():
    installer = ext("installer")
    reqs = installer.requirements("CPU")
    assert reqs[0] == "torch==2.13.0"
    assert f"numpy=={numpy.__version__}" in reqs
    cmd = installer.pip_command("/tmp/target", reqs, variant="CPU", python="python3", platform="linux")
    assert cmd[:4] == ["python3", "-m", "pip", "install"]
    assert cmd[cmd.index("--target") + 1] == "/tmp/target"
    assert cmd[cmd.index("--extra-index-url") + 1] == "https://download.pytorch.org/whl/cpu"
    assert "--only-binary" in cmd and cmd[-len(reqs):] == reqs
    cuda_linux = installer.pip_command("/t", reqs, variant="CUDA", python="p", platform="linux")
    assert "--extra-index-url" not in cuda_linux  # PyPI's Linux torch wheels are the CUDA builds
    cuda_win = installer.pip_command("/t", reqs, variant="CUDA", python="p", platform="win32")
    assert installer.CUDA_INDEX_WINDOWS in cuda_win
    with pytest.raises(installer.InstallError, match="macOS"):
        installer.pip_command("/t", reqs, variant="CUDA", python="p", platform="darwin")
    offline = installer.pip_command("/t", reqs, wheel_dir="/w", python="p")
    assert offline[offline.index("--find-links") + 1] == "/w" and "--no-index" in offline
