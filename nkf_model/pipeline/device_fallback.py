"""Falling back from the GPU to the CPU when the GPU runs out of memory.

:func:`run_with_cpu_fallback` runs one piece of work (solve and evaluate) with the chosen engine; if
that engine is on a GPU and PyTorch reports ``torch.cuda.OutOfMemoryError``, it frees PyTorch's
cached GPU memory, warns with a :class:`DeviceWarning` and runs the same work again on the CPU
engine. Any other error, and any error on the CPU, propagates unchanged.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TypeVar

from ..errors import DeviceWarning
from ..kernel.engines import Engine, cpu_engine

T = TypeVar("T")


def is_device_out_of_memory(exc: BaseException) -> bool:
    """True when ``exc`` is PyTorch's out-of-memory error for a GPU."""
    try:
        import torch
    except ImportError:
        return False
    oom = getattr(torch.cuda, "OutOfMemoryError", None) or getattr(torch, "OutOfMemoryError", None)
    return oom is not None and isinstance(exc, oom)


def _free_gpu_cache() -> None:
    try:
        import torch

        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    except Exception:  # pragma: no cover - best effort only
        pass


def run_with_cpu_fallback(work: Callable[[Engine], T], engine: Engine, cpu: Callable[[], Engine] = cpu_engine) -> T:
    """``work(engine)``; on a GPU out-of-memory error, ``work(cpu())`` after a :class:`DeviceWarning`.

    Parameters
    ----------
    work : callable
        Takes an engine and returns the result. It must not keep state between calls, since it
        may run twice.
    engine : Engine
        The engine chosen for the run.
    cpu : callable
        Returns the CPU engine to fall back to.
    """
    try:
        return work(engine)
    except Exception as exc:
        if getattr(engine, "device", "cpu") == "cpu" or not is_device_out_of_memory(exc):
            raise
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else "out of memory"
        del exc
        _free_gpu_cache()
        warnings.warn(
            f"the GPU ran out of memory ({detail}); continuing on the CPU, which is slower",
            DeviceWarning,
            stacklevel=2,
        )
        return work(cpu())
