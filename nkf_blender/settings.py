"""The reconstruction parameters, shared by the operator and the panel's scene settings.

``method`` (NKF, Neural Splines), ``regularization`` (the paper's lambda, shown as "Lambda"),
``resolution``, ``max_points`` and ``device``; for scans ``normals_mode`` (Auto, Given, Estimate),
``orientation`` of estimated normals (Outward, Up, Viewpoint: towards the scene camera),
``use_scan`` (an open surface: trim it where it runs farther than ``trim`` point spacings from the
points, and drop pieces under ``min_piece`` of the area), ``use_close`` and ``use_colors``. The
memory budget is a preference of the machine (:mod:`nkf_blender.prefs`), not a scene setting.

Defaults, hard ranges, slider ranges, labels, tooltips and enum item texts come from
:data:`nkf_model.options.SETTING` (standard library only, so this costs nothing at registration);
:func:`to_options` turns the properties into one validated :class:`nkf_model.options.Options`.
What stays Blender's own:

* the property names and enum identifiers (and the enum items' numbers), stored in .blend files;
* ``max_points``: 0 means all points (the core's ``None``), and the default is
  :data:`DEFAULT_MAX_POINTS` (the core's is all points), so a large scan is not run whole by accident;
* ``orientation``: Outward by default (the core's ``None`` means "viewpoint when there are
  viewpoints", and Blender's viewpoint is the scene camera, which most scenes have);
* ``trim`` and ``min_piece`` default to the scan preset (:data:`~nkf_model.options.SCAN_TRIM`,
  :data:`~nkf_model.options.SCAN_MIN_PIECE`) and apply only while ``use_scan`` is on;
* ``use_scan`` and ``use_colors`` have no core setting (colours are data: read them or not);
* the method's default is decided at registration (:func:`nkf_blender.methods.quick_default`).
"""

from __future__ import annotations

import math
import numbers

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from nkf_model.errors import InvalidParameterError
from nkf_model.options import SCAN_MIN_PIECE, SCAN_TRIM, SETTING, Options

from .errors import UserError
from .methods import DEVICE_IDS, METHOD_IDS

# Blender enum identifier -> the core's value, in the items' stored order (never reorder: a .blend
# file stores an enum property as the item's number).
NORMALS_IDS = {"AUTO": "auto", "GIVEN": "given", "ESTIMATE": "estimate"}
ORIENTATION_IDS = {"OUTWARD": "outward", "UP": "up", "VIEWPOINT": "viewpoint"}
# Blender-only defaults (see the module's docstring).
DEFAULT_MAX_POINTS = 100_000
DEFAULT_ORIENTATION = "OUTWARD"
# What an item means in Blender, added to the core's tooltip.
_ITEM_NOTES = {
    ("method", "nkf"): "; also needs PyTorch (add-on preferences)",
    ("orientation", "viewpoint"): ": here, the scene camera",
}


def description(name: str, none: str = "") -> str:
    """The core's tooltip of setting ``name``, its clause about ``None`` (which a Blender property
    cannot hold) replaced by ``none`` (Blender's equivalent) or dropped."""
    text = SETTING[name].description
    head, sep, _ = text.partition("; None")
    if sep:
        text = head + (f"; {none}" if none else "")
    return text


def enum_items(name: str, ids: dict) -> list[tuple[str, str, str, int]]:
    """``EnumProperty`` items for setting ``name``: ``ids`` maps each Blender identifier to the
    core's value; label and tooltip are the core's, the number is the position in ``ids``."""
    choices = {c.value: c for c in SETTING[name].choices}
    assert set(ids.values()) == set(choices), f"{name}: Blender items {ids} do not match the core's"
    return [
        (bid, choices[v].label, choices[v].description + _ITEM_NOTES.get((name, v), ""), i)
        for i, (bid, v) in enumerate(ids.items())
    ]


def _blender_id(ids: dict, value) -> str:
    return next(bid for bid, v in ids.items() if v == value)


def _changed(self, context) -> None:
    """A setting that Live follows changed (scene settings only)."""
    from . import live

    live.changed(self, context)


