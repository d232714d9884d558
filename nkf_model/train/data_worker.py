"""Training batches, made in the training process or in a worker process.

:class:`DataSource` turns a step number into that step's examples: ``numpy.random.default_rng([seed,
step])`` decides, for each example of the batch, whether it comes from a procedural shape
(:mod:`nkf_model.train.procedural`, probability ``p_procedural``, a new shape every time) or from a
corpus training mesh (its samples cached on disk, built the first time the mesh is drawn), and then
augments it with :func:`nkf_model.train.examples.make_example`. Nothing depends on earlier steps, so a
resumed run gets exactly the examples an uninterrupted one would have got, whatever the state of the
disk cache.

:class:`BatchWorker` runs a :class:`DataSource` in one spawned process that works ahead of the
trainer (a small queue of finished batches), so making examples overlaps with the solve. Both
processes are single-threaded.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_mod
import time
from pathlib import Path

import numpy as np

from .examples import AugmentSpec, CacheSpec, load_samples, make_example
from .procedural import ProceduralSpec, shape_samples


class DataSource:
    """The examples of any step; see the module docstring.

    Parameters
    ----------
    entries : list of corpus.CorpusMesh
        Training meshes.
    cache_dir : path
        Folder of the per-mesh sample cache (shared with :func:`examples.build_cache`).
    """

    def __init__(self, entries, cache_dir, cache_spec: CacheSpec, augment: AugmentSpec, seed: int, batch: int,
                 p_procedural: float = 0.0, procedural: ProceduralSpec | None = None):
        self.entries = list(entries)
        self.cache_dir = Path(cache_dir)
        self.cache_spec = cache_spec
        self.augment = augment
        self.seed = seed
        self.batch = batch
        self.p_procedural = p_procedural
        self.procedural = procedural or ProceduralSpec()
        self._samples: dict = {}
        if not self.entries and p_procedural < 1.0:
            raise ValueError("no training meshes and p_procedural < 1")

    def mesh_samples(self, i: int) -> dict:
        """Cached samples of training mesh ``i`` (computed and written to the cache if missing)."""
        if i not in self._samples:
            from .examples import _cache_path, build_samples

            e = self.entries[i]
            path = _cache_path(self.cache_dir, e)
            d = load_samples(path)
            if d is None:
                d = build_samples(e, self.cache_spec)
                self.cache_dir.mkdir(parents=True, exist_ok=True)
                tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
                np.savez(tmp, **d)
                tmp.replace(path)
                d.pop("version")
            self._samples[i] = d
        return self._samples[i]

    def procedural_samples(self, shape_seed: int) -> dict:
        """Samples of a procedural shape; a shape with no surface on the grid is replaced by the next seed."""
        for k in range(20):
            try:
                return shape_samples(shape_seed + k, self.procedural)
            except ValueError:
                continue
        raise RuntimeError(f"procedural shapes {shape_seed}..{shape_seed + 19} all failed")

    def batch_at(self, step: int) -> list:
        """The examples of ``step`` (a list of ``batch`` :class:`examples.Example`)."""
        rng = np.random.default_rng([self.seed, step])
        out = []
        for _ in range(self.batch):
            if self.p_procedural > 0 and rng.random() < self.p_procedural:
                samples = self.procedural_samples(int(rng.integers(2**62)))
            else:
                samples = self.mesh_samples(int(rng.integers(len(self.entries))))
            out.append(make_example(samples, rng, self.augment))
        return out


def _worker_main(kwargs: dict, start: int, q, stop) -> None:  # pragma: no cover - runs in the child
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        import numba

        numba.set_num_threads(1)
    except ImportError:
        pass
    try:
        src = DataSource(**kwargs)
        step = start
        while not stop.is_set():
            batch = src.batch_at(step)
            item = (step, batch, time.process_time())
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.5)
                    break
                except queue_mod.Full:
                    continue
            step += 1
    except BaseException as exc:  # report to the trainer instead of dying silently
        try:
            q.put(("error", f"{type(exc).__name__}: {exc}", time.process_time()), timeout=5)
        except Exception:
            pass
        raise


class BatchWorker:
    """One worker process making the batches of steps ``start, start + 1, ...`` in order.

    ``get(step)`` returns that step's examples; ``cpu_seconds`` is the worker's CPU time so far.
    """

    def __init__(self, source_kwargs: dict, start: int, prefetch: int = 3):
        ctx = mp.get_context("spawn")
        self.q = ctx.Queue(maxsize=max(1, prefetch))
        self.stop_event = ctx.Event()
        self.proc = ctx.Process(target=_worker_main, args=(source_kwargs, start, self.q, self.stop_event),
                                daemon=True, name="nkf-train-data")
        self.proc.start()
        self.cpu_seconds = 0.0

    def get(self, step: int, timeout: float = 3600.0) -> list:
        t0 = time.monotonic()
        while True:
            try:
                item = self.q.get(timeout=1.0)
                break
            except queue_mod.Empty:
                if not self.proc.is_alive():
                    raise RuntimeError(f"the data worker exited (code {self.proc.exitcode})") from None
                if time.monotonic() - t0 > timeout:
                    raise TimeoutError(f"no batch for step {step} within {timeout:.0f} s") from None
        got, batch, cpu = item
        if got == "error":
            raise RuntimeError(f"the data worker failed: {batch}")
        if got != step:
            raise RuntimeError(f"the data worker sent step {got}, expected {step}")
        self.cpu_seconds = cpu
        return batch

    def close(self) -> None:
        self.stop_event.set()
        try:
            while True:
                self.q.get_nowait()
        except (queue_mod.Empty, OSError, ValueError):
            pass
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout=5)


def source_kwargs(entries, cfg) -> dict:
    """Keyword arguments of :class:`DataSource` for a :class:`kernel_training.TrainConfig`."""
    return {
        "entries": list(entries),
        "cache_dir": str(cfg.data.cache),
        "cache_spec": cfg.cache,
        "augment": cfg.augment,
        "seed": cfg.train.seed,
        "batch": cfg.train.batch,
        "p_procedural": cfg.data.p_procedural,
        "procedural": cfg.procedural,
    }

