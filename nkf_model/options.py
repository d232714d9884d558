"""Every setting of a reconstruction in one place: its default, range, choices, label and message.

Standard library only, so that a user interface (the ``nkf`` command line, Blender's property
group) can read defaults, ranges, enum items and tooltips without loading NumPy's heavier
neighbours (SciPy, scikit-image, numba, PyTorch)::

    from nkf_model.options import Options, SETTINGS

    opts = Options(method="splines", resolution=256)   # validated here: InvalidParameterError
    opts = opts.replace(lam=1e-8)                       # a new, validated copy
    mesh = nkf_model.reconstruct(points, normals, options=opts)

:data:`SETTINGS` lists one :class:`Setting` per field of :class:`Options`, in the order a user
interface shows them. The data a run works on (points, normals, viewpoints, colours) and its
callbacks (progress, cancel) are arguments of :func:`nkf_model.reconstruct`, not settings.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InvalidParameterError

# The learned kernel's weights shipped in the package; ``weights=None`` means this file.
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "nkf_default.safetensors"


@dataclass(frozen=True)
class Choice:
    """One allowed value of a setting with choices: ``value`` as :class:`Options` takes it, the
    ``label`` a user interface shows and a one-line ``description`` (a tooltip)."""

    value: str
    label: str
    description: str


@dataclass(frozen=True)
class Setting:
    """What a setting is: ``kind`` one of ``"choice"``, ``"float"``, ``"int"``, ``"bool"``, ``"path"``;
    ``optional`` when ``None`` is allowed (and what it means is in ``description``); a hard range
    ``low``/``high`` (``low_open``, ``high_open``: that bound itself is excluded) and a ``soft_high``
    for sliders."""

    name: str
    kind: str
    default: Any
    label: str
    description: str
    choices: tuple[Choice, ...] = ()
    optional: bool = False
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    soft_high: float | None = None

    @property
    def values(self) -> tuple[str, ...]:
        return tuple(c.value for c in self.choices)


def _ranged(s: Setting) -> str:
    if s.low is not None and s.high is not None:
        return f"between {s.low:g} and {s.high:g}"
    return f">= {s.low:g}"


def _message(s: Setting, value, problem: str) -> str:
    """The one message for a bad value of ``s``; ``problem`` is ``"type"`` or ``"range"``."""
    custom = _MESSAGES.get(s.name)
    if custom is not None:
        return custom(value, problem)
    if s.kind == "choice":
        return f"{s.name} must be one of {', '.join(s.values)}; got {value!r}"
    if s.kind == "int":
        return f"{s.name} must be an integer {_ranged(s)}{' or None' if s.optional else ''}, got {value!r}"
    return f"{s.name} must be a number {_ranged(s)}{' or None' if s.optional else ''}, got {value!r}"


def _lam_message(value, problem):
    if problem == "type":
        return f"lambda must be a number, got {value!r}"
    return f"lambda must be a finite number >= 0, got {value!r}"


def _resolution_message(value, problem):
    if problem == "type":
        return f"resolution must be an integer, got {value!r}"
    return f"resolution must be between {MIN_RESOLUTION} and {MAX_RESOLUTION}, got {value}"


def _trim_message(value, problem):
    if problem == "type":
        return f"trim must be a number of point spacings (> 0) or None, got {value!r}"
    return f"trim must be a positive number of point spacings, or None to keep the closed surface; got {value!r}"


_MESSAGES = {
    "lam": _lam_message,
    "resolution": _resolution_message,
    "device": lambda v, p: f"device must be 'auto', 'cpu' or 'cuda', got {v!r}",
    "eps": lambda v, p: f"eps must be in (0, 0.1] of the bounding box, got {v!r}",
    "max_centres": lambda v, p: f"max_centres must be an integer >= 100, got {v!r}",
    "reduce_to": lambda v, p: f"reduce_to must be an integer >= 1000 or None, got {v!r}",
    "trim": _trim_message,
    "min_piece": lambda v, p: f"min_piece must be a fraction of the mesh's area in [0, 1), got {v!r}",
    "memory_budget": lambda v, p: f"memory_budget must be a positive number of bytes or None, got {v!r}",
    "max_points": lambda v, p: f"max_points must be an integer >= 10 or None (all points), got {v!r}",
}

MIN_RESOLUTION = 16
MAX_RESOLUTION = 1024
# Scans: trim the surface farther than SCAN_TRIM point spacings from every point and drop pieces
# under SCAN_MIN_PIECE of the area (docs/scans.md: chosen on the synthetic room scans).
SCAN_TRIM = 4.0
SCAN_MIN_PIECE = 0.002

METHOD_CHOICES = (
    Choice("splines", "Neural Splines", "The data-free Neural Spline kernel: no weights, runs everywhere"),
    Choice("nkf", "NKF", "Neural Kernel Field: the learned kernel (needs its trained weights)"),
)
DEVICE_CHOICES = (
    Choice("auto", "Auto", "A CUDA GPU when PyTorch sees one, else the CPU"),
    Choice("cpu", "CPU", "Always the CPU"),
    Choice("cuda", "GPU", "A CUDA GPU (needs the CUDA build of PyTorch)"),
)
NORMALS_CHOICES = (
    Choice("auto", "Auto", "The given normals when there are any, else estimate them"),
    Choice("given", "Given", "The given normals; an error without them"),
    Choice("estimate", "Estimate", "Estimate normals from the points (PCA over 16 neighbours), ignoring any given"),
)
ORIENTATION_CHOICES = (
    Choice("outward", "Outward", "Estimated normals point away from the object (closed objects seen from all around)"),
    Choice("up", "Up", "Estimated normals point upwards (terrain, aerial scans)"),
    Choice("viewpoint", "Viewpoint", "Estimated normals point towards the viewpoints (where the scanner was)"),
)
SOLVER_CHOICES = (
    Choice("auto", "Auto", "Exact up to max_centres constraints (3,000 points), then the partition of unity"),
    Choice("dense", "Dense", "One exact solve of all constraints"),
    Choice("falkon", "Falkon", "Nystrom centres with a preconditioned conjugate gradient"),
    Choice("pou", "Partition of Unity", "Small exact solves in overlapping patches, blended"),
)

# The default method is whichever passes the gate on held-out sources (docs/nkf.md, "The gate"): the
# learned kernel beats Neural Splines by at least 0.02 mean IoU at 300 and 1,000 points (clean and
# noisy) and on half surfaces of shapes from sources it never trained on, and is not behind at 3,000
# and 10,000 points. The weights file records that measurement in its metadata (``"gate"``: JSON
# with ``"passed": true`` and the split it was measured on); weights without the record, or with a
# failed one, leave Neural Splines the default. Read from the safetensors header with the standard
# library only (8 bytes of length, then JSON), so that deciding the default loads nothing heavy.
GATE_SPLIT = "sources"


def weights_gate(path) -> dict | None:
    """The gate record in the metadata of the weights file ``path`` (a dict), or None when the file
    is missing, unreadable or has none."""
    try:
        with open(path, "rb") as f:
            n = int.from_bytes(f.read(8), "little")
            if not 0 < n < 100_000_000:
                return None
            header = json.loads(f.read(n))
        gate = json.loads(header.get("__metadata__", {}).get("gate", "null"))
    except (OSError, ValueError, TypeError, AttributeError):
        return None
    return gate if isinstance(gate, dict) else None


def gate_passed(gate: dict | None) -> bool:
    """Whether a gate record says the weights passed on held-out sources."""
    return bool(gate) and gate.get("passed") is True and gate.get("split") == GATE_SPLIT


SHIPPED_GATE = weights_gate(SHIPPED_WEIGHTS)
DEFAULT_METHOD = "nkf" if SHIPPED_WEIGHTS.is_file() and gate_passed(SHIPPED_GATE) else "splines"
# Why the default is what it is, for the README, the command line and the Blender panel.
DEFAULT_METHOD_REASON = (
    "the shipped weights beat Neural Splines on shapes from sources they never trained on"
    if DEFAULT_METHOD == "nkf" else
    "Neural Splines is the default: the learned kernel has not yet beaten it by the gate's margin "
    "on shapes from sources it never trained on (docs/nkf.md)"
    if SHIPPED_WEIGHTS.is_file() else
    "Neural Splines is the default: this installation has no weights for the learned kernel"
)

SETTINGS: tuple[Setting, ...] = (
    Setting("method", "choice", DEFAULT_METHOD, "Method", f"Which kernel fits the surface ({DEFAULT_METHOD_REASON})",
            choices=METHOD_CHOICES),
    Setting("lam", "float", 1e-10, "Lambda",
            "Regularization (the paper's lambda) per constraint: 0 interpolates the points exactly, larger "
            "values give a smoother surface; 1e-12 to 1e-8 fit the points",
            low=0.0, soft_high=1e-3),
    Setting("resolution", "int", 128, "Resolution",
            "Grid cells along the longest side; higher gives finer detail and takes longer",
            low=MIN_RESOLUTION, high=MAX_RESOLUTION, soft_high=512),
    Setting("device", "choice", "auto", "Device", "Where the kernel runs", choices=DEVICE_CHOICES),
    Setting("max_points", "int", None, "Max Points",
            "Use a random subset (seeded) of at most this many points; None uses all",
            optional=True, low=10, soft_high=1_000_000),
    Setting("seed", "int", 0, "Seed", "Seed for the Max Points subset, Nystrom centres and thinned patches",
            low=0),
    Setting("normals_mode", "choice", "auto", "Normals", "Where the normals come from",
            choices=NORMALS_CHOICES),
    Setting("orientation", "choice", None, "Orientation",
            "Which way estimated normals point; None: towards the viewpoints when there are any, else outward",
            choices=ORIENTATION_CHOICES, optional=True),
    Setting("trim", "float", None, "Trim Distance",
            "Cut the surface farther than this many point spacings from every point (open scans); "
            "None keeps the closed surface",
            optional=True, low=0.0, low_open=True, soft_high=20.0),
    Setting("min_piece", "float", 0.0, "Min Piece",
            "Drop connected pieces with less than this fraction of the total area (0 keeps all)",
            low=0.0, high=1.0, high_open=True, soft_high=0.1),
    Setting("close", "bool", False, "Watertight",
            "Cap the surface where it runs into the bounding box (plus 5 %), so that the mesh is closed"),
    Setting("outliers", "bool", True, "Remove Outliers",
            "Drop points far sparser than the surface around them (scanner mixed pixels, stray returns) "
            "from inputs of 10,000 points or more"),
    Setting("balloon_check", "bool", True, "Check Learned Surface",
            "Learned kernel, up to 3,000 points: when its surface bulges far beyond the points (0.2 of their "
            "diagonal or more), fit the data-free kernel too and use it if it stays nearer"),
    Setting("reduce_to", "int", 300_000, "Reduce To",
            "Reduce larger inputs to at most this many points by voxel-grid averaging; None never reduces",
            optional=True, low=1000),
    Setting("solver", "choice", "auto", "Solver", "How the kernel weights are solved",
            choices=SOLVER_CHOICES),
    Setting("max_centres", "int", 6000, "Max Centres",
            "Largest exact solve, in constraints (2 per point); Falkon uses this many Nystrom centres",
            low=100),
    Setting("eps", "float", None, "Offset",
            "Offset of the constraints along the normals, as a fraction of the bounding box's longest side; "
            "None: 0.01 up to 3,000 points, then shrinking with the point spacing",
            optional=True, low=0.0, high=0.1, low_open=True),
    Setting("memory_budget", "float", None, "Memory Budget",
            "Bytes a run may use; None: 60 % of this machine's memory, at most 16 GiB",
            optional=True, low=0.0, low_open=True),
    Setting("weights", "path", None, "Weights",
            "Weights file (safetensors) of the learned kernel; None: the weights shipped in the package",
            optional=True),
)
SETTING = {s.name: s for s in SETTINGS}


def _check(s: Setting, value):
    """``value`` if it is valid for ``s`` (ints as int, numeric strings as float, other numbers as
    given), else InvalidParameterError."""
    if value is None:
        if s.optional:
            return None
        raise InvalidParameterError(_message(s, value, "type"))
    if s.kind == "choice":
        if value not in s.values:
            raise InvalidParameterError(_message(s, value, "range"))
        return value
    if s.kind == "bool":
        return bool(value)
    if s.kind == "path":
        if not isinstance(value, (str, os.PathLike)):
            raise InvalidParameterError(f"{s.name} must be a file path or None, got {value!r}")
        return value
    if s.kind == "int":
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise InvalidParameterError(_message(s, value, "type"))
        v = int(value)
    else:
        if isinstance(value, bool) or not isinstance(value, (numbers.Real, str)):
            raise InvalidParameterError(_message(s, value, "type"))
        try:  # numeric strings ("1e-8") too, as lambda always took them
            v = float(value)
        except ValueError:
            raise InvalidParameterError(_message(s, value, "type")) from None
        value = value if isinstance(value, numbers.Real) else v
        if not math.isfinite(v):
            raise InvalidParameterError(_message(s, value, "range"))
    if s.low is not None and (v < s.low or (s.low_open and v <= s.low)):
        raise InvalidParameterError(_message(s, value, "range"))
    if s.high is not None and (v > s.high or (s.high_open and v >= s.high)):
        raise InvalidParameterError(_message(s, value, "range"))
    return v if s.kind == "int" else value


@dataclass(frozen=True)
class Options:
    """The settings of one reconstruction, validated when made (:class:`InvalidParameterError`).

    Every field, its default and range is described by :data:`SETTINGS`; see
    :func:`nkf_model.reconstruct` for what each does. Make a changed copy with :meth:`replace`.
    """

    method: str = SETTING["method"].default
    lam: float = SETTING["lam"].default
    resolution: int = SETTING["resolution"].default
    device: str = SETTING["device"].default
    max_points: int | None = SETTING["max_points"].default
    seed: int = SETTING["seed"].default
    normals_mode: str = SETTING["normals_mode"].default
    orientation: str | None = SETTING["orientation"].default
    trim: float | None = SETTING["trim"].default
    min_piece: float = SETTING["min_piece"].default
    close: bool = SETTING["close"].default
    outliers: bool = SETTING["outliers"].default
    balloon_check: bool = SETTING["balloon_check"].default
    reduce_to: int | None = SETTING["reduce_to"].default
    solver: str = SETTING["solver"].default
    max_centres: int = SETTING["max_centres"].default
    eps: float | None = SETTING["eps"].default
    memory_budget: float | None = SETTING["memory_budget"].default
    weights: Any = field(default=SETTING["weights"].default)

    def __post_init__(self):
        for s in SETTINGS:
            object.__setattr__(self, s.name, _check(s, getattr(self, s.name)))

    @classmethod
    def build(cls, options: Options | None = None, **settings) -> Options:
        """``options`` (or the defaults) with ``settings`` applied; an unknown name is an
        :class:`InvalidParameterError` that lists the known ones."""
        unknown = sorted(set(settings) - set(SETTING))
        if unknown:
            raise InvalidParameterError(
                f"unknown setting {', '.join(unknown)}; the settings are {', '.join(SETTING)}"
            )
        if options is None:
            return cls(**settings)
        if not isinstance(options, Options):
            raise InvalidParameterError(f"options must be an nkf_model.Options, got {type(options).__name__}")
        return options.replace(**settings) if settings else options

    def replace(self, **changes) -> Options:
        """A validated copy with ``changes`` applied."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """The settings as a plain dict (field name -> value)."""
        return {s.name: getattr(self, s.name) for s in SETTINGS}

    @property
    def scan(self) -> bool:
        """Whether the surface is cleaned as an open scan (trimmed or small pieces dropped)."""
        return self.trim is not None or self.min_piece > 0


def scan_preset(options: Options | None = None) -> Options:
    """``options`` with the open-scan clean-up (:data:`SCAN_TRIM`, :data:`SCAN_MIN_PIECE`)."""
    return Options.build(options, trim=SCAN_TRIM, min_piece=SCAN_MIN_PIECE)