def annotations(default_method: str, update=None) -> dict:
    """Fresh property definitions, for a class's ``__annotations__`` before it is registered.

    ``update``: the callback of the settings that a kept fit only re-solves or re-meshes for (Lambda,
    Resolution, trim, Minimum Piece, Watertight), which Live follows."""
    upd = {} if update is None else {"update": update}
    lam, res, mp = SETTING["lam"], SETTING["resolution"], SETTING["max_points"]
    trim, piece, close = SETTING["trim"], SETTING["min_piece"], SETTING["close"]
    return {
        "method": EnumProperty(
            name=SETTING["method"].label, items=enum_items("method", METHOD_IDS), default=default_method,
            description=description("method"),
        ),
        "regularization": FloatProperty(
            name=lam.label, default=lam.default, min=lam.low, soft_max=lam.soft_high, precision=6,
            description=LAMBDA_TOOLTIP, **upd,
        ),
        "resolution": IntProperty(
            name=res.label, default=res.default, min=int(res.low), max=int(res.high), soft_max=int(res.soft_high),
            description=description("resolution"), **upd,
        ),
        "max_points": IntProperty(
            # 0 (all points) is Blender's stand-in for the core's None; 1 to 9 are refused by to_options.
            name=mp.label, default=DEFAULT_MAX_POINTS, min=0, soft_max=int(mp.soft_high),
            description=description("max_points", "0 uses all"),
        ),
        "device": EnumProperty(
            name=SETTING["device"].label, items=enum_items("device", DEVICE_IDS),
            default=_blender_id(DEVICE_IDS, SETTING["device"].default), description=description("device"),
        ),
        "normals_mode": EnumProperty(
            name=SETTING["normals_mode"].label, items=enum_items("normals_mode", NORMALS_IDS),
            default=_blender_id(NORMALS_IDS, SETTING["normals_mode"].default),
            description=description("normals_mode"),
        ),
        "orientation": EnumProperty(
            name=SETTING["orientation"].label, items=enum_items("orientation", ORIENTATION_IDS),
            default=DEFAULT_ORIENTATION, description=description("orientation"),
        ),
        "use_scan": BoolProperty(
            name="Scan (Open Surface)", default=False,
            description=(
                "The points are an open scan (a room, a facade, a statue on a plinth): cut the surface "
                "where it runs far from the points and drop small pieces, instead of closing it"
            ),
        ),
        "trim": FloatProperty(
            name=trim.label, default=SCAN_TRIM, min=trim.low, soft_max=trim.soft_high, precision=1,
            description=description("trim", "used while Scan is on"), **upd,
        ),
        "min_piece": FloatProperty(
            name=piece.label, default=SCAN_MIN_PIECE, min=piece.low, max=piece.high, soft_max=piece.soft_high,
            precision=4, step=0.1, description=description("min_piece") + "; used while Scan is on", **upd,
        ),
        "use_close": BoolProperty(name=close.label, default=close.default, description=description("close"), **upd),
        "use_outliers": BoolProperty(
            name=SETTING["outliers"].label, default=SETTING["outliers"].default, description=description("outliers"),
        ),
        "use_balloon_check": BoolProperty(
            name=SETTING["balloon_check"].label, default=SETTING["balloon_check"].default,
            description=description("balloon_check"),
        ),
        "use_colors": BoolProperty(
            name="Colours", default=True,
            description="Carry the points' colour attribute (e.g. 'Col' from a PLY) onto the mesh",
        ),
        "use_new_object": BoolProperty(
            name="New Object", default=False,
            description=(
                "Add a new result object; off: a source that already has a result gets that result updated "
                "in place (same object, name, materials, modifiers and collection)"
            ),
        ),
        "use_evaluated": BoolProperty(
            name="Evaluated Geometry", default=True,
            description=(
                "Read the points as the viewport shows them (modifiers and Geometry Nodes applied); "
                "off: the object's original data"
            ),
        ),
    }


PROPERTY_NAMES = (
    "method", "regularization", "resolution", "max_points", "device",
    "normals_mode", "orientation", "use_scan", "trim", "min_piece", "use_close", "use_outliers", "use_colors",
    "use_new_object", "use_evaluated", "use_balloon_check",
)
LAMBDA_TOOLTIP = (
    SETTING["lam"].description + ". Typed and shown like 1e-10; each step of the log slider is a factor of 10. "
    "Above 3,000 points the local fits use at least 8e-4 (s/h)^2 for the noise s estimated from the points and "
    "their spacing h (a floor that ignores smaller values)"
)
LOG_LAMBDA_MIN, LOG_LAMBDA_MAX = -16.0, math.log10(SETTING["lam"].soft_high)


