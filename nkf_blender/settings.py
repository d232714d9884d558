"""The reconstruction parameters, shared by the operator and the panel's scene settings.

``method`` (NKF, Neural Splines), ``regularization`` (the paper's lambda, shown as "Lambda"),
``resolution``, ``max_points`` and ``device``. The method's default is decided at registration:
NKF when ``nkf_model`` says it can run here, else Neural Splines.
"""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty

from .job import Settings
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
    }


PROPERTY_NAMES = ("method", "regularization", "resolution", "max_points", "device")


def to_settings(props) -> Settings:
    """A :class:`~nkf_blender.job.Settings` from anything with the five properties."""
    return Settings(
        method=METHOD_IDS[props.method],
        lam=float(props.regularization),
        resolution=int(props.resolution),
        max_points=int(props.max_points),
        device=DEVICE_IDS[props.device],
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
