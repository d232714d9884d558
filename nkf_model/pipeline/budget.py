"""Time and memory of a reconstruction, estimated before it starts.

:func:`estimate` predicts, from the number of input points and the settings alone (no look at the
data, no heavy work: microseconds), what :func:`nkf_model.reconstruct` will do (reduction, normal
estimation, solver) and about how long it takes and how much memory it needs on the CPU.
:func:`enforce` refuses a run whose memory estimate exceeds the budget with a
:class:`~nkf_model.errors.MemoryBudgetError` that names the setting to lower.

The constants below were fitted to runs on this project's reference machine (2-core AMD EPYC,
numba engine; see ``docs/scans.md``); the number of grid points evaluated depends on the area of
the surface, which is only known afterwards, so times are "about" (within a factor of 2 for
objects; open scenes with large areas take longer).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass

from ..errors import MemoryBudgetError
from ..normals.sign_check import MAX_POINTS as SIGN_CHECK_MAX_POINTS
from ..options import SETTING, Options

# --- fitted constants (reference CPU, 2 threads) ---------------------------------------------
NODES_PER_R2 = 22.0  # grid points evaluated over all levels, per resolution^2 (objects)
KERNEL_RATE = 2.0e9  # kernel evaluations per second, fused numba sums on 2 cores
POU_RATE = 0.8e9  # the same inside the partition-of-unity sum (short loops, 8 patches)
POU_EVALS_PER_NODE = 1300  # kernel evaluations per grid point with ~80 points per patch
FLOPS = 25e9  # dense Cholesky, float64
POU_FIT_PER_POINT = 25e-6  # seconds per point for the local solves
NORMALS_PER_POINT = 60e-6  # seconds per point for PCA, views and propagation
# ... and for the learned sign check (sign_check.MAX_POINTS points at most; measured 30 us a point)
SIGN_CHECK_PER_POINT = 30e-6
INPUT_PER_POINT = 1.5e-6  # seconds per input point: cleaning, normalising, reducing
MESH_PER_NODE = 0.6e-6  # seconds per evaluated grid point: band bookkeeping and marching cubes
FALKON_ITERATIONS = 40
FIXED_SECONDS = 0.15
# The learned kernel (method="nkf"): 12 numbers per homogeneous point instead of 4. The partition of
# unity's sum takes its general loop: at 100,000 points, resolution 256, evaluation 20.0 s against
# 4.5 s for splines (local fits 5.0 s against 4.8 s, the feature network 0.2 s). The global fits
# (dense, Falkon) have fused 12-D loops: at 1,000 points, resolution 128, 0.3 s against 0.2 s.
NKF_EVAL_FACTOR = 4.4
NKF_EVAL_FACTOR_GLOBAL = 1.5
NKF_FIXED_SECONDS = 0.1
# Per solved point, for the learned kernel: 12-D constraints and partition-of-unity patch centres
# instead of 4-D (1,000,000 points, all kept, resolution 256: peak 3,121 MiB against 1,220 MiB).
BYTES_NKF = 2000

BYTES_INPUT = 420  # per input point during cleaning and reduction
BYTES_SOLVED = 250  # per solved point: constraints, homogeneous vectors, normals
BYTES_NORMALS = 900  # per point while normals are estimated (neighbour graph, views)
BYTES_POU = 900  # per point: centres of the 8 patches a point belongs to, and their weights
BYTES_NODE = 330  # per evaluated grid point: keys, values and the finest levels' work arrays
FIXED_BYTES = 150 * 2**20

GIB = 2**30


@dataclass
class Estimate:
    """What a run will do and about what it costs.

    Attributes
    ----------
    points_in : int
        Input points.
    points_solved : int
        Points after voxel-grid reduction (an upper bound: the reduction stops at ``reduce_to``).
    reduced : bool
        Whether the input will be reduced.
    estimate_normals : bool
    solver : str
        ``"dense"``, ``"falkon"`` or ``"pou"``.
    resolution : int
    seconds : float
        Expected wall time on the reference CPU.
    peak_bytes : int
        Expected peak memory growth of the call.
    """

    points_in: int
    points_solved: int
    reduced: bool
    estimate_normals: bool
    solver: str
    resolution: int
    seconds: float
    peak_bytes: int

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        """One line for a user interface, e.g. ``"about 40 s, 2.1 GB (pou solver, 100,000 points)"``."""
        what = f"{self.solver} solver, {self.points_solved:,} points"
        if self.reduced:
            what += f" reduced from {self.points_in:,}"
        if self.estimate_normals:
            what += ", normals estimated"
        return f"about {_fmt_seconds(self.seconds)}, {self.peak_bytes / GIB:.1f} GB ({what})"


def _fmt_seconds(s: float) -> str:
    if s < 1:
        return "1 s"
    if s < 90:
        return f"{s:.0f} s"
    return f"{s / 60:.1f} min"


def default_memory_budget() -> int:
    """Default budget: 60 % of this machine's physical memory, at most 16 GiB (8 GiB if unknown)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 * GIB
    return int(min(16 * GIB, 0.6 * total))


def choose_solver(n_points: int, max_centres: int, solver: str = "auto") -> str:
    """The solver :func:`nkf_model.reconstruct` uses for ``n_points`` oriented points."""
    if solver != "auto":
        return solver
    return "dense" if 2 * n_points <= max_centres else "pou"


