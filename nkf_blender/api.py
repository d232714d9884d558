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

from nkf_model.options import SETTING

from . import prefs, runner
from .errors import UserError
from .methods import DEVICE_IDS, METHOD_IDS, default_method
from .settings import DEFAULT_MAX_POINTS, build_options

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


def _choice(name: str, value, setting: str) -> str:
    """``value`` lower-cased, if it is a value of the core's ``setting`` (the message names this
    function's keyword ``name``)."""
    v = str(value).lower()
    allowed = SETTING[setting].values
    if v not in allowed:
        raise UserError(f"{name} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
    return v


def _as(kind, value):
    """``kind(value)`` (numbers given as other numeric types), else ``value`` itself for
    :class:`~nkf_model.options.Options` to refuse with its message."""
    try:
        return kind(value)
    except (TypeError, ValueError):
        return value


def reconstruct_object(
    obj: bpy.types.Object,
    *,
    method: str | None = None,
    regularization: float = SETTING["lam"].default,
    resolution: int = SETTING["resolution"].default,
    max_points: int = DEFAULT_MAX_POINTS,
    device: str = "auto",
    normals: str = "auto",
    orientation: str = "outward",
    trim: float | None = None,
    min_piece: float = 0.0,
    close: bool = False,
    balloon_check: bool = True,
    colors: bool = True,
    memory_budget_gb: float | None = None,
    new_object: bool = False,
    evaluated: bool = True,
    context=None,
) -> bpy.types.Object:
    """Reconstruct a surface from ``obj``'s points; return the result object.

    A source that already has a result (a mesh object whose ``nkf_source_ref`` custom property is
    ``obj``) gets that result updated in place, unless ``new_object``; a kept fit of the same points
    and fit settings is reused (only a new lambda or resolution: a re-solve or a re-mesh).

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
        Use a seeded random subset above this many points; 0 uses all. The default, 100,000, is the
        panel's (the core's is all points).
    device : {"auto", "cpu", "gpu"}
    normals : {"auto", "given", "estimate"}
        ``"auto"``: the object's normals when it has them, else estimated; ``"given"``: the
        object must have normals; ``"estimate"``: estimated even when it has some.
    orientation : {"outward", "up", "viewpoint"}
        Which way estimated normals point; ``"viewpoint"``: towards the scanner-position empties of
        an imported E57 scan (its children marked ``nkf_scanner``), else the scene camera.
    trim : float, optional
        For open scans: cut the surface farther than this many point spacings from every point
        (``nkf_model.options.SCAN_TRIM`` = 4 suits scans); ``None`` keeps the closed surface.
    min_piece : float
        Drop connected pieces under this fraction of the area (scans:
        ``nkf_model.options.SCAN_MIN_PIECE`` = 0.002); 0 keeps all.
    close : bool
        Cap the surface where it runs into the bounding box (plus 5 %): a watertight mesh.
    balloon_check : bool
        ``method="nkf"``, up to 3,000 points: fit the data-free kernel too where the learned surface
        bulges far beyond the points, and use it if it stays nearer (``Mesh.stats["balloon_check"]``).
    colors : bool
        Carry the object's POINT colour attribute (e.g. ``Col``) onto the mesh as ``Col``.
    memory_budget_gb : float, optional
        Refuse runs estimated above this many GiB; default: the add-on preference, else 60 % of
        the memory (at most 16 GiB).
    new_object : bool
        Add a new result object even when ``obj`` has one.
    evaluated : bool
        Read the points as evaluated (modifiers and Geometry Nodes applied); ``False``: the original data.
    context : bpy.types.Context, optional
        Default ``bpy.context``; its view layer gets the new object selected and active.

    Returns
    -------
    bpy.types.Object
        A new one named ``<obj.name>_nkf``, in ``obj``'s collection, with ``obj``'s world matrix (or
        the updated result, which keeps its name, collection, materials and modifiers); its mesh is
        in ``obj``'s local coordinates, so the two line up exactly. Smooth shaded. Custom properties
        record how it was made (``nkf_method``, ``nkf_lambda``, ``nkf_resolution``, ...).

    Raises
    ------
    nkf_blender.errors.UserError
        (a ``ValueError``) with one clear line, for every problem with the object, the settings
        or the installation; nothing is changed then.
    """
    if not isinstance(obj, bpy.types.Object):
        raise UserError(f"expected a bpy.types.Object, got {type(obj).__name__}")
    context = context or bpy.context
    if memory_budget_gb is not None and not float(memory_budget_gb) > 0:
        raise UserError(f"memory_budget_gb must be > 0, got {memory_budget_gb!r}")
    options = build_options(
        method=_method(method),
        lam=_as(float, regularization),
        resolution=_as(int, resolution),
        max_points=_as(int, max_points),
        device=_device(device),
        normals_mode=_choice("normals", normals, "normals_mode"),
        orientation=_choice("orientation", orientation, "orientation"),
        trim=None if trim is None else _as(float, trim),
        min_piece=_as(float, min_piece),
        close=bool(close),
        balloon_check=bool(balloon_check),
        memory_budget=(
            int(float(memory_budget_gb) * prefs.GIB) if memory_budget_gb is not None else prefs.memory_budget(context)
        ),
    )
    ob = runner.run_sync(context, obj, options, colors=bool(colors), new_object=bool(new_object),
                         evaluated=bool(evaluated))
    if ob is None:  # only a cancel event can get here, and nothing sets one in this path
        raise UserError("the reconstruction was cancelled")
    return ob
