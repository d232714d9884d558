"""One reconstruction, run on a worker thread or synchronously. No ``bpy`` here.

The worker sees only NumPy arrays, a progress callback and a ``threading.Event``; Blender's main
thread starts the job, polls :attr:`ReconstructJob.state` and :attr:`ReconstructJob.progress`
from a timer, and builds the mesh from :attr:`ReconstructJob.result` once the state is ``"done"``.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass

import numpy as np

PENDING, RUNNING, DONE, FAILED, CANCELLED = "pending", "running", "done", "failed", "cancelled"
STAGE_LABELS = {
    "start": "Starting",
    "subsample": "Subsampling",
    "normalise": "Normalising",
    "reduce": "Reducing",
    "normals": "Estimating normals",
    "augment": "Augmenting",
    "features": "Features",
    "solve": "Solving",
    "evaluate": "Evaluating",
    "mesh": "Meshing",
    "clean": "Trimming",
    "colors": "Colours",
    "done": "Done",
}


# The scan defaults of nkf_model.surface.trim (SCAN_TRIM, SCAN_MIN_PIECE), repeated here so that the
# add-on registers even when nkf_model's dependencies are missing; a test keeps them equal.
SCAN_TRIM = 4.0
SCAN_MIN_PIECE = 0.002
NORMALS_MODES = ("auto", "given", "estimate")
ORIENTATIONS = ("outward", "up", "viewpoint")


@dataclass(frozen=True)
class Settings:
    """What to run, in nkf_model's terms.

    ``method`` ``"nkf"`` or ``"splines"``; ``lam`` >= 0; ``resolution`` grid cells per side;
    ``max_points`` cap on the points used (a seeded random subset above it, 0 = no cap);
    ``device`` ``"auto"``, ``"cpu"`` or ``"cuda"``.

    Scans: ``normals_mode`` ``"auto"`` (the object's normals when it has them, else estimated),
    ``"given"`` (the object must have normals) or ``"estimate"`` (always estimated);
    ``orientation`` of estimated normals, ``"outward"``, ``"up"`` or ``"viewpoint"`` (towards the
    scene camera); ``trim`` point spacings beyond which the surface is cut (``None``: closed
    surface); ``min_piece`` smallest piece kept, as a fraction of the area (0 keeps all);
    ``close`` caps the surface at the grid's bounds (a watertight mesh);
    ``colors`` carry the object's point colours onto the mesh; ``memory_budget`` bytes a run may
    use (``None``: nkf_model's default, 60 % of the memory, at most 16 GiB).
    """

    method: str = "splines"
    lam: float = 1e-10
    resolution: int = 128
    max_points: int = 0
    device: str = "auto"
    seed: int = 0
    normals_mode: str = "auto"
    orientation: str = "outward"
    trim: float | None = None
    min_piece: float = 0.0
    close: bool = False
    colors: bool = True
    memory_budget: int | None = None


def subsample(points: np.ndarray, normals, max_points: int, seed: int = 0, colors=None):
    """At most ``max_points`` rows, chosen at random with ``seed`` and kept in their order.

    ``normals`` and ``colors`` (either may be ``None``) are indexed like ``points``. Returns
    ``(points, normals, colors)``.
    """
    n = len(points)
    if not max_points or n <= max_points:
        return points, normals, colors
    idx = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
    return points[idx], None if normals is None else normals[idx], None if colors is None else colors[idx]


class ReconstructJob:
    """Reconstruct a mesh from ``points`` (N, 3) and ``normals`` (N, 3) or ``None``, float32 or float64.

    ``colors`` (N, 3) uint8 sRGB or ``None``; ``viewpoints`` (K, 3) scanner positions in the frame
    of ``points`` (for ``orientation="viewpoint"``) or ``None``. With ``normals=None`` the normals
    are estimated (``settings.orientation``).

    Use ``start()`` to run on a daemon worker thread, or ``run()`` to run in the calling thread.
    ``on_progress(fraction, stage)``, if given, is called from the thread that runs the work.
    Afterwards ``state`` is ``"done"`` (``result`` holds the ``nkf_model.Mesh``), ``"failed"``
    (``error`` holds one line for the user), or ``"cancelled"``.
    """

    def __init__(self, points, normals, settings: Settings, on_progress=None, *, colors=None, viewpoints=None):
        self.points = points
        self.normals = normals
        self.colors = colors
        self.viewpoints = viewpoints
        self.settings = settings
        self._listener = on_progress
        self.cancel_event = threading.Event()
        self._lock = threading.Lock()
        self._fraction = 0.0
        self._stage = "start"
        self.state = PENDING
        self.result = None
        self.error: str | None = None
        self.notes: list[str] = []
        self.points_used = 0
        self.thread: threading.Thread | None = None
        self.t_start = 0.0
        self.t_end: float | None = None

    # -- main thread -------------------------------------------------------------------------
    def start(self) -> ReconstructJob:
        """Run on a new worker thread and return at once."""
        if self.state != PENDING:
            raise RuntimeError("a job runs only once")
        self.state = RUNNING
        self.t_start = time.perf_counter()
        self.thread = threading.Thread(target=self._work, name="nkf-reconstruct", daemon=True)
        self.thread.start()
        return self

    def run(self) -> ReconstructJob:
        """Run in the calling thread (headless Blender) and return when finished."""
        if self.state != PENDING:
            raise RuntimeError("a job runs only once")
        self.state = RUNNING
        self.t_start = time.perf_counter()
        self._work()
        return self

    def cancel(self) -> None:
        """Ask the worker to stop; it does within about half a second."""
        self.cancel_event.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the worker thread; True if it is no longer alive."""
        if self.thread is not None:
            self.thread.join(timeout)
            return not self.thread.is_alive()
        return True

    @property
    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive()

    @property
    def finished(self) -> bool:
        """True once the work has ended (and the worker thread has returned)."""
        return self.state in (DONE, FAILED, CANCELLED) and not self.alive

    @property
    def progress(self) -> tuple[float, str]:
        """``(fraction in [0, 1], stage)``; stage is a key of :data:`STAGE_LABELS`."""
        with self._lock:
            return self._fraction, self._stage

    @property
    def stage_label(self) -> str:
        frac, stage = self.progress
        return STAGE_LABELS.get(stage, stage.capitalize())

    @property
    def elapsed(self) -> float:
        if not self.t_start:
            return 0.0
        return (self.t_end or time.perf_counter()) - self.t_start

    # -- worker ------------------------------------------------------------------------------
    def _on_progress(self, fraction: float, stage: str) -> None:
        with self._lock:
            self._fraction = float(fraction)
            self._stage = stage
        if self._listener is not None:
            self._listener(float(fraction), stage)

    def _work(self) -> None:
        s = self.settings
        try:
            import nkf_model

            self._on_progress(0.0, "subsample")
            pts, nrm, rgb = subsample(self.points, self.normals, s.max_points, s.seed, self.colors)
            self.points_used = len(pts)
            if len(pts) < len(self.points):
                self.notes.append(f"used a random {len(pts):,} of {len(self.points):,} points (Max Points)")
            estimate = nrm is None
            mesh = nkf_model.reconstruct(
                pts, nrm, method=s.method, lam=s.lam, resolution=s.resolution, device=s.device,
                progress=self._on_progress, cancel=self.cancel_event, seed=s.seed,
                normals_mode="estimate" if estimate else "given",
                orientation=s.orientation if estimate else None,
                viewpoints=self.viewpoints if estimate and s.orientation == "viewpoint" else None,
                colors=rgb if s.colors else None, trim=s.trim, min_piece=s.min_piece, close=s.close,
                memory_budget=s.memory_budget,
            )
            self.notes.extend(mesh.stats.get("warnings", []))
            if estimate:
                self.notes.append(f"normals estimated (oriented {s.orientation})")
            if self.cancel_event.is_set():
                self.state = CANCELLED
            else:
                self.result = mesh
                self.state = DONE
        except Exception as exc:
            self._fail(exc)
        finally:
            self.t_end = time.perf_counter()

    def _fail(self, exc: Exception) -> None:
        try:
            import nkf_model

            cancelled = isinstance(exc, nkf_model.Cancelled)
            user_error = isinstance(exc, nkf_model.NKFInputError)
        except ImportError:
            cancelled, user_error = False, False
        if cancelled or self.cancel_event.is_set():
            self.state = CANCELLED
            return
        if user_error:
            self.error = str(exc)
        elif isinstance(exc, ImportError):
            self.error = (
                f"a Python package is missing ({exc}); install the dependencies in the add-on preferences"
            )
        elif isinstance(exc, MemoryError):
            self.error = "out of memory: lower Resolution or Max Points, or set a Memory Budget in the preferences"
        else:
            traceback.print_exc()
            self.error = f"unexpected error ({type(exc).__name__}: {exc}); see the system console"
        self.state = FAILED
