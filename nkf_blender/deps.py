"""Which Python packages the reconstruction needs, and whether Blender's Python can import them.

No ``bpy`` here. The check uses :func:`importlib.util.find_spec`, which finds a package without
importing it, so it is cheap enough for a panel; the result is cached until :func:`refresh`.

* Required for any reconstruction: ``nkf_model``, ``scipy``, ``skimage`` (scikit-image),
  ``threadpoolctl``, and a kernel engine: ``numba`` (fast on the CPU) or ``torch``. The
  self-contained zips bundle all of them (and ``safetensors``, for NKF's weights).
* ``torch`` (PyTorch) is needed only for the GPU: NKF runs on the CPU without it.

Extra folders (the extension's own ``site-packages`` and a folder the user points to) are
*appended* to ``sys.path``, so Blender's bundled NumPy always comes first.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from dataclasses import dataclass, field
from pathlib import Path

# import name -> name on PyPI (what the user would install).
REQUIRED = {"nkf_model": "nkf-model", "scipy": "scipy", "skimage": "scikit-image", "threadpoolctl": "threadpoolctl"}
ENGINES = {"numba": "numba", "torch": "torch"}
OPTIONAL = {"torch": "torch", "safetensors": "safetensors"}


def _importable(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # ValueError: sys.modules[name] is None (import blocked)
        return False


@dataclass(frozen=True)
class DepStatus:
    """What is importable now.

    Attributes
    ----------
    found : dict[str, bool]
        Import name -> importable, for every package in REQUIRED, ENGINES and OPTIONAL.
    """

    found: dict = field(default_factory=dict)

    @property
    def missing_required(self) -> list[str]:
        """PyPI names of the packages without which nothing can run (empty when ready)."""
        out = [pypi for mod, pypi in REQUIRED.items() if not self.found.get(mod)]
        if not any(self.found.get(mod) for mod in ENGINES):
            out.append("numba or torch")
        return out

    @property
    def ready(self) -> bool:
        """True when a reconstruction can run (on the CPU, with Neural Splines at least)."""
        return not self.missing_required

    @property
    def torch(self) -> bool:
        return bool(self.found.get("torch"))

    def message(self) -> str:
        """One line for the user, empty when everything (PyTorch included) is there."""
        if not self.ready:
            return (
                "Missing Python packages: " + ", ".join(self.missing_required)
                + ". Install them in the add-on preferences (Install Dependencies)"
            )
        if not self.torch:
            return (
                "PyTorch is not installed: only the GPU needs it. "
                "Install GPU support in the add-on preferences"
            )
        return ""


_status: DepStatus | None = None


def check() -> DepStatus:
    """Look for every package now (cheap: nothing is imported) and cache the answer."""
    global _status
    importlib.invalidate_caches()
    names = {**REQUIRED, **ENGINES, **OPTIONAL}
    _status = DepStatus(found={mod: _importable(mod) for mod in names})
    return _status


def status() -> DepStatus:
    """The cached status (checked on first use)."""
    return _status if _status is not None else check()


def refresh() -> DepStatus:
    """Forget the cached status and check again (after an install or a path change)."""
    return check()


# What a reconstruction really imports, beyond the package names: a package can be found and still
# fail to import (a partly unpacked wheel, a library missing, another version first on sys.path).
IMPORTS = {
    "nkf_model": "nkf_model.pipeline.reconstruct",
    "scipy": "scipy.linalg, scipy.spatial, scipy.sparse.csgraph",
    "skimage": "skimage.measure",
    "threadpoolctl": "threadpoolctl",
    "numba": "numba",
    "safetensors": "safetensors.numpy",
    "torch": "torch",  # optional (the GPU); a half-finished install is found but does not import
}

_VERIFY = """
import importlib, json, sys
sys.path[:] = json.loads(sys.argv[1])
out = {}
for name, mods in json.loads(sys.argv[2]).items():
    try:
        for mod in mods.split(", "):
            importlib.import_module(mod)
    except BaseException as exc:
        out[name] = (type(exc).__name__ + ": " + str(exc)).splitlines()[0]
print(json.dumps(out))
"""


def verify(names=None, timeout: float = 120.0) -> dict[str, str]:
    """Import the packages for real, in a separate Python process with this one's ``sys.path`` (so a
    broken binary cannot take Blender down); returns ``{import name: one line}`` for each failure,
    ``{}`` when all import. ``names``: keys of :data:`IMPORTS` (default: all of them)."""
    import json
    import subprocess

    wanted = {n: IMPORTS.get(n, n) for n in (names or IMPORTS)}
    try:
        run = subprocess.run(
            [sys.executable, "-c", _VERIFY, json.dumps(sys.path), json.dumps(wanted)],
            capture_output=True, text=True, timeout=timeout,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {n: f"the check could not run ({type(exc).__name__})" for n in wanted}
    if run.returncode != 0:  # the interpreter itself died: a crashing binary; find which
        if len(wanted) > 1:
            out: dict[str, str] = {}
            for n in wanted:
                out.update(verify([n], timeout))
            return out
        return {n: f"importing it crashed Python (exit status {run.returncode})" for n in wanted}
    try:
        return json.loads(run.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {n: "the check printed nothing readable" for n in wanted}


# Folders this module appended to sys.path, so they can be taken off again.
_added: list[str] = []


def add_path(path) -> bool:
    """Append ``path`` to ``sys.path`` (after Blender's own folders) if it is an existing folder.

    Returns True when the folder is on ``sys.path`` afterwards.
    """
    if not path:
        return False
    p = str(Path(path).expanduser().resolve())
    if not Path(p).is_dir():
        return False
    if p not in sys.path:
        sys.path.append(p)
        _added.append(p)
        importlib.invalidate_caches()
    return True


def remove_path(path) -> None:
    """Take ``path`` off ``sys.path`` if :func:`add_path` put it there."""
    if not path:
        return
    p = str(Path(path).expanduser().resolve())
    if p in _added:
        _added.remove(p)
        while p in sys.path:
            sys.path.remove(p)
        importlib.invalidate_caches()


def remove_added_paths() -> None:
    """Take every folder :func:`add_path` appended back off ``sys.path``."""
    while _added:
        p = _added.pop()
        while p in sys.path:
            sys.path.remove(p)
    importlib.invalidate_caches()


def added_paths() -> list[str]:
    return list(_added)
