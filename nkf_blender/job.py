"""One reconstruction, run on a worker thread or synchronously. No ``bpy`` here.

The worker sees only NumPy arrays, a progress callback and a ``threading.Event``; Blender's main
thread starts the job, polls :attr:`ReconstructJob.state` and :attr:`ReconstructJob.progress`
from a timer, and builds the mesh from :attr:`ReconstructJob.result` once the state is ``"done"``.
"""

from __future__ import annotations

import threading
import time
import traceback

from nkf_model.options import Options
from nkf_model.pipeline.stages import STAGE_LABELS

from .devices import describe as describe_device
from .import_failure import explain as explain_import_failure

__all__ = ["ReconstructJob", "STAGE_LABELS", "PENDING", "RUNNING", "DONE", "FAILED", "CANCELLED"]

PENDING, RUNNING, DONE, FAILED, CANCELLED = "pending", "running", "done", "failed", "cancelled"


class ReconstructJob:
    """Reconstruct a mesh from ``points`` (N, 3) and ``normals`` (N, 3) or ``None``, float32 or float64,
    with the settings ``options`` (an :class:`nkf_model.options.Options`).

    ``colors`` (N, 3) uint8 sRGB or ``None`` (carried onto the mesh when given); ``viewpoints``
    (K, 3) scanner positions in the frame of ``points`` (for ``orientation="viewpoint"``) or
    ``None``. With ``normals=None`` (``normals_mode`` "auto") or ``normals_mode="estimate"`` the
    normals are estimated, oriented by ``options.orientation``. ``options.max_points`` takes a
    seeded random subset inside :func:`nkf_model.reconstruct`; ``points_used`` says how many
    points it fitted (and, before the run ends, how many it will).

    Use ``start()`` to run on a daemon worker thread, or ``run()`` to run in the calling thread.
    ``on_progress(fraction, stage)``, if given, is called from the thread that runs the work.
    Afterwards ``state`` is ``"done"`` (``result`` holds the ``nkf_model.Mesh``), ``"failed"``
    (``error`` holds one line for the user), or ``"cancelled"``.
    """

    def __init__(self, points, normals, options: Options, on_progress=None, *, colors=None, viewpoints=None,
                 fit=None, keep_fit: bool = False):
        if not isinstance(options, Options):
            raise TypeError(f"options must be an nkf_model.options.Options, got {type(options).__name__}")
        self.points = points
        self.normals = normals
        self.colors = colors
        self.viewpoints = viewpoints
        self.options = options
        # A kept nkf_model.Fit of these points and fit settings (nkf_blender.fitcache): the job only
        # re-solves for Lambda and re-meshes. ``keep_fit``: make one (nkf_model.fit) and leave it in
        # ``self.fit`` for the cache. ``reused`` says whether a kept fit was used.
        self.fit = fit
        self.keep_fit = keep_fit
        self.reused = fit is not None
        self._listener = on_progress
        self.cancel_event = threading.Event()
        self._lock = threading.Lock()
        self._fraction = 0.0
        self._stage = "start"
        self.state = PENDING
        self.result = None
        self.error: str | None = None
        self.notes: list[str] = []
        self.device = ""  # which device ran it, in words (nkf_blender.devices), once done
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
        opts = self.options
        estimate = opts.normals_mode == "estimate" or (opts.normals_mode == "auto" and self.normals is None)
        n = len(self.points)
        self.points_used = n if opts.max_points is None else min(n, opts.max_points)
        try:
            import nkf_model

            # The points were read for the normals mode already: say which normals these are, and
            # orient only estimated ones (an orientation would otherwise ask for viewpoints).
            run = opts.replace(
                normals_mode="estimate" if estimate else opts.normals_mode,
                orientation=opts.orientation if estimate else None,
            )
            if self.fit is not None or self.keep_fit:
                mesh = self._fit_and_mesh(nkf_model, run, estimate)
            else:
                mesh = nkf_model.reconstruct(
                    self.points, None if estimate else self.normals, options=run,
                    progress=self._on_progress, cancel=self.cancel_event, colors=self.colors,
                    viewpoints=self.viewpoints if estimate else None,
                )
            subset = mesh.stats.get("subset")
            if subset:
                self.points_used = int(subset["to"])
                self.notes.append(f"used a random {subset['to']:,} of {subset['from']:,} points (Max Points)")
            else:
                self.points_used = n
            self.notes.extend(mesh.stats.get("warnings", []))
            self.device = describe_device(mesh.stats)
            if estimate:
                rule = run.orientation or ("viewpoint" if self.viewpoints is not None else "outward")
                self.notes.append(f"normals estimated (oriented {rule})")
            if self.cancel_event.is_set():
                self.state = CANCELLED
            else:
                self.result = mesh
                self.state = DONE
        except Exception as exc:
            self._fail(exc)
        finally:
            self.t_end = time.perf_counter()

    def _fit_and_mesh(self, nkf_model, run: Options, estimate: bool):
        """``nkf_model.fit`` (or the kept fit, re-solved for ``run.lam``) then ``Fit.mesh``: the
        same mesh as ``nkf_model.reconstruct`` with these settings."""
        f = self.fit
        share = 0.6 if f is None else (0.3 if f.lam != run.lam else 0.0)

        def part(lo, width):
            def report(fr, st):
                if st != "done":  # the end of a part is not the end of the job
                    self._on_progress(lo + width * fr, st)

            return report

        if f is None:
            f = nkf_model.fit(
                self.points, None if estimate else self.normals, options=run, progress=part(0.0, share),
                cancel=self.cancel_event, colors=self.colors, viewpoints=self.viewpoints if estimate else None,
            )
            self.fit = f
        elif f.lam != run.lam:
            f = f.with_lam(run.lam, progress=part(0.0, share), cancel=self.cancel_event)
        mesh = f.mesh(resolution=run.resolution, close=run.close, trim=run.trim, min_piece=run.min_piece,
                      progress=part(share, 1.0 - share), cancel=self.cancel_event)
        self._on_progress(1.0, "done")
        return mesh

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
        if user_error and isinstance(exc.__cause__, ImportError):  # e.g. the GPU asked for, PyTorch broken
            self.error = f"{str(exc).split(' (', 1)[0]}: {explain_import_failure(exc.__cause__)}"
        elif user_error:
            self.error = str(exc)
        elif isinstance(exc, ImportError):  # which package, from which folder, and what to do
            self.error = explain_import_failure(exc)
        elif isinstance(exc, MemoryError):
            self.error = "out of memory: lower Resolution or Max Points, or set a Memory Budget in the preferences"
        else:
            traceback.print_exc()
            self.error = f"unexpected error ({type(exc).__name__}: {exc}); see the system console"
        self.state = FAILED
