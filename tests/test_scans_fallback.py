"""A GPU out-of-memory error falls back to the CPU with a warning (issue 5).

There is no GPU here, so the failure is injected: an engine that claims to be on a CUDA device and
raises PyTorch's own ``torch.cuda.OutOfMemoryError`` from every kernel call.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from shapes import sphere_points

import nkf_model
from nkf_model.kernel.engines import Engine, cpu_engine
from nkf_model.pipeline.device_fallback import DeviceWarning, run_with_cpu_fallback

torch = pytest.importorskip("torch")
rec = importlib.import_module("nkf_model.pipeline.reconstruct")  # the module, not the function


class OutOfMemoryEngine(Engine):
    """Stands in for a CUDA engine whose every allocation fails."""

    name = "torch"
    device = "cuda"

    def __init__(self, error=None):
        self.calls = 0
        self.error = error or torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 9.00 GiB")

    def _fail(self, *a, **k):
        self.calls += 1
        raise self.error

    kernel_sum = kernel_matrix = normal_product = _fail


@pytest.mark.parametrize("n_points", [800, 25_000], ids=["dense", "pou"])
def test_reconstruct_falls_back_to_the_cpu(monkeypatch, n_points):
    p, n = sphere_points(n_points, seed=1)
    failing = OutOfMemoryEngine()
    monkeypatch.setattr(rec, "select_engine", lambda device: failing)
    with pytest.warns(DeviceWarning, match="GPU ran out of memory"):
        m = nkf_model.reconstruct(p, n, resolution=32, device="cuda")
    assert failing.calls >= 1
    assert m.stats["engine"].endswith(":cpu")
    monkeypatch.undo()
    ref = nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    assert np.array_equal(m.faces, ref.faces) and np.allclose(m.vertices, ref.vertices)


def test_other_errors_are_not_swallowed(monkeypatch):
    p, n = sphere_points(300, seed=1)
    monkeypatch.setattr(rec, "select_engine", lambda device: OutOfMemoryEngine(RuntimeError("driver crashed")))
    with pytest.raises(RuntimeError, match="driver crashed"):
        nkf_model.reconstruct(p, n, resolution=32, device="cuda")


def test_cpu_out_of_memory_is_not_retried():
    class CpuFailing(OutOfMemoryEngine):
        device = "cpu"

    with pytest.raises(torch.cuda.OutOfMemoryError):
        run_with_cpu_fallback(lambda eng: eng.kernel_sum(None, None, None, None, None), CpuFailing())


def test_fallback_runs_the_work_again_on_the_cpu_engine():
    seen = []

    def work(eng):
        seen.append(eng.device)
        if eng.device == "cuda":
            raise torch.cuda.OutOfMemoryError("out of memory")
        return 42

    with pytest.warns(DeviceWarning):
        assert run_with_cpu_fallback(work, OutOfMemoryEngine()) == 42
    assert seen == ["cuda", cpu_engine().device]
