"""The time/memory estimate and the memory budget (issue 5)."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest
from shapes import sphere_points

import nkf_model
from nkf_model.pipeline import budget


def test_estimate_is_cheap_and_grows_with_the_job():
    t0 = time.perf_counter()
    for _ in range(1000):
        e = nkf_model.estimate(100_000, resolution=256)
    assert (time.perf_counter() - t0) / 1000 < 1e-3  # well under a millisecond per call
    assert e.solver == "pou" and not e.reduced and e.seconds > 0 and e.peak_bytes > 0
    small = nkf_model.estimate(1_000, resolution=128)
    assert small.solver == "dense" and small.seconds < e.seconds and small.peak_bytes < e.peak_bytes
    assert nkf_model.estimate(10_000, resolution=256).solver == "pou"
    assert nkf_model.estimate(3_000, resolution=256).solver == "dense"
    big = nkf_model.estimate(1_000_000, resolution=256, estimate_normals=True)
    assert big.reduced and big.points_solved < big.points_in and big.estimate_normals
    assert nkf_model.estimate(100_000, resolution=512).seconds > e.seconds
    assert "GB" in e.summary() and "pou" in e.summary()


def test_learned_kernel_estimate_is_slower(tmp_path):
    # method="nkf" evaluates 13-number kernel inputs in the general loops: the estimate says so, and
    # reconstruct() checks the budget with the learned kernel's estimate (the timing itself is
    # measured by the benchmarks, docs/scans.md).
    from nkf_helpers import tiny_weights

    s = nkf_model.estimate(100_000, resolution=256, method="splines")
    n = nkf_model.estimate(100_000, resolution=256, method="nkf")
    assert n.seconds > 2 * s.seconds and n.peak_bytes > s.peak_bytes
    w = tiny_weights(tmp_path / "w.safetensors", gate=0.2)
    p, q = sphere_points(500, seed=2)
    m = nkf_model.reconstruct(p, q, method="nkf", weights=w, resolution=32, device="cpu")
    assert m.stats["estimate"]["seconds"] == pytest.approx(nkf_model.estimate(500, resolution=32, method="nkf").seconds)
    assert m.stats["estimate"]["seconds"] > nkf_model.estimate(500, resolution=32, method="splines").seconds


def test_oversized_job_is_refused_before_allocating():
    p, n = sphere_points(60_000, seed=0)
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        with pytest.raises(nkf_model.MemoryBudgetError, match="max_centres") as exc:
            # An exact solve of 120,000 constraints needs a 120,000^2 float64 matrix (115 GB).
            nkf_model.reconstruct(p, n, solver="dense", max_centres=200_000, device="cpu")
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert isinstance(exc.value, nkf_model.NKFInputError)
    assert "GB" in str(exc.value)
    assert elapsed < 0.5
    assert peak < 5 * 2**20  # nothing but small bookkeeping was allocated


def test_budget_argument_names_the_setting_to_lower():
    p, n = sphere_points(2000, seed=0)
    with pytest.raises(nkf_model.MemoryBudgetError, match="resolution"):
        nkf_model.reconstruct(p, n, resolution=1024, memory_budget=0.3 * 2**30, device="cpu")
    est = budget.plan(5_000_000, resolution=128, estimate_normals=True, solver="auto", max_centres=6000,
                      reduce_to=None)
    with pytest.raises(nkf_model.MemoryBudgetError, match="reduce_to"):
        budget.enforce(est, 1 * 2**30)
    budget.enforce(nkf_model.estimate(1000), 1 * 2**30)  # a small job passes


def test_default_budget_is_a_share_of_this_machine():
    b = budget.default_memory_budget()
    assert 1 * 2**30 <= b <= 16 * 2**30


def test_stats_carry_the_estimate():
    p, n = sphere_points(500, seed=0)
    m = nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    assert m.stats["estimate"]["solver"] == m.stats["solver"] == "dense"
    assert np.isfinite(m.stats["estimate"]["seconds"])
