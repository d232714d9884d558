"""Where the add-on's packages come from, and one line that says why an import failed. No ``bpy``.

A self-contained zip bundles its wheels; Blender unpacks them into the extensions'
``site-packages`` folder, which Blender puts *after* its own folders on ``sys.path``. Anything
earlier on the path wins: a user site-packages (Blender started with ``--python-use-system-env``),
``PYTHONPATH``, or another add-on that inserted its own folder at the front. When such a folder
holds another SciPy (or NumPy, or numba) that does not work with Blender's Python, the import fails
inside that other copy. :func:`explain` turns the exception into one line that names the package,
the folder it was imported from, and what to do: the bundled copy damaged (reinstall the add-on),
another copy first on the path (remove it or take its folder off the path), or a package missing.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import sys
import sysconfig
from pathlib import Path

MANIFEST = "blender_manifest.toml"
# Top-level import names of what the reconstruction imports, and what those import in turn.
PACKAGES = ("nkf_model", "scipy", "skimage", "numba", "llvmlite", "threadpoolctl", "safetensors", "numpy",
            "lazy_loader", "torch")

# Import name -> distribution name, where they differ.
DISTRIBUTIONS = {"skimage": "scikit-image", "nkf_model": "nkf-model"}


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _unpacked(info: Path) -> bool:
    """False for an editable install's ``.dist-info`` (PEP 610): its files are elsewhere."""
    try:
        return not json.loads((info / "direct_url.json").read_text()).get("dir_info", {}).get("editable", False)
    except (OSError, ValueError, AttributeError):
        return True


def manifest_wheels(ext_dir=None) -> set[tuple[str, str]]:
    """``(normalised distribution name, version)`` of each wheel the extension's manifest lists
    (``ext_dir``, default this package's folder); empty without a manifest or wheels."""
    import tomllib

    ext_dir = Path(__file__).parent if ext_dir is None else Path(ext_dir)
    try:
        wheels = tomllib.loads((ext_dir / MANIFEST).read_text()).get("wheels", [])
    except (OSError, ValueError):
        return set()
    out = set()
    for w in wheels:
        parts = Path(w).name.split("-")
        if len(parts) >= 2:
            out.add((_canon(parts[0]), parts[1]))
    return out


def bundled_folder(ext_dir=None, paths=None) -> tuple[Path | None, list[Path]]:
    """The folder Blender unpacked this extension's wheels into: the first of ``paths`` (default
    ``sys.path``) that holds the ``.dist-info`` of a wheel listed in the extension's manifest
    (``ext_dir``, default this package's folder), editable installs left out; and those
    ``.dist-info`` folders. ``(None, [])`` when there is none (no manifest, no wheels: an add-on
    installed without its bundled wheels, or the project's own environment)."""
    wanted = manifest_wheels(ext_dir)
    if not wanted:
        return None, []
    for entry in sys.path if paths is None else paths:
        folder = Path(entry or ".")
        try:
            infos = [d for d in folder.glob("*.dist-info")
                     if (_canon(d.name[:-10].split("-", 1)[0]), d.name[:-10].split("-", 1)[-1]) in wanted
                     and _unpacked(d)]
        except OSError:
            continue
        if infos:
            return folder, infos
    return None, []


def _holds(folder: Path, top: str) -> bool:
    return (folder / top).is_dir() or (folder / f"{top}.py").is_file() or any(folder.glob(f"{top}.*.so"))


def _entries(paths) -> list[tuple[str, Path]]:
    out = []
    for entry in sys.path if paths is None else paths:
        try:
            p = Path(entry or ".").resolve()
        except OSError:
            continue
        out.append((str(p) + os.sep, p))
    return sorted(out, key=lambda e: -len(e[0]))  # the deepest folder first


def _locate(filename: str, entries) -> tuple[str, Path] | None:
    """(top-level package, folder on the path) of a source file, or None."""
    try:
        f = str(Path(filename).resolve())
    except (OSError, ValueError):
        return None
    for prefix, folder in entries:
        if f.startswith(prefix):
            top = f[len(prefix):].split(os.sep, 1)[0]
            return top.split(".", 1)[0], folder
    return None


