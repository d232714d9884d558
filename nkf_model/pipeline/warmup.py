"""Compile the CPU path's numba kernels ahead of the first real reconstruction.

numba compiles each kernel the first time it runs, which makes a fresh installation's first
reconstruction several times slower than later ones; with ``cache=True`` the machine code is then
stored beside the modules (``__pycache__``) and later processes load it. :func:`warm_up` runs small
synthetic reconstructions through every CPU code path (the exact solve, the partition of unity,
Neural Splines and NKF, estimated normals, trimming, colours) so that all of it is compiled and
cached once, for example in the background right after a Blender extension is installed.
:data:`LOAD_STEPS` (the two small exact solves) is the short version for a process whose kernels
are already cached: it imports the solver and sets up numba's tables (a few seconds), so that
the first real reconstruction of the session does not pay for that.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ..errors import Cancelled
from .reconstruct import reconstruct

# (label, points, settings): small inputs that reach every compiled kernel of the CPU path.
# Above 3,000 points the solver is the partition of unity (its own kernels).
STEPS = (
    ("exact solve, Neural Splines", 600, dict(method="splines")),
    ("exact solve, NKF", 600, dict(method="nkf")),
    ("partition of unity", 3_400, dict(method="splines")),
    ("estimated normals, trimming, colours", 800, dict(method="splines", normals_mode="estimate", trim=4.0,
                                                      min_piece=0.002)),
)

# The short "load" version: the exact solves only (imports, numba's tables, the cached kernels they use).
LOAD_STEPS = ("exact solve, Neural Splines", "exact solve, NKF")


def _sphere(n: int):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    d = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return d * 0.5, d


def warm_up(progress=None, cancel: threading.Event | None = None, methods=("splines", "nkf"), steps=None) -> dict:
    """Run :data:`STEPS` (those whose method is in ``methods`` and, when ``steps`` is given, whose
    label is in it, e.g. :data:`LOAD_STEPS`) on the CPU; return seconds per step.

    ``progress(fraction, label)`` is called before each step and at the end; ``cancel`` (an Event)
    stops it between steps and inside them (raises :class:`~nkf_model.errors.Cancelled`).
    """
    chosen = [s for s in STEPS if s[2]["method"] in methods and (steps is None or s[0] in steps)]
    seconds = {}
    for k, (label, n, settings) in enumerate(chosen):
        if cancel is not None and cancel.is_set():
            raise Cancelled("the preparation was cancelled")
        if progress is not None:
            progress(k / len(chosen), label)
        pts, nrm = _sphere(n)
        colors = np.tile(np.array([[200, 120, 40]], np.uint8), (n, 1)) if "trim" in settings else None
        t0 = time.perf_counter()
        reconstruct(pts, nrm, resolution=32, device="cpu", cancel=cancel, colors=colors, **settings)
        seconds[label] = time.perf_counter() - t0
    if progress is not None:
        progress(1.0, "done")
    return seconds
