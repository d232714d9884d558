"""Background steps after enabling: the first-time preparation, and a short load step in later
sessions. No ``bpy``.

**First-time preparation.** A fresh installation's first reconstruction would otherwise spend most
of its time compiling (numba caches the machine code beside the bundled modules, so only the first
run pays). After the add-on is enabled in the UI, :func:`start` runs
:func:`nkf_model.pipeline.warmup.warm_up` on a worker thread, then writes the bytecode of the
extension's bundled packages (:func:`compile_bundled`: Blender unpacks the wheels without it, and a
Python run with ``PYTHONDONTWRITEBYTECODE`` never writes it); the panel shows "Preparing the solver
(first time only)" with its progress. A marker file in the extension's user folder remembers that
it is done for this version of ``nkf_model``, numba and Python.

**Load step.** When the marker says the installation is prepared, :func:`start` runs only the
short version (:data:`~nkf_model.pipeline.warmup.LOAD_STEPS`, two 600-point exact solves, a few
seconds): it imports the solver and sets up numba's tables, which a later session's first
reconstruction would otherwise pay for (1.2 to 1.9 times a warm run without it, 0.8 to 1.3 with
it; docs/blender-user.md). The panel shows "Loading the solver".

A reconstruction started while either runs proceeds: the background step gives way at its next
check, as soon as a reconstruction thread is alive (:class:`_GiveWay`; the add-on's timer also
cancels it through :func:`cancel`), so that two threads do not run numba's parallel loops at once (its
``workqueue`` threading layer, the one used where OpenMP is missing, aborts the process on
concurrent launches). Imports are thread-safe, so the job simply uses what the step has loaded.

Faults end in :func:`status` (``state`` "failed" with one line in ``error``), never in an
exception on Blender's side: a read-only folder (no marker, no bytecode, a note in ``note``;
numba falls back to its user-wide cache), a missing or broken package, or disabling the add-on
meanwhile (:func:`stop` cancels between and inside the steps and joins the thread).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from .import_failure import bundled_folder, explain

IDLE, RUNNING, DONE, FAILED, CANCELLED = "idle", "running", "done", "failed", "cancelled"
PREPARE, LOAD = "prepare", "load"  # Status.kind: the first-time preparation, or the short load step
MARKER = "prepared.txt"
THREAD_NAME = "nkf-prepare"
# Worker threads of the add-on that run the solver: the background step gives way to them.
SOLVER_THREADS = ("nkf-reconstruct", "nkf-factorize")
# Share of the first-time preparation's progress bar taken by compiling the kernels; the rest is
# writing the bundled packages' bytecode (bpy 5.0.1, linux zip: 16.6 s of 103.7 s, 2,087 files).
WARM_UP_SHARE = 0.85


@dataclass(frozen=True)
class Status:
    state: str = IDLE
    fraction: float = 0.0
    label: str = ""
    error: str = ""
    seconds: float = 0.0
    kind: str = PREPARE
    note: str = ""  # what was skipped without failing (the bytecode of a read-only folder)


_lock = threading.Lock()
_status = Status()
_thread: threading.Thread | None = None
_cancel = threading.Event()


class _GiveWay:
    """The cancel "event" handed to the solver: set by :func:`cancel` / :func:`stop`, and seen as
    set while one of the add-on's solver threads runs (a reconstruction started meanwhile), so the
    background step stops at its next check instead of at the add-on timer's next tick."""

    def is_set(self) -> bool:
        if _cancel.is_set():
            return True
        return any(t.name in SOLVER_THREADS and t.is_alive() for t in threading.enumerate())


_give_way = _GiveWay()


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


def blender_wheel_folder(user_folder) -> Path | None:
    """Where Blender unpacks the extensions' wheels, found from this extension's user folder
    ``<extensions>/.user/<repo>/<id>/cache`` (``bpy.utils.extension_path_user``):
    ``<extensions>/.local/lib/pythonX.Y/site-packages`` (``addon_utils``); None when the folder is
    not laid out so."""
    if user_folder is None:
        return None
    p = Path(user_folder)
    if len(p.parents) < 4 or p.parents[2].name != ".user":
        return None
    return p.parents[3] / ".local" / "lib" / "python{}.{}".format(*sys.version_info[:2]) / "site-packages"


def bundled_files(ext_dir=None, paths=None) -> tuple[Path | None, list[Path]]:
    """The folder Blender unpacked this extension's wheels into
    (:func:`~.import_failure.bundled_folder`: the first of ``paths``, default ``sys.path``, that holds
    the ``.dist-info`` of a wheel listed in the extension's manifest, editable installs left out) and
    the ``.py`` files those wheels put there (from their ``RECORD``: the top-level packages, walked,
    and modules); ``(None, [])`` when there is none (no manifest, no wheels)."""
    folder, infos = bundled_folder(ext_dir, paths)
    if folder is None:
        return None, []
    return folder, _files_of(folder, infos)


