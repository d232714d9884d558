"""Scripting: reconstruct an object from Python and get the new object back.

Once the extension is enabled its modules live under ``bl_ext.<repository>.nkf_blender``::

    import importlib
    api = importlib.import_module("bl_ext.user_default.nkf_blender.api")
    new_obj = api.reconstruct_object(bpy.data.objects["scan"], method="splines", resolution=128)

This is the operator's code path (``runner.run_sync``), without the operator: it works on any
object (not only the active one), in the foreground or headless, and runs synchronously.
"""

from __future__ import annotations

import bpy

from . import runner
from .errors import UserError
from .job import Settings
from .methods import DEVICE_IDS, METHOD_IDS, default_method
from .settings import DEFAULT_LAMBDA, DEFAULT_MAX_POINTS, DEFAULT_RESOLUTION

__all__ = ["reconstruct_object", "UserError"]


def _method(value) -> str:
    if value is None:
        return METHOD_IDS[default_method()]
    v = str(value).lower()
    v = {"neural splines": "splines", "neural_splines": "splines"}.get(v, v)
    if v not in METHOD_IDS.values():
        raise UserError(f"method must be 'nkf' or 'splines', got {value!r}")
    return v


def _device(value) -> str:
    v = str(value).lower()
    v = {"gpu": "cuda"}.get(v, v)
    if v not in DEVICE_IDS.values():
        raise UserError(f"device must be 'auto', 'cpu' or 'gpu', got {value!r}")
    return v


def reconstruct_object(
    obj: bpy.types.Object,
    *,
    method: str | None = None,
    regularization: float = DEFAULT_LAMBDA,
    resolution: int = DEFAULT_RESOLUTION,
    max_points: int = DEFAULT_MAX_POINTS,
    device: str = "auto",
    context=None,
) -> bpy.types.Object:
    """Reconstruct a surface from ``obj``'s oriented points; return the new mesh object.

    Parameters
    ----------
    obj : bpy.types.Object
        A Mesh (loose vertices with a ``normal`` point attribute, as PLY import gives, or a mesh
        with faces) or a PointCloud. Never modified.
    method : {"nkf", "splines"}, optional
        Default: ``"nkf"`` when nkf_model can run it here, else ``"splines"``.
    regularization : float
        The paper's lambda, >= 0; larger is smoother.
    resolution : int
        Grid cells along the longest side, 16 to 1024.
    max_points : int
        Use a seeded random subset above this many points; 0 uses all.
    device : {"auto", "cpu", "gpu"}
    context : bpy.types.Context, optional
        Default ``bpy.context``; its view layer gets the new object selected and active.

    Returns
    -------
    bpy.types.Object
        Named ``<obj.name>_nkf``, in ``obj``'s collection, with ``obj``'s world matrix; its mesh
        is in ``obj``'s local coordinates, so the two line up exactly. Smooth shaded.

    Raises
    ------
    nkf_blender.errors.UserError
        (a ``ValueError``) with one clear line, for every problem with the object, the settings
        or the installation; nothing is changed then.
    """
    if not isinstance(obj, bpy.types.Object):
        raise UserError(f"expected a bpy.types.Object, got {type(obj).__name__}")
    settings = Settings(
        method=_method(method),
        lam=float(regularization),
        resolution=int(resolution),
        max_points=int(max_points),
        device=_device(device),
    )
    ob = runner.run_sync(context or bpy.context, obj, settings)
    if ob is None:  # only a cancel event can get here, and nothing sets one in this path
        raise UserError("the reconstruction was cancelled")
    return ob
