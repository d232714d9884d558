"""Time and memory of a reconstruction before it starts, in the panel's and the operator's terms.

No ``bpy`` here. Wraps :func:`nkf_model.estimate` (microseconds, no data looked at; it applies the
same settings as :func:`nkf_model.reconstruct`, the Max Points subset included) and turns a memory
estimate over the budget into one line that names the Blender setting to lower.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

from nkf_model.options import MIN_RESOLUTION, Options

GB = 2**30


@dataclass(frozen=True)
class Outlook:
    """``summary`` one line (e.g. ``"about 3 s, 0.3 GB (dense solver, 400 points)"``);
    ``seconds`` and ``peak_bytes`` the estimate; ``budget`` the memory budget in bytes;
    ``problem`` one line when the run would be refused, else ``""``."""

    summary: str
    seconds: float
    peak_bytes: int
    budget: int
    problem: str


def gb(n_bytes: float) -> str:
    """Bytes as GB with two significant digits below 1 GB (``"0.15 GB"``, ``"2.1 GB"``)."""
    x = n_bytes / GB
    return f"{x:.1f} GB" if x >= 1 else f"{x:.2g} GB"


def points_used(count: int, max_points: int | None) -> int:
    """Points fitted: all, or the Max Points subset (``max_points`` ``None``: all)."""
    return count if max_points is None else min(count, max_points)


def resolve_budget(memory_budget: int | None) -> int:
    """The budget in bytes: the given one, or nkf_model's default (60 % of memory, at most 16 GiB)."""
    if memory_budget:
        return int(memory_budget)
    from nkf_model.pipeline.budget import default_memory_budget

    return int(default_memory_budget())


def outlook(count: int, options: Options, estimate_normals: bool, colors: bool) -> Outlook:
    """The estimate for ``count`` points of an object run with ``options``.

    ``estimate_normals``: whether the object's normals will be estimated; ``colors``: whether
    colours will be carried (the object has them and Colours is on). Raises ImportError when
    nkf_model cannot be imported (missing packages).
    """
    return _outlook(int(count), options, bool(estimate_normals), bool(colors), resolve_budget(options.memory_budget))


@lru_cache(maxsize=64)
def _outlook(count: int, options: Options, estimate_normals: bool, colors: bool, budget: int) -> Outlook:
    import nkf_model

    def est(n_points, opts):
        return nkf_model.estimate(n_points, options=opts, estimate_normals=estimate_normals, colors=colors)

    e = est(count, options)
    problem = ""
    if e.peak_bytes > budget:
        # Name the setting whose halving saves more memory.
        n = points_used(count, options.max_points)
        resolution = options.resolution
        half_res = options.replace(resolution=max(MIN_RESOLUTION, resolution // 2))
        by_resolution = e.peak_bytes - est(count, half_res).peak_bytes
        by_points = e.peak_bytes - est(max(1, n // 2), options).peak_bytes
        if by_resolution >= by_points:
            hint = f"lower Resolution (now {resolution})"
        else:
            hint = f"lower Max Points (now {n:,} points used)"
        problem = (
            f"this reconstruction needs about {gb(e.peak_bytes)} but the memory budget is "
            f"{gb(budget)}: {hint}, or raise Memory Budget in the add-on preferences"
        )
    return Outlook(e.summary(), float(e.seconds), int(e.peak_bytes), int(budget), problem)