def _files_of(folder: Path, infos) -> list[Path]:
    tops = set()
    for info in infos:
        try:
            rows = (info / "RECORD").read_text().splitlines()
        except OSError:
            continue
        for row in rows:
            first = row.split(",", 1)[0].replace("\\", "/").split("/", 1)[0]
            if first and first != ".." and not first.endswith((".dist-info", ".data")) and first != "__pycache__":
                tops.add(first)
    files = []
    for top in sorted(tops):
        path = folder / top
        if path.is_dir():
            for root, dirs, names in os.walk(path):
                dirs[:] = sorted(d for d in dirs if d != "__pycache__")
                files.extend(Path(root) / n for n in sorted(names) if n.endswith(".py"))
        elif path.suffix == ".py" and path.is_file():
            files.append(path)
    return files


def compile_bundled(progress=None, cancel=None, ext_dir=None, paths=None) -> str:
    """Write the bytecode of the extension's bundled packages (:func:`bundled_files`) where it is
    missing or stale, quietly; return a note ("" when all was written). A read-only folder is not
    an error: the note says so and nothing is written. ``progress(fraction, label)``; ``cancel``
    (``is_set()``) raises :class:`nkf_model.Cancelled` between files."""
    import compileall

    folder, files = bundled_files(ext_dir, paths)
    if folder is None:
        return "no bundled packages found: bytecode not written"
    if not os.access(folder, os.W_OK):
        return f"{folder} is read-only: bytecode not written"
    failed = []
    for k, path in enumerate(files):
        if cancel is not None and cancel.is_set():
            from nkf_model import Cancelled

            raise Cancelled("the preparation was cancelled")
        if progress is not None and k % 50 == 0:
            progress(k / len(files), f"bytecode {k:,} of {len(files):,} files")
        try:
            ok = compileall.compile_file(str(path), quiet=2)
        except Exception:  # compile_file reports OSError and syntax errors itself; anything else too
            ok = False
        if not ok:
            failed.append(path)
    if progress is not None:
        progress(1.0, "bytecode written")
    if failed:
        return (f"bytecode not written for {len(failed):,} of {len(files):,} files in {folder} "
                f"(first: {failed[0].relative_to(folder)})")
    return ""


def _work(folder, kind: str) -> None:
    t0 = time.perf_counter()
    note = ""
    try:
        from nkf_model.pipeline.warmup import LOAD_STEPS, warm_up

        if kind == LOAD:
            warm_up(progress=lambda f, label: _set(fraction=float(f), label=label), cancel=_give_way,
                    steps=LOAD_STEPS)
        else:
            warm_up(progress=lambda f, label: _set(fraction=WARM_UP_SHARE * float(f), label=label),
                    cancel=_give_way)
            where = blender_wheel_folder(folder)
            note = compile_bundled(
                progress=lambda f, label: _set(fraction=WARM_UP_SHARE + (1 - WARM_UP_SHARE) * float(f), label=label),
                cancel=_give_way, paths=None if where is None else [str(where), *sys.path])
            if note:
                print(f"NKF: {note}")
    except Exception as exc:  # one line for the panel; Blender keeps working
        if type(exc).__name__ == "Cancelled":
            _set(state=CANCELLED, seconds=time.perf_counter() - t0)
        elif isinstance(exc, ImportError):  # which package, from which folder, and what to do
            _set(state=FAILED, error=explain(exc), seconds=time.perf_counter() - t0)
        else:
            _set(state=FAILED, error=f"{type(exc).__name__}: {exc}".splitlines()[0],
                 seconds=time.perf_counter() - t0)
        return
    if kind == PREPARE and folder is not None:
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            (Path(folder) / MARKER).write_text(_key() + "\n")
        except OSError:
            pass  # read-only user folder: it is prepared again next session (from numba's cache)
    _set(state=DONE, fraction=1.0, label="done", note=note, seconds=time.perf_counter() - t0)


def start(folder=None, force: bool = False, load: bool = True) -> bool:
    """Start the first-time preparation on a worker thread, or, when the marker in ``folder`` says
    this installation is prepared (and not ``force``), the short load step (unless ``load`` is
    False); nothing while one runs. Returns True when a thread was started."""
    global _thread
    if _thread is not None and _thread.is_alive():
        return False
    kind = PREPARE
    if not force and is_prepared(folder):
        if not load:
            _set(state=DONE, fraction=1.0, label="done")
            return False
        kind = LOAD
    _cancel.clear()
    _set(state=RUNNING, kind=kind, fraction=0.0, label="starting", error="", note="", seconds=0.0)
    _thread = threading.Thread(target=_work, args=(folder, kind), name=THREAD_NAME, daemon=True)
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
    """Ask the background step to stop at its next check (within about half a second), without
    waiting."""
    _cancel.set()


def stop(timeout: float = 30.0) -> bool:
    """Cancel and join (add-on disabled); True when no thread is left running."""
    _cancel.set()
    return wait(timeout)


def running() -> bool:
    return status().state == RUNNING
