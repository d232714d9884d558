"""Which device ran a reconstruction, in words for the report ("CPU, 2 threads", "CUDA: NVIDIA ...").
No ``bpy`` here; nothing is imported that the run itself did not import."""

from __future__ import annotations

import sys


def describe(stats: dict) -> str:
    """The device of a finished run from ``mesh.stats["engine"]`` (``"numba:cpu"``,
    ``"torch:cuda"``, ...); ``""`` when unknown."""
    engine = str(stats.get("engine", ""))
    name, _, device = engine.partition(":")
    if not name:
        return ""
    if device.startswith("cuda"):
        torch = sys.modules.get("torch")
        try:
            gpu = torch.cuda.get_device_name(torch.device(device)) if torch is not None else ""
        except Exception:  # the name is only for the report
            gpu = ""
        return f"CUDA: {gpu}" if gpu else "CUDA"
    threads = 0
    numba = sys.modules.get("numba")
    torch = sys.modules.get("torch")
    if name == "numba" and numba is not None:
        threads = int(numba.get_num_threads())
    elif name == "torch" and torch is not None:
        threads = int(torch.get_num_threads())
    if threads:
        return f"CPU, {threads} thread{'s' if threads != 1 else ''}"
    return "CPU"
