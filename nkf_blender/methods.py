"""Which reconstruction methods ``nkf_model`` can run here.

No ``bpy`` here. The learned NKF kernel may be missing (no weights, no safetensors); Neural Splines
needs nothing beyond the required packages. Two answers:

* :func:`method_status` asks ``nkf_model`` itself (``nkf_model.method_available``: it loads the
  weights, so it imports PyTorch, about a second). Used when the real answer is needed: the Python
  API's default method. Cached until :func:`refresh`.
* :func:`quick_status` imports nothing heavy: the real answer when it is cached, else whether the
  core ships its weights (:data:`nkf_model.options.SHIPPED_WEIGHTS`) and whether safetensors (for
  the weights; PyTorch is optional) can be found (``importlib.util.find_spec``, through
  :mod:`nkf_blender.deps`). Used at
  registration (the operator's default method) and by the panel, so that enabling the add-on and
  drawing the panel never load PyTorch. A weights file that is there but broken is then reported
  by the reconstruction itself.
"""

from __future__ import annotations

import threading

import numpy as np

from nkf_model.options import DEFAULT_METHOD, SHIPPED_WEIGHTS

from . import deps
from .import_failure import explain as explain_import_failure

# Blender enum identifier -> nkf_model's value, in the items' stored order (never reorder: a .blend
# file stores an enum property as the item's number).
METHOD_IDS = {"NKF": "nkf", "SPLINES": "splines"}
DEVICE_IDS = {"AUTO": "auto", "CPU": "cpu", "GPU": "cuda"}

_cache: dict[str, tuple[bool, str]] = {}


def _probe_points():
    """Twenty-six points on a unit sphere with outward normals (enough for any input check)."""
    d = np.array(
        [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
        dtype=np.float64,
    )
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, d.copy()


def method_status(method: str) -> tuple[bool, str]:
    """``(available, reason)`` for an nkf_model method name (``"nkf"`` or ``"splines"``).

    Uses ``nkf_model.method_available(method)`` when the package has it. Otherwise it asks
    :func:`nkf_model.reconstruct` directly with a cancel event that is already set: an unavailable
    method raises :class:`~nkf_model.errors.MethodUnavailableError` with its reason before any work,
    and an available one stops at its first progress check with
    :class:`~nkf_model.errors.Cancelled`, so the probe costs milliseconds.
    """
    if method in _cache:
        return _cache[method]
    try:
        import nkf_model
    except ImportError as exc:
        return False, explain_import_failure(exc)
    ask = getattr(nkf_model, "method_available", None)
    if callable(ask):
        try:
            res = ask(method)
            ok, why = (res if isinstance(res, tuple) else (bool(res), ""))
        except Exception as exc:  # the package's own check failed: say so, do not crash the UI
            ok, why = False, str(exc)
    else:
        stop = threading.Event()
        stop.set()
        pts, nrm = _probe_points()
        try:
            nkf_model.reconstruct(pts, nrm, method=method, resolution=16, device="cpu", cancel=stop)
            ok, why = True, ""
        except nkf_model.Cancelled:
            ok, why = True, ""
        except nkf_model.MethodUnavailableError as exc:
            ok, why = False, str(exc)
        except Exception as exc:
            ok, why = False, f"{type(exc).__name__}: {exc}"
    _cache[method] = (bool(ok), str(why))
    return _cache[method]


def quick_status(method: str) -> tuple[bool, str]:
    """``(available, reason)`` without importing PyTorch or any of nkf_model's reconstruction code:
    :func:`method_status`'s answer when it is cached, else what can be told from the files."""
    if method in _cache:
        return _cache[method]
    if method == "splines":
        return True, ""
    if method != "nkf":
        return False, f"unknown method {method!r}"
    if not SHIPPED_WEIGHTS.is_file():
        return False, "this installation has no default weights for method 'nkf'; use Neural Splines"
    st = deps.status()
    # PyTorch is not needed: without it the feature network runs in NumPy (same features).
    missing = [name for name in ("safetensors",) if not st.found.get(name)]
    if missing:
        return False, (
            f"{' and '.join(missing)} {'is' if len(missing) == 1 else 'are'} not installed: "
            "install the dependencies in the add-on preferences"
        )
    return True, ""


def quick_default() -> str:
    """The Blender enum id of the default method (nothing heavy imported): ``"NKF"`` only when the core
    makes it the default (:data:`nkf_model.options.DEFAULT_METHOD`: its weights passed the gate on
    held-out sources) and :func:`quick_status` says it can run here."""
    return "NKF" if DEFAULT_METHOD == "nkf" and quick_status("nkf")[0] else "SPLINES"


def nkf_available() -> tuple[bool, str]:
    """``(available, reason)`` for the learned NKF kernel."""
    return method_status("nkf")


def default_method() -> str:
    """The Blender enum id of the default method: ``"NKF"`` when the core makes it the default
    (:data:`nkf_model.options.DEFAULT_METHOD`) and it can run here, else ``"SPLINES"``."""
    return "NKF" if DEFAULT_METHOD == "nkf" and nkf_available()[0] else "SPLINES"


def refresh() -> None:
    """Forget the cached answers (after installing dependencies)."""
    _cache.clear()
