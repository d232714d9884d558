"""Where the kernel sums run: fused numba loops on the CPU, or PyTorch on a CUDA device.

Both engines take and return NumPy float64 arrays, so the solver and the evaluator do not know
which one runs. Inputs are homogeneous vectors already split into unit vectors ``u`` (N, D) and
norms ``r`` (N,) by :func:`nkf_model.kernel.neural_spline.split_unit`; ``K(a_i, b_j) = r_i r_j g_ij / pi``.

Long sums are cut into chunks of about :data:`CHUNK_EVALS` kernel evaluations, and the optional
``cancel_poll`` callable (which raises to cancel) runs between chunks.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Optional

import numpy as np

from ..errors import InvalidParameterError, MethodUnavailableError

# Kernel evaluations per chunk: about 0.02 s at 2.5 G evaluations/s on an idle 2-core CPU, so that a
# cancel request is seen well within 0.5 s even when the machine is busy with other work.
CHUNK_EVALS = 50_000_000
CancelPoll = Optional[Callable[[], None]]


def _chunks(n_rows: int, n_cols: int, per_chunk: int = CHUNK_EVALS, dim: int = 4):
    # Kernel evaluations cost more with more dimensions (the learned kernel's 12-D vectors about
    # twice the 4-D ones): keep each chunk's time, not its count, about constant.
    per_chunk = per_chunk * 4 // max(4, dim)
    step = max(1, per_chunk // max(1, n_cols))
    for s in range(0, n_rows, step):
        yield s, min(n_rows, s + step)


class Engine:
    """Interface shared by the engines."""

    name = "base"
    device = "cpu"

    def kernel_sum(self, qu, qr, cu, cr, w, cancel_poll: CancelPoll = None) -> np.ndarray:
        """``sum_j K(q_i, c_j) w_j`` for every query: (Nq,) float64."""
        raise NotImplementedError

    def kernel_matrix(self, qu, qr, cu, cr, cancel_poll: CancelPoll = None) -> np.ndarray:
        """``K(q_i, c_j)``: (Nq, Nc) float64."""
        raise NotImplementedError

    def gram(self, u, r, diag: float, cancel_poll: CancelPoll = None) -> np.ndarray:
        """``K(a_i, a_j) + diag * I`` (N, N) float64 for unit rows ``u`` and norms ``r``; only the
        lower triangle is guaranteed (what a Cholesky factorisation reads)."""
        g = self.kernel_matrix(u, r, u, r, cancel_poll=cancel_poll)
        g[np.diag_indices(len(g))] += diag
        return g

    def normal_product(self, xu, xr, cu, cr, u, v, cancel_poll: CancelPoll = None) -> np.ndarray:
        """``K^T (K u + v)`` with ``K = K(x, c)`` (N, M), never stored: (M,) float64."""
        raise NotImplementedError


class NumbaEngine(Engine):
    """Fused, vectorised CPU loops (see :mod:`nkf_model.kernel._numba_kernels`)."""

    name = "numba"
    device = "cpu"
    # numba's default thread pool must not be entered from two threads at once.
    _lock = threading.Lock()

    def __init__(self):
        import numba

        from . import _numba_kernels as nk

        self._nk = nk
        self._numba = numba

    def _acute(self, *unit_vectors) -> bool:
        """True when every 4-D unit vector is [x : 1] / |[x : 1]| with |x| < 1 (all pairs within
        90 degrees), so the faster angle term applies.

        For the 12-D vectors [x : phi : 1] of the learned kernel (d = 8) the same argument is made
        with a common direction ``e`` (the mean of the vectors) instead of the last axis: unit
        vectors that are all within 45 degrees of ``e`` (``u . e >= 1/sqrt(2)``) are pairwise
        within 90 degrees."""
        lim = self._nk.ACUTE_MIN_LAST
        dims = {u.shape[1] for u in unit_vectors}
        if dims == {12}:
            e = sum(u.sum(axis=0) for u in unit_vectors)
            norm = float(np.linalg.norm(e))
            if norm == 0.0:
                return False
            e = e / norm
            return all(len(u) == 0 or float((u @ e).min()) >= lim for u in unit_vectors)
        return all(u.shape[1] == 4 and (len(u) == 0 or float(u[:, 3].min()) >= lim) for u in unit_vectors)

    def kernel_sum(self, qu, qr, cu, cr, w, cancel_poll: CancelPoll = None):
        beta = np.ascontiguousarray(cr * w)
        out = np.empty(len(qu))
        four = cu.shape[1] == 4
        twelve = cu.shape[1] == 12
        acute = self._acute(qu, cu)
        if four:
            cols = [np.ascontiguousarray(cu[:, k]) for k in range(4)]
        else:
            ct = np.ascontiguousarray(cu.T)
        for s, e in _chunks(len(qu), len(cu), dim=cu.shape[1]):
            if cancel_poll is not None:
                cancel_poll()
            q = np.ascontiguousarray(qu[s:e])
            with self._lock:
                if four:
                    out[s:e] = self._nk.gsum4(q, *cols, beta, acute)
                elif twelve:
                    out[s:e] = self._nk.gsum12(q, ct, beta, acute)
                else:
                    out[s:e] = self._nk.gsum(q, ct, beta)
        return out * qr / math.pi

    def kernel_matrix(self, qu, qr, cu, cr, cancel_poll: CancelPoll = None):
        ct = np.ascontiguousarray(cu.T)
        acute = self._acute(qu, cu)
        g = np.empty((len(qu), len(cu)))
        # Writing the matrix is slower per entry than summing: smaller chunks.
        for s, e in _chunks(len(qu), len(cu), per_chunk=CHUNK_EVALS // 10, dim=cu.shape[1]):
            if cancel_poll is not None:
                cancel_poll()
            with self._lock:
                g[s:e] = self._nk.gmatrix(np.ascontiguousarray(qu[s:e]), ct, acute)
            g[s:e] *= qr[s:e, None] / math.pi
            g[s:e] *= cr[None, :]
        return g

    def gram(self, u, r, diag: float, cancel_poll: CancelPoll = None) -> np.ndarray:
        # One fused pass over the lower triangle (half the kernel values, no scaling passes).
        if cancel_poll is not None:
            cancel_poll()
        with self._lock:
            g = self._nk.gram_lower(np.ascontiguousarray(u), np.ascontiguousarray(u.T),
                                    np.ascontiguousarray(r, dtype=np.float64), float(diag), self._acute(u))
        if cancel_poll is not None:
            cancel_poll()
        return g

    def normal_product(self, xu, xr, cu, cr, u, v, cancel_poll: CancelPoll = None):
        ct = np.ascontiguousarray(cu.T)
        us = np.ascontiguousarray(cr * u)
        ws = np.ascontiguousarray(xr / math.pi)
        acc = np.zeros(len(cu))
        nchunks = max(1, self._numba.get_num_threads())
        acute = self._acute(xu, cu)
        for s, e in _chunks(len(xu), len(cu), dim=cu.shape[1]):
            if cancel_poll is not None:
                cancel_poll()
            with self._lock:
                acc += self._nk.gnormal(
                    np.ascontiguousarray(xu[s:e]), ct, us, np.ascontiguousarray(v[s:e]),
                    np.ascontiguousarray(ws[s:e]), nchunks, acute,
                )
        return acc * cr


class TorchEngine(Engine):
    """PyTorch float64 tensors on a CUDA device (or on the CPU, as a cross-check)."""

    name = "torch"

    def __init__(self, device: str = "cuda"):
        import torch

        self._torch = torch
        self.device = device
        self._dev = torch.device(device)

    def _t(self, a):
        return self._torch.as_tensor(np.ascontiguousarray(a), dtype=self._torch.float64, device=self._dev)

    def _g(self, q, c):
        from .neural_spline import angle_term_torch

        d = self._torch.cdist(q, c, compute_mode="donot_use_mm_for_euclid_dist")
        return angle_term_torch(d * d)

    def kernel_sum(self, qu, qr, cu, cr, w, cancel_poll: CancelPoll = None):
        c = self._t(cu)
        beta = self._t(cr * w)
        out = np.empty(len(qu))
        for s, e in _chunks(len(qu), len(cu), per_chunk=CHUNK_EVALS // 4):
            if cancel_poll is not None:
                cancel_poll()
            out[s:e] = (self._g(self._t(qu[s:e]), c) @ beta).cpu().numpy()
        return out * qr / math.pi

    def kernel_matrix(self, qu, qr, cu, cr, cancel_poll: CancelPoll = None):
        c = self._t(cu)
        g = np.empty((len(qu), len(cu)))
        for s, e in _chunks(len(qu), len(cu), per_chunk=CHUNK_EVALS // 4):
            if cancel_poll is not None:
                cancel_poll()
            g[s:e] = self._g(self._t(qu[s:e]), c).cpu().numpy()
        return g * (qr[:, None] / math.pi) * cr[None, :]

    def normal_product(self, xu, xr, cu, cr, u, v, cancel_poll: CancelPoll = None):
        c = self._t(cu)
        us = self._t(cr * u)
        acc = self._torch.zeros(len(cu), dtype=self._torch.float64, device=self._dev)
        for s, e in _chunks(len(xu), len(cu), per_chunk=CHUNK_EVALS // 4):
            if cancel_poll is not None:
                cancel_poll()
            g = self._g(self._t(xu[s:e]), c)
            w = self._t(xr[s:e] / math.pi)
            t = w * (w * (g @ us) + self._t(v[s:e]))
            acc += g.T @ t
        return acc.cpu().numpy() * cr


def cuda_driver_present() -> bool:
    """Whether this machine has an NVIDIA driver at all, told without importing PyTorch (which
    takes seconds): its device files or driver version on Linux (``/usr/lib/wsl`` on WSL), the
    driver library on Windows; never on macOS. Without one, PyTorch cannot see a CUDA device."""
    import os
    import sys

    if sys.platform == "darwin":
        return False
    if sys.platform.startswith("linux"):
        if any(os.path.exists(p) for p in ("/proc/driver/nvidia/version", "/dev/nvidiactl", "/dev/nvidia0")):
            return True
        return os.path.isdir("/usr/lib/wsl/lib") and any(
            name.startswith("libcuda.so") for name in os.listdir("/usr/lib/wsl/lib")
        )
    import ctypes.util

    return ctypes.util.find_library("nvcuda") is not None


def cuda_available() -> bool:
    """True when PyTorch is installed and sees a CUDA device. PyTorch is imported only when an
    NVIDIA driver is there (:func:`cuda_driver_present`) or it already was, so the CPU path of a
    machine without a GPU never pays for importing it."""
    return cuda_problem()[0] == ""


_CPU_ENGINE: Engine | None = None


def cpu_engine() -> Engine:
    """The CPU engine: numba when installed, else PyTorch on the CPU."""
    global _CPU_ENGINE
    if _CPU_ENGINE is None:
        try:
            _CPU_ENGINE = NumbaEngine()
        except ImportError:
            try:
                _CPU_ENGINE = TorchEngine("cpu")
            except ImportError:
                raise MethodUnavailableError(
                    "neither numba nor PyTorch is installed: install one of them to run the kernel"
                ) from None
    return _CPU_ENGINE


def select_engine(device: str = "auto") -> Engine:
    """Engine for ``device``: ``"auto"`` (CUDA when present), ``"cpu"`` or ``"cuda"``."""
    if device not in ("auto", "cpu", "cuda"):
        raise InvalidParameterError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    if device == "cpu":
        return cpu_engine()
    reason, cause = cuda_problem()  # one look (it may import PyTorch): both the answer and the why
    if not reason:
        return TorchEngine("cuda")
    if device == "cuda":
        raise MethodUnavailableError(f"device 'cuda' was asked for, but {reason}; use 'cpu' or 'auto'") from cause
    return cpu_engine()


def cuda_problem() -> tuple[str, ImportError | None]:
    """Why CUDA cannot be used, in words, and the ``ImportError`` of PyTorch when that is the
    reason (a missing or half-installed PyTorch): no NVIDIA driver on this machine (PyTorch is
    then not imported), PyTorch that cannot be imported, or PyTorch that sees no CUDA device."""
    import sys

    if "torch" not in sys.modules and not cuda_driver_present():
        return "this computer has no NVIDIA driver (no CUDA device)", None
    try:
        import torch
    except ImportError as exc:
        line = (f"{type(exc).__name__}: {exc}".splitlines() or [""])[0]
        return f"PyTorch cannot be imported ({line})", exc
    if torch.cuda.is_available():
        return "", None
    return "PyTorch sees no CUDA device", None