def origin(top: str, paths=None) -> Path | None:
    """The folder on the path that ``import top`` uses (the loaded module's, or where Python would
    find it now), or None when it is not there."""
    mod = sys.modules.get(top)
    file = getattr(mod, "__file__", None) if mod is not None else None
    if file is None:
        try:
            spec = importlib.util.find_spec(top)
        except (ImportError, ValueError):
            spec = None
        file = getattr(spec, "origin", None) if spec is not None else None
    if not file or file in ("built-in", "frozen"):
        return None
    hit = _locate(file, _entries(paths))
    if hit is not None:
        return hit[1]
    file = Path(file)
    return file.parent.parent if file.stem == "__init__" else file.parent


def _failed_package(exc: BaseException, entries) -> tuple[str | None, Path | None]:
    """Which known package the import failed in, and its folder: the innermost frame of the
    traceback inside one of :data:`PACKAGES`, else the module the exception names."""
    frames = []
    tb = exc.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame.f_code.co_filename)
        tb = tb.tb_next
    for filename in reversed(frames):
        hit = _locate(filename, entries)
        if hit is not None and hit[0] in PACKAGES and hit[0] != "nkf_model":
            return hit
    name = getattr(exc, "name", None)
    if name:
        return name.split(".", 1)[0], None
    for filename in reversed(frames):
        hit = _locate(filename, entries)
        if hit is not None and hit[0] in PACKAGES:
            return hit
    return None, None


def _first_line(exc: BaseException) -> str:
    return (f"{type(exc).__name__}: {exc}".splitlines() or [type(exc).__name__])[0]


def _numpy_note(bundled: Path | None) -> str:
    """A clause when NumPy comes from a folder that is neither Blender's own nor the bundle's."""
    where = origin("numpy")
    if where is None:
        return ""
    own = {Path(p).resolve() for p in (sysconfig.get_path("purelib"), sysconfig.get_path("platlib")) if p}
    if where in own or where == bundled:
        return ""
    version = getattr(sys.modules.get("numpy"), "__version__", "")
    return f"; NumPy {version} is imported from {where}, not from Blender's own".replace("NumPy  ", "NumPy ")


def explain(exc: BaseException, paths=None, ext_dir=None) -> str:
    """One line for the user about a failed import ``exc``: the package, the folder it was imported
    from and what to do. ``paths`` (default ``sys.path``) and ``ext_dir`` (the extension's folder,
    for its manifest) are for tests."""
    entries = _entries(paths)
    bundled, _ = bundled_folder(ext_dir, paths)
    bundled = bundled.resolve() if bundled is not None else None
    top, folder = _failed_package(exc, entries)
    why = _first_line(exc)
    note = _numpy_note(bundled)
    if top is None:
        return f"a Python package cannot be imported ({why}); install the dependencies in the add-on preferences"
    if folder is None and isinstance(exc, ModuleNotFoundError):
        listed = {name for name, _ in manifest_wheels(ext_dir)}
        if bundled is not None and _canon(DISTRIBUTIONS.get(top, top)) in listed:
            return (f"the Python package {top} is missing from the add-on's bundled packages in {bundled} "
                    f"({why}); reinstall the add-on{note}")
        return f"the Python package {top} is missing ({why}); install the dependencies in the add-on preferences"
    folder = folder if folder is not None else origin(top, paths)
    if bundled is not None and folder is not None and folder != bundled and _holds(bundled, top):
        return (f"cannot import {top}: another copy of it, in {folder}, comes before the add-on's own on "
                f"Python's search path and fails ({why}); remove it there or take that folder off the path "
                f"(PYTHONPATH, the user site-packages or another add-on puts it first){note}")
    if bundled is not None and folder == bundled:
        return f"cannot import the add-on's bundled {top} from {folder} ({why}); reinstall the add-on{note}"
    where = f" from {folder}" if folder is not None else ""
    if top == "torch":  # optional, for the GPU: installed by the preferences' own button
        return (f"cannot import torch (PyTorch){where} ({why}){note}; install GPU support (PyTorch) again in "
                "the add-on preferences, or remove that copy if another program put it there")
    return (f"cannot import {top}{where} ({why}){note}; install the dependencies in the add-on preferences, "
            "or remove that copy if another program put it there")
