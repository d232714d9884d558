"""The reconstruction parameters, shared by the operator and the panel's scene settings.

``method`` (NKF, Neural Splines), ``regularization`` (the paper's lambda, shown as "Lambda"),
``resolution``, ``max_points`` and ``device``. The method's default is decided at registration:
NKF when ``nkf_model`` says it can run here, else Neural Splines.

For scans: ``normals_mode`` (Auto, Given, Estimate), ``orientation`` of estimated normals
(Outward, Up, Viewpoint: towards the scene camera), ``use_scan`` (an open surface: trim it where
it runs farther than ``trim`` point spacings from the points, and drop pieces under ``min_piece``
of the area; the defaults are nkf_model's scan defaults) and ``use_colors``. The memory budget is
a preference of the machine (:mod:`nkf_blender.prefs`), not a scene setting.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty

from .job import SCAN_MIN_PIECE, SCAN_TRIM, Settings
from .methods import DEVICE_IDS, METHOD_IDS

METHOD_ITEMS = [
    ("NKF", "NKF", "Neural Kernel Field: the learned kernel (needs its trained weights and PyTorch)"),
    ("SPLINES", "Neural Splines", "The data-free Neural Spline kernel: no weights, runs everywhere"),
]
DEVICE_ITEMS = [
    ("AUTO", "Auto", "A CUDA GPU when PyTorch sees one, else the CPU"),
    ("CPU", "CPU", "Always the CPU"),
    ("GPU", "GPU", "A CUDA GPU (needs the CUDA build of PyTorch)"),
]
NORMALS_ITEMS = [
    ("AUTO", "Auto", "The object's normals when it has them, else estimate them"),
    ("GIVEN", "Given", "The object's normals ('normal' attribute or vertex normals); an error without them"),
    ("ESTIMATE", "Estimate", "Estimate normals from the points (PCA over 16 neighbours), ignoring the object's"),
]
ORIENTATION_ITEMS = [
    ("OUTWARD", "Outward", "Estimated normals point away from the object (closed objects seen from all around)"),
    ("UP", "Up", "Estimated normals point upwards (terrain, aerial scans)"),
    ("VIEWPOINT", "Viewpoint", "Estimated normals point towards the scene camera (put it where the scanner was)"),
]
DEFAULT_LAMBDA = 1e-10
DEFAULT_RESOLUTION = 128
DEFAULT_MAX_POINTS = 100_000


def annotations(default_method: str) -> dict:
    """Fresh property definitions, for a class's ``__annotations__`` before it is registered."""
    return {
        "method": EnumProperty(
            name="Method", items=METHOD_ITEMS, default=default_method,
            description="Which kernel fits the surface",
        ),
        "regularization": FloatProperty(
            name="Lambda", default=DEFAULT_LAMBDA, min=0.0, soft_max=1e-3, precision=6,
            description=(
                "Regularization (the paper's lambda): 0 interpolates the points exactly, larger "
                "values give a smoother surface; 1e-12 to 1e-8 fit the points"
            ),
        ),
        "resolution": IntProperty(
            name="Resolution", default=DEFAULT_RESOLUTION, min=16, max=1024, soft_max=512,
            description="Grid cells along the longest side; higher gives finer detail and takes longer",
        ),
        "max_points": IntProperty(
            name="Max Points", default=DEFAULT_MAX_POINTS, min=0, soft_max=1_000_000,
            description="Use a random subset (fixed seed) when the object has more points; 0 uses all",
        ),
        "device": EnumProperty(
            name="Device", items=DEVICE_ITEMS, default="AUTO", description="Where the kernel runs",
        ),
        "normals_mode": EnumProperty(
            name="Normals", items=NORMALS_ITEMS, default="AUTO",
            description="Where the normals come from",
        ),
        "orientation": EnumProperty(
            name="Orientation", items=ORIENTATION_ITEMS, default="OUTWARD",
            description="Which way estimated normals point",
        ),
        "use_scan": BoolProperty(
            name="Scan (Open Surface)", default=False,
            description=(
                "The points are an open scan (a room, a facade, a statue on a plinth): cut the surface "
                "where it runs far from the points and drop small pieces, instead of closing it"
            ),
        ),
        "trim": FloatProperty(
            name="Trim Distance", default=SCAN_TRIM, min=0.5, soft_max=20.0, precision=1,
            description="Cut the surface farther than this many point spacings from every point",
        ),
        "min_piece": FloatProperty(
            name="Min Piece", default=SCAN_MIN_PIECE, min=0.0, max=0.99, soft_max=0.1, precision=4, step=0.1,
            description="Drop connected pieces with less than this fraction of the total area (0 keeps all)",
        ),
        "use_close": BoolProperty(
            name="Watertight", default=False,
            description=(
                "Cap the surface where it runs into the bounding box (plus 5 %), so that the mesh is "
                "closed, for 3D printing; off leaves it open there"
            ),
        ),
        "use_colors": BoolProperty(
            name="Colours", default=True,
            description="Carry the points' colour attribute (e.g. 'Col' from a PLY) onto the mesh",
        ),
    }


PROPERTY_NAMES = (
    "method", "regularization", "resolution", "max_points", "device",
    "normals_mode", "orientation", "use_scan", "trim", "min_piece", "use_close", "use_colors",
)


def to_settings(props, memory_budget: int | None = None) -> Settings:
    """A :class:`~nkf_blender.job.Settings` from anything with the properties of
    :data:`PROPERTY_NAMES`; ``memory_budget`` in bytes (``None``: nkf_model's default)."""
    scan = bool(props.use_scan)
    return Settings(
        method=METHOD_IDS[props.method],
        lam=float(props.regularization),
        resolution=int(props.resolution),
        max_points=int(props.max_points),
        device=DEVICE_IDS[props.device],
        normals_mode=props.normals_mode.lower(),
        orientation=props.orientation.lower(),
        trim=float(props.trim) if scan else None,
        min_piece=float(props.min_piece) if scan else 0.0,
        close=bool(props.use_close),
        colors=bool(props.use_colors),
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
        cls.__annotations__ = {**getattr(cls, "__annotations__", {}), **annotations(default_method)}