def format_lambda(value: float) -> str:
    """Lambda as a person reads it: ``1e-10``, ``3.2e-07``, ``0``."""
    v = float(value)
    if v == 0.0:
        return "0"
    text = f"{v:.2g}"
    return text.replace("e-0", "e-").replace("e+0", "e")


def _get_lambda_text(self) -> str:
    return format_lambda(self.regularization)


def _set_lambda_text(self, text: str) -> None:
    try:
        v = float(str(text).strip())
    except ValueError:
        return  # not a number: the field shows the current value again
    if v >= 0 and v == v and v != float("inf"):
        self.regularization = v


def _get_lambda_log(self) -> float:
    v = float(self.regularization)
    return LOG_LAMBDA_MIN if v <= 0 else max(LOG_LAMBDA_MIN, math.log10(v))


def _set_lambda_log(self, value: float) -> None:
    self.regularization = 0.0 if value <= LOG_LAMBDA_MIN else float(10.0 ** round(float(value), 2))


def scene_annotations() -> dict:
    """Properties of the scene settings only: Live, and Lambda on a log scale (both views of
    ``regularization``, which stays the stored value)."""
    return {
        "lambda_text": StringProperty(
            name="Lambda", get=_get_lambda_text, set=_set_lambda_text, description=LAMBDA_TOOLTIP,
        ),
        "lambda_log": FloatProperty(
            name="log10 Lambda", get=_get_lambda_log, set=_set_lambda_log, min=LOG_LAMBDA_MIN, max=LOG_LAMBDA_MAX,
            soft_min=-12.0, soft_max=LOG_LAMBDA_MAX, step=25, precision=2,
            description="Lambda on a log scale: -10 is 1e-10, -6 is 1e-6 (smoother). " + LAMBDA_TOOLTIP,
        ),
        "live": BoolProperty(
            name="Live", default=False,
            description=(
                "Update the result by itself when Lambda, Resolution or a clean-up setting changes: a coarse "
                "preview while you drag, the full mesh when you stop (needs one Reconstruct first)"
            ),
        ),
    }


def build_options(**settings) -> Options:
    """A validated :class:`~nkf_model.options.Options` from settings in the core's names and values,
    with Blender's one convention (``max_points`` 0: all points). Any bad value raises
    :class:`~nkf_blender.errors.UserError` with the core's message; nothing else checks them."""
    mp = settings.get("max_points")
    if isinstance(mp, numbers.Integral) and not isinstance(mp, bool):
        low = int(SETTING["max_points"].low)
        if mp == 0:
            settings["max_points"] = None
        elif 0 < mp < low:
            raise UserError(f"Max Points must be 0 (all points) or at least {low}, got {mp}")
    try:
        return Options.build(**settings)
    except InvalidParameterError as exc:
        raise UserError(str(exc)) from None


def to_options(props, memory_budget: int | None = None) -> Options:
    """The :class:`~nkf_model.options.Options` of anything with the properties of
    :data:`PROPERTY_NAMES` (the operator, ``scene.nkf_settings``); ``memory_budget`` in bytes
    (``None``: the core's default). ``use_colors`` is not a setting: the caller reads it (whether
    colours are read and handed over). Raises :class:`~nkf_blender.errors.UserError`."""
    scan = bool(props.use_scan)
    return build_options(
        method=METHOD_IDS[props.method],
        lam=float(props.regularization),
        resolution=int(props.resolution),
        max_points=int(props.max_points),
        device=DEVICE_IDS[props.device],
        normals_mode=NORMALS_IDS[props.normals_mode],
        orientation=ORIENTATION_IDS[props.orientation],
        trim=float(props.trim) if scan else None,
        min_piece=float(props.min_piece) if scan else 0.0,
        close=bool(props.use_close),
        outliers=bool(props.use_outliers),
        balloon_check=bool(props.use_balloon_check),
        memory_budget=memory_budget,
    )


def copy_to(dst, src) -> None:
    for name in PROPERTY_NAMES:
        setattr(dst, name, getattr(src, name))


class NKF_PG_settings(bpy.types.PropertyGroup):
    """The panel's parameters, stored in the scene (``scene.nkf_settings``)."""


def prepare_classes(default_method: str, *classes) -> None:
    """Give each class its property definitions (call before ``register_class``)."""
    for cls in classes:
        scene = cls is NKF_PG_settings
        cls.__annotations__ = {
            **getattr(cls, "__annotations__", {}),
            **annotations(default_method, update=_changed if scene else None),
            **(scene_annotations() if scene else {}),
        }
