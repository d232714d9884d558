"""Install the heavy Python dependencies into a folder with pip, without blocking Blender.

No ``bpy`` here: the preferences start a :class:`PipJob`, poll it from a timer on the main thread,
and call :meth:`PipJob.finish` once it has ended. pip runs as a subprocess
(``sys.executable -m pip install --target FOLDER ...``); a reader thread collects its output so the
UI can show the current step.

NumPy is never installed over Blender's: the requirements pin ``numpy`` to the version Blender
ships (so pip picks compatible SciPy, scikit-image and numba builds), and every NumPy that pip puts
into the target folder is deleted afterwards. The target folder is appended to ``sys.path``, after
Blender's own ``site-packages``.
"""

from __future__ import annotations

import collections
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

TORCH_SPEC = "torch==2.13.0"
OTHER_REQUIREMENTS = ("scipy>=1.13", "scikit-image>=0.26,<0.27", "numba>=0.61",
                      "threadpoolctl>=3.1", "safetensors>=0.4",
                      "plyfile>=1.0", "laspy>=2.5", "lazrs>=0.6", "pye57>=0.4")  # the last four: point-cloud import
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
# PyPI's Linux torch wheels are CUDA builds; Windows needs PyTorch's own CUDA index.
CUDA_INDEX_WINDOWS = "https://download.pytorch.org/whl/cu128"
VARIANTS = ("CPU", "CUDA")
# pip output lines that name the current step (shown in the preferences).
STEP_PREFIXES = ("collecting", "downloading", "installing collected", "successfully installed")


class InstallError(Exception):
    """The install cannot start; the message says why and what to do."""


def numpy_version() -> str:
    """The version of the NumPy this Python (Blender's) already has."""
    import numpy

    return numpy.__version__


def requirements(variant: str = "CPU") -> list[str]:
    """What 'Install Dependencies' asks pip for (NumPy is pinned to Blender's, then removed)."""
    if variant not in VARIANTS:
        raise InstallError(f"unknown PyTorch build {variant!r}; use one of {', '.join(VARIANTS)}")
    return [TORCH_SPEC, *OTHER_REQUIREMENTS, f"numpy=={numpy_version()}"]


def pip_command(
    target,
    reqs,
    *,
    variant: str = "CPU",
    wheel_dir=None,
    python: str | None = None,
    platform: str | None = None,
) -> list[str]:
    """The pip command line that installs ``reqs`` into ``target``.

    ``wheel_dir``: install only from the wheels in that folder (``--no-index --find-links``, pip's
    user configuration ignored), so nothing is downloaded. Otherwise PyPI, plus PyTorch's CPU index
    for ``variant="CPU"`` (or its CUDA index on Windows for ``"CUDA"``).
    """
    platform = platform or sys.platform
    cmd = [
        python or sys.executable, "-m", "pip", "install",
        "--target", str(target), "--upgrade",
        "--only-binary", ":all:",
        "--no-input", "--disable-pip-version-check", "--progress-bar", "off",
    ]
    if wheel_dir:
        cmd += ["--isolated", "--no-index", "--find-links", str(wheel_dir)]
    elif variant == "CPU":
        cmd += ["--extra-index-url", CPU_INDEX]
    elif variant == "CUDA":
        if platform == "darwin":
            raise InstallError("PyTorch has no CUDA build for macOS; choose the CPU build")
        if platform.startswith("win"):
            cmd += ["--extra-index-url", CUDA_INDEX_WINDOWS]
    else:
        raise InstallError(f"unknown PyTorch build {variant!r}; use one of {', '.join(VARIANTS)}")
    return cmd + list(reqs)


