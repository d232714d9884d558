"""First-time preparation: compile the solver's numba kernels once, in the background. No ``bpy``.

A fresh installation's first reconstruction would otherwise spend most of its time compiling
(numba caches the machine code beside the bundled modules, so only the first run pays). After the
add-on is enabled in the UI, :func:`start` runs :func:`nkf_model.pipeline.warmup.warm_up` on a
worker thread; the panel shows "Preparing the solver (first time only)" with its progress. A marker
file in the extension's user folder remembers that it is done for this version of ``nkf_model``,
numba and Python, so later Blender sessions skip it. A reconstruction started meanwhile simply
waits for the compiler (numba's compile lock); the add-on then cancels the preparation
(:func:`cancel`), so that two threads do not run numba's parallel loops at once (its ``workqueue``
threading layer, the one used where OpenMP is missing, aborts the process on concurrent launches).

Faults end in :func:`status` (``state`` "failed" with one line in ``error``), never in an
exception on Blender's side: a read-only folder (no marker; numba falls back to its user-wide
cache), a missing or broken package, or disabling the add-on meanwhile (:func:`stop` cancels
between and inside the steps and joins the thread).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

IDLE, RUNNING, DONE, FAILED, CANCELLED = "idle", "running", "done", "failed", "cancelled"
MARKER = "prepared.txt"
THREAD_NAME = "nkf-prepare"


@dataclass(frozen=True)
class Status:
    state: str = IDLE
    fraction: float = 0.0
    label: str = ""
    error: str = ""
    seconds: float = 0.0


_lock = threading.Lock()
_status = Status()
_thread: threading.Thread | None = None
_cancel = threading.Event()


def _key() -> str:
    """What the compiled code depends on: nkf_model's and numba's versions, and Python's."""
    try:
        from importlib.metadata import version

        parts = [f"nkf_model {version('nkf-model')}", f"numba {version('numba')}"]
    except Exception:  # metadata missing: prepare every session rather than never
        parts = ["unknown"]
    return "; ".join(parts + [f"python {sys.version.split()[0]}"])


def _set(**kw) -> None:
    global _status
    with _lock:
        _status = Status(**{**_status.__dict__, **kw})


def status() -> Status:
    with _lock:
        return _status


def is_prepared(folder) -> bool:
    """True when the marker in ``folder`` says this installation was prepared."""
    if folder is None:
        return False
    try:
        return (Path(folder) / MARKER).read_text().strip() == _key()
    except OSError:
        return False


def _work(folder) -> None:
    t0 = time.perf_counter()
    try:
        from nkf_model import Cancelled
        from nkf_model.pipeline.warmup import warm_up

        warm_up(progress=lambda f, label: _set(fraction=float(f), label=label), cancel=_cancel)
    except Cancelled:
        _set(state=CANCELLED, seconds=time.perf_counter() - t0)
        return
    except Exception as exc:  # one line for the panel; Blender keeps working
        _set(state=FAILED, error=f"{type(exc).__name__}: {exc}".splitlines()[0],
             seconds=time.perf_counter() - t0)
        return
    if folder is not None:
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            (Path(folder) / MARKER).write_text(_key() + "\n")
        except OSError:
            pass  # read-only user folder: it is prepared again next session (from numba's cache)
    _set(state=DONE, fraction=1.0, label="done", seconds=time.perf_counter() - t0)


def start(folder=None, force: bool = False) -> bool:
    """Start the preparation on a worker thread unless it ran (marker in ``folder``) or runs now.
    Returns True when a thread was started."""
    global _thread
    if _thread is not None and _thread.is_alive():
        return False
    if not force and is_prepared(folder):
        _set(state=DONE, fraction=1.0, label="done")
        return False
    _cancel.clear()
    _set(state=RUNNING, fraction=0.0, label="starting", error="", seconds=0.0)
    _thread = threading.Thread(target=_work, args=(folder,), name=THREAD_NAME, daemon=True)
    _thread.start()
    return True


def wait(timeout: float | None = None) -> bool:
    """Wait for the thread; True when it is not running (any more)."""
    t = _thread
    if t is not None:
        t.join(timeout)
        return not t.is_alive()
    return True


def cancel() -> None:
    """Ask the preparation to stop at its next check (within about half a second), without waiting."""
    _cancel.set()


def stop(timeout: float = 30.0) -> bool:
    """Cancel and join (add-on disabled); True when no thread is left running."""
    _cancel.set()
    return wait(timeout)


def running() -> bool:
    return status().state == RUNNING