def estimate(
    n_points: int,
    *,
    options: Options | None = None,
    estimate_normals: bool = False,
    colors: bool = False,
    trim: bool | None = None,
    **settings,
) -> Estimate:
    """Predict what :func:`nkf_model.reconstruct` does with ``n_points`` points and these settings.

    Cheap (no data is looked at): meant for a user interface to call whenever a setting changes.
    The settings are those of :func:`nkf_model.reconstruct` (``options`` and/or keywords, with the
    same defaults: ``method``, ``resolution``, ``solver``, ``max_centres``, ``reduce_to``,
    ``max_points``, ...). ``estimate_normals``: the normals will be estimated; ``colors``: colours
    will be carried; ``trim``: the surface will be trimmed (default: whether ``options`` trims).
    """
    opts = Options.build(options, **settings)
    return plan_for(n_points, opts, estimate_normals=estimate_normals, colors=colors, trim=trim)


def plan_for(n_points: int, opts: Options, *, estimate_normals: bool, colors: bool = False,
             trim: bool | None = None) -> Estimate:
    """The estimate for ``n_points`` input points run with ``opts`` (after its ``max_points`` subset)."""
    n = max(0, int(n_points))
    if opts.max_points is not None:
        n = min(n, opts.max_points)
    return plan(n, resolution=opts.resolution, estimate_normals=estimate_normals, solver=opts.solver,
                max_centres=opts.max_centres, reduce_to=opts.reduce_to, colors=colors,
                trim=opts.trim is not None if trim is None else trim, method=opts.method)


def plan(
    n_points: int,
    *,
    resolution: int,
    estimate_normals: bool,
    solver: str,
    max_centres: int,
    reduce_to: int | None,
    colors: bool = False,
    trim: bool = False,
    method: str = SETTING["method"].default,
) -> Estimate:
    """The estimate for explicit settings (``reduce_to=None``: no reduction; ``method="nkf"``: the
    learned kernel, see :data:`NKF_EVAL_FACTOR`)."""
    n_in = max(0, int(n_points))
    reduced = reduce_to is not None and n_in > reduce_to
    n = min(n_in, reduce_to) if reduced else n_in
    kind = choose_solver(n, max_centres, solver)
    r = int(resolution)
    nodes = NODES_PER_R2 * r * r

    seconds = FIXED_SECONDS + INPUT_PER_POINT * n_in + MESH_PER_NODE * nodes
    mem_stage = []
    if estimate_normals:
        seconds += NORMALS_PER_POINT * n + (SIGN_CHECK_PER_POINT * n if n <= SIGN_CHECK_MAX_POINTS else 0.0)
        mem_stage.append(BYTES_NORMALS * n)
    m2 = 2 * n
    learned = method == "nkf"
    slow = 1.0  # kernel evaluations at the grid points, against the data-free kernel's
    if learned:
        slow = NKF_EVAL_FACTOR if kind == "pou" else NKF_EVAL_FACTOR_GLOBAL
        seconds += NKF_FIXED_SECONDS
    if kind == "dense":
        seconds += m2**3 / 3 / FLOPS + m2 * m2 / KERNEL_RATE + slow * nodes * m2 / KERNEL_RATE
        mem_stage.append(2 * 8 * m2 * m2)
        mem_stage.append(BYTES_NODE * nodes)
    elif kind == "falkon":
        mc = min(max_centres, m2)
        seconds += mc**3 / FLOPS + FALKON_ITERATIONS * m2 * mc / KERNEL_RATE + slow * nodes * mc / KERNEL_RATE
        mem_stage.append(3 * 8 * mc * mc + 64 * m2)
        mem_stage.append(8 * mc * mc + BYTES_NODE * nodes)
    else:
        seconds += POU_FIT_PER_POINT * n + 3000**3 / 3 / FLOPS + slow * nodes * POU_EVALS_PER_NODE / POU_RATE
        mem_stage.append(BYTES_POU * n)
        mem_stage.append(BYTES_POU * n + BYTES_NODE * nodes)
    if colors or trim:
        seconds += 2e-6 * n + 1e-6 * nodes
    peak = FIXED_BYTES + BYTES_INPUT * n_in + (BYTES_SOLVED + (BYTES_NKF if learned else 0)) * n + max(mem_stage)
    return Estimate(
        points_in=n_in,
        points_solved=n,
        reduced=bool(reduced),
        estimate_normals=bool(estimate_normals),
        solver=kind,
        resolution=r,
        seconds=float(seconds),
        peak_bytes=int(peak),
    )


def enforce(est: Estimate, memory_budget: float | None = None) -> None:
    """Raise :class:`MemoryBudgetError` if ``est`` needs more than ``memory_budget`` bytes.

    The message names the setting that drives the estimate: the exact solve's size
    (``max_centres`` / ``solver``), the reduction target (``reduce_to``), or the resolution.
    """
    budget = default_memory_budget() if memory_budget is None else float(memory_budget)
    if est.peak_bytes <= budget:
        return
    need = est.peak_bytes / GIB
    have = budget / GIB
    n, r = est.points_solved, est.resolution
    if est.solver == "dense" and 16 * (2 * n) ** 2 > est.peak_bytes / 2:
        hint = "lower max_centres (or use solver='auto') so that the exact solve stays small"
    elif est.solver == "falkon" and est.peak_bytes > 2 * (BYTES_NODE * NODES_PER_R2 * r * r):
        hint = "lower max_centres (Nystrom centres)"
    elif BYTES_NODE * NODES_PER_R2 * r * r > 0.4 * est.peak_bytes:
        hint = f"lower the resolution (now {r})"
    else:
        hint = f"lower the point count with reduce_to / max points (now {n:,} points solved)"
    raise MemoryBudgetError(
        f"this reconstruction needs about {need:.1f} GB but the memory budget is {have:.1f} GB; {hint}, "
        f"or raise the memory budget"
    )