def remove_numpy(target) -> list[str]:
    """Delete every NumPy that pip put into ``target``; return the names removed."""
    target = Path(target)
    removed = []
    if not target.is_dir():
        return removed
    for p in sorted(target.iterdir()):
        name = p.name.lower()
        is_meta = name.startswith("numpy-") and name.endswith((".dist-info", ".data"))
        if name in ("numpy", "numpy.libs") or is_meta:
            shutil.rmtree(p) if p.is_dir() else p.unlink()
            removed.append(p.name)
    bindir = target / "bin"
    if bindir.is_dir():
        for p in bindir.iterdir():
            if p.name.startswith(("f2py", "numpy-config")):
                p.unlink()
                removed.append(f"bin/{p.name}")
    return removed


@dataclass
class InstallResult:
    ok: bool
    message: str
    installed: list
    removed_numpy: list
    returncode: int


class PipJob:
    """One pip run in a subprocess, its output read by a thread.

    ``start()`` returns at once; ``running`` is polled from the main thread; ``finish()`` (after
    it stops running) removes NumPy from the target and returns an :class:`InstallResult`.
    """

    def __init__(self, cmd: list[str], target):
        self.cmd = list(cmd)
        self.target = Path(target)
        self.lines: collections.deque[str] = collections.deque(maxlen=400)
        self.step = "starting pip"
        self.returncode: int | None = None
        self.cancelled = False
        self._proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._t0 = 0.0
        self._t1: float | None = None

    def start(self) -> PipJob:
        if not _has_pip(self.cmd[0]):
            raise InstallError(
                "this Python has no pip module; install pip into Blender's Python "
                f"({self.cmd[0]} -m ensurepip) or point the add-on to a folder with PyTorch"
            )
        self.target.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, PYTHONNOUSERSITE="1", PYTHONUNBUFFERED="1")
        self._t0 = time.monotonic()
        self._proc = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, env=env,
        )
        self._reader = threading.Thread(target=self._read, name="nkf-pip-reader", daemon=True)
        self._reader.start()
        return self

    def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for raw in self._proc.stdout:
            line = raw.rstrip()
            if not line:
                continue
            self.lines.append(line)
            low = line.lstrip().lower()
            if low.startswith(STEP_PREFIXES):
                self.step = line.strip()[:120]
        self._proc.wait()
        self.returncode = self._proc.returncode
        self._t1 = time.monotonic()

    @property
    def running(self) -> bool:
        return self._reader is not None and self._reader.is_alive()

    @property
    def elapsed(self) -> float:
        return ((self._t1 or time.monotonic()) - self._t0) if self._t0 else 0.0

    def wait(self, timeout: float | None = None) -> bool:
        """Block until pip ends (headless use); True if it ended."""
        if self._reader is not None:
            self._reader.join(timeout)
        return not self.running

    def cancel(self) -> None:
        """Stop pip (the target may hold a partial install; run the install again)."""
        self.cancelled = True
        if self._proc is not None and self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
        self.wait(10)

    def finish(self) -> InstallResult:
        """After pip has ended: drop NumPy from the target and describe the outcome."""
        if self.running:
            raise RuntimeError("pip is still running")
        removed = remove_numpy(self.target)
        installed = []
        for line in self.lines:
            if line.startswith("Successfully installed "):
                installed = line[len("Successfully installed "):].split()
        rc = self.returncode if self.returncode is not None else -1
        if self.cancelled:
            return InstallResult(False, "Install cancelled; press Install Dependencies to try again",
                                 installed, removed, rc)
        if rc != 0:
            errors = [ln for ln in self.lines if ln.lstrip().startswith("ERROR")]
            why = (errors or list(self.lines)[-1:] or ["no output"])[-1].strip()
            return InstallResult(False, f"pip failed (exit {rc}): {why}", installed, removed, rc)
        kept = [p for p in installed if not p.lower().startswith("numpy-")]
        msg = f"Installed {', '.join(kept) if kept else 'nothing new'} into {self.target}"
        return InstallResult(True, msg, kept, removed, rc)


def _has_pip(python: str) -> bool:
    if python == sys.executable:
        import importlib.util

        return importlib.util.find_spec("pip") is not None
    return True
