"""Progress reporting and cooperative cancellation shared by every stage.

A :class:`Tracker` maps each stage onto a slice of the overall fraction ``[0, 1]``, forwards
``progress(fraction, stage)`` to the caller, and raises :class:`~nkf_model.errors.Cancelled`
when the caller's ``threading.Event`` is set. Stages call :meth:`Tracker.step` between chunks of
work, and each chunk is sized to take well under 0.5 s on a slow CPU.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from ..errors import Cancelled
from .stages import STAGE_WEIGHTS

ProgressFn = Callable[[float, str], None]

class Tracker:
    """Tracks the current stage, reports progress and checks for cancellation.

    Parameters
    ----------
    progress:
        ``progress(fraction, stage)`` callback, or ``None``. ``fraction`` is in ``[0, 1]`` and
        never decreases; ``stage`` is one of the keys of :data:`nkf_model.pipeline.stages.STAGES`.
    cancel:
        Any object with ``is_set() -> bool`` (normally ``threading.Event``), or ``None``.
    stages:
        The stages this run goes through, in order.
    """

    def __init__(self, progress: ProgressFn | None = None, cancel=None, stages=None):
        self._progress = progress
        self._cancel = cancel
        stages = list(stages or ("normalise", "augment", "solve", "evaluate", "mesh"))
        total = sum(STAGE_WEIGHTS[s] for s in stages)
        self._start = {}
        self._width = {}
        acc = 0.0
        for s in stages:
            self._start[s] = acc / total
            self._width[s] = STAGE_WEIGHTS[s] / total
            acc += STAGE_WEIGHTS[s]
        self._stage = stages[0]
        self._last = 0.0
        self.timings: dict[str, float] = {}
        self._t0 = time.perf_counter()

    def cancel_poll(self) -> None:
        """Raise :class:`Cancelled` if the cancel event is set."""
        if self._cancel is not None and self._cancel.is_set():
            raise Cancelled("reconstruction cancelled")

    def begin(self, stage: str) -> None:
        """Start ``stage``: closes the timing of the previous one and reports its start."""
        self._close()
        self._stage = stage
        self._t0 = time.perf_counter()
        self.step(0.0)

    def step(self, local_fraction: float) -> None:
        """Report that the current stage is ``local_fraction`` done, then check for cancel."""
        self.cancel_poll()
        lf = min(max(float(local_fraction), 0.0), 1.0)
        frac = self._start[self._stage] + self._width[self._stage] * lf
        frac = max(frac, self._last)
        self._last = frac
        if self._progress is not None:
            self._progress(frac, self._stage)

    def finish(self) -> None:
        """Close the last stage and report 1.0."""
        self._close()
        self._last = 1.0
        if self._progress is not None:
            self._progress(1.0, "done")

    def _close(self) -> None:
        if self._stage is not None:
            self.timings[self._stage] = self.timings.get(self._stage, 0.0) + (
                time.perf_counter() - self._t0
            )
