"""Kept fits (``nkf_model.fit``) per source, so that a new Lambda or Resolution does not start over.
No ``bpy`` here.

A fit is kept under a :class:`FitKey`: the source object's ``session_uid``, a digest of the arrays
that were read from it (points, normals, colours, viewpoints) and the settings the fit depends on
(everything but Lambda, Resolution, Watertight, Minimum Piece, the trim distance and the memory
budget; Resolution too when a large input was reduced for it). The cache is bounded by memory
(least recently used fits are dropped first; the add-on preference "Fit Cache"), and
:func:`drop_source` / :func:`clear` forget fits when a source changes, is deleted or another file
is loaded (the add-on's handlers call them).

While a kept fit is being factorised for cheap lambda changes (``Fit.factorize`` on a background
thread, :func:`factorize_later`), it stays usable: until the factorisation is done a new lambda is
solved by Cholesky.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from nkf_model.options import Options

# Settings that only need a new mesh or a new solve, never a new fit (see nkf_model.pipeline.fitted).
REMESH_SETTINGS = ("lam", "resolution", "close", "min_piece", "trim", "memory_budget")
DEFAULT_BUDGET = 1 << 30  # bytes: 1 GiB unless the preference says otherwise


@dataclass(frozen=True)
class FitKey:
    """Which fit a run can reuse."""

    source: int
    data: str
    settings: tuple


def digest(*arrays) -> str:
    """A short digest of the arrays' shapes, types and bytes (``None`` entries count too)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        if a is None:
            h.update(b"none;")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def fit_settings(options: Options, resolution_dependent: bool = False) -> tuple:
    """The settings a fit depends on, as a hashable tuple (trim only as on/off)."""
    d = options.as_dict()
    out = [(k, str(v)) for k, v in d.items() if k not in REMESH_SETTINGS]
    out.append(("trim_on", d["trim"] is not None))
    if resolution_dependent:
        out.append(("resolution", d["resolution"]))
    return tuple(out)


def key_for(source: int, options: Options, *arrays, resolution_dependent: bool = False) -> FitKey:
    return FitKey(int(source), digest(*arrays), fit_settings(options, resolution_dependent))


class FitCache:
    """Fits by :class:`FitKey`, least recently used first out, at most ``budget`` bytes in all.

    Thread-safe. A single fit larger than the budget is not kept (:meth:`put` returns False).
    """

    def __init__(self, budget: int = DEFAULT_BUDGET):
        self.budget = int(budget)
        self._items: OrderedDict[FitKey, object] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: FitKey):
        """The fit for ``key`` (also for a reduced input fitted at another resolution: None), or None."""
        with self._lock:
            fit = self._items.get(key)
            if fit is not None:
                self._items.move_to_end(key)
            return fit

    def put(self, key: FitKey, fit) -> bool:
        """Keep ``fit``; drop older fits of the same source and data, then the least recently used
        ones until the total fits the budget."""
        size = int(fit.nbytes)
        with self._lock:
            for k in [k for k in self._items if k.source == key.source and k != key]:
                del self._items[k]  # one fit per source: its settings changed
            self._items.pop(key, None)
            if size > self.budget:
                return False
            self._items[key] = fit
            self._trim()
            return True

    def _trim(self) -> None:
        while self._items and self.nbytes_unlocked() > self.budget:
            self._items.popitem(last=False)

    def nbytes_unlocked(self) -> int:
        return sum(int(f.nbytes) for f in self._items.values())

    @property
    def nbytes(self) -> int:
        with self._lock:
            return self.nbytes_unlocked()

    def set_budget(self, budget: int) -> None:
        with self._lock:
            self.budget = int(budget)
            self._trim()

    def fit_for(self, source: int):
        """The kept fit of a source, whatever its key, or None."""
        with self._lock:
            for k, f in self._items.items():
                if k.source == source:
                    return f
            return None

    def drop_source(self, source: int) -> int:
        """Forget every fit of ``source``; return how many."""
        with self._lock:
            keys = [k for k in self._items if k.source == source]
            for k in keys:
                del self._items[k]
            return len(keys)

    def keep_only(self, sources) -> int:
        """Forget the fits of every source not in ``sources`` (deleted objects); return how many."""
        live = set(sources)
        with self._lock:
            keys = [k for k in self._items if k.source not in live]
            for k in keys:
                del self._items[k]
            return len(keys)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


CACHE = FitCache()

# Background factorisations: one thread each, stopped (as far as they can be) by stop_factorizing.
_factorizers: list[tuple[threading.Thread, threading.Event]] = []


def factorize_later(fit) -> threading.Thread | None:
    """Start ``fit.factorize()`` on a daemon thread, so that later lambdas are cheap."""
    if not getattr(fit, "can_factorize", False) or fit.factorized:
        return None
    stop = threading.Event()

    def work():
        try:
            fit.factorize(cancel=stop)
        except Exception:  # noqa: BLE001 - cancelled, or out of memory: later lambdas solve by Cholesky
            pass

    t = threading.Thread(target=work, name="nkf-factorize", daemon=True)
    _factorizers[:] = [(th, ev) for th, ev in _factorizers if th.is_alive()]
    _factorizers.append((t, stop))
    t.start()
    return t


def stop_factorizing(timeout: float = 10.0) -> list[threading.Thread]:
    """Ask every background factorisation to stop and wait; return the threads still running (a
    dense eigendecomposition cannot be interrupted)."""
    for _, ev in _factorizers:
        ev.set()
    left = [t for t, _ in _factorizers if (t.join(timeout), t.is_alive())[1]]
    _factorizers[:] = [(t, ev) for t, ev in _factorizers if t.is_alive()]
    return left
