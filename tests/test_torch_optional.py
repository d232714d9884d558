"""The CPU path never imports PyTorch on a machine without an NVIDIA driver (importing it took 3.3 s
of a 1,000-point command-line run), and device "auto" still finds CUDA where there is one."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from nkf_model.kernel import engines

CODE = textwrap.dedent(
    """
    import sys
    import numpy as np
    import nkf_model
    rng = np.random.default_rng(0)
    p = rng.normal(size=(300, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    for method in ("splines", "nkf"):
        mesh = nkf_model.reconstruct(p * 0.4, p, method=method, resolution=24, device="auto")
        assert mesh.stats["engine"] == "numba:cpu", mesh.stats["engine"]
    print("torch" in sys.modules)
    """
)


@pytest.mark.skipif(engines.cuda_driver_present(), reason="this machine has an NVIDIA driver")
def test_auto_device_without_a_driver_does_not_import_torch():
    run = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "False"


def test_driver_check_gates_the_torch_import(monkeypatch):
    code = ("import sys\nfrom nkf_model.kernel import engines\nengines.cuda_driver_present = lambda: False\n"
            "print(engines.cuda_available(), 'torch' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False"]
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(engines, "cuda_driver_present", lambda: True)
    assert engines.cuda_available() is bool(torch.cuda.is_available())


def test_cuda_asked_for_without_a_driver_says_so_without_importing_torch():
    code = ("import sys\nfrom nkf_model.kernel import engines\nengines.cuda_driver_present = lambda: False\n"
            "try:\n    engines.select_engine('cuda')\nexcept Exception as exc:\n    print(exc)\n"
            "print('torch' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == [
        "device 'cuda' was asked for, but this computer has no NVIDIA driver (no CUDA device); use 'cpu' or 'auto'",
        "False",
    ]


def test_cuda_asked_for_with_a_pytorch_that_does_not_import(monkeypatch):
    """A half-installed PyTorch: the message says PyTorch cannot be imported, with its error, and
    carries the ImportError as its cause (the add-on names the folder from it)."""
    monkeypatch.setattr(engines, "cuda_driver_present", lambda: True)
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` now raises ImportError
    with pytest.raises(engines.MethodUnavailableError) as info:
        engines.select_engine("cuda")
    assert str(info.value).startswith("device 'cuda' was asked for, but PyTorch cannot be imported (ModuleNotFoundError: import of torch halted")
    assert isinstance(info.value.__cause__, ImportError)
    assert engines.cuda_available() is False
