"""Stage 5: evaluate the fitted function on a grid, only near its zero level set.

The grid covers the cube ``[-GRID_HALF, GRID_HALF]^3`` of the unit box with ``resolution`` cells
per side. Instead of all ``(R+1)^3`` nodes, the function is evaluated on a coarse grid (16 to 32
cells per side), and at each finer level only inside the cells whose corners change sign; from there
the fine level follows the surface (a flood fill) into every coarse cell it runs into, so the fine band
is closed even where the coarse grid missed a crossing. The number of evaluations then grows as R^2
(the surface), not R^3.
Node values are kept in hash tables of int64 node keys (compiled loops in
:mod:`nkf_model.surface._flood_kernels`), so memory also grows as R^2.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..points.normalise import GRID_HALF
from . import _flood_kernels as _fk

# The grid spans [-GRID_HALF, GRID_HALF]^3 (points.normalise); its resolution range is the setting's
# (options.MIN_RESOLUTION, options.MAX_RESOLUTION).
COARSEST = 16  # the coarsest level has 16 to 32 cells per side

_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
def levels(resolution: int) -> list[int]:
    """Cells per side of the (padded) grid at each level, coarse to fine.

    The finest level has ``resolution`` cells per side, rounded up to a multiple of ``2**(L-1)`` so
    that every level halves the one after it; the cell size stays ``2 * GRID_HALF / resolution`` and
    the extra cells (fewer than ``2**(L-1)``) lie past the grid's far side, where nothing is meshed.
    The coarsest level has between ``COARSEST`` and ``2 * COARSEST`` cells per side.
    """
    r = int(resolution)
    k = 0
    while (r >> (k + 1)) >= COARSEST:
        k += 1
    step = 1 << k
    top = -(-r // step) * step
    return [top >> (k - i) for i in range(k + 1)]


def node_keys(ijk: np.ndarray, r: int) -> np.ndarray:
    """Flat int64 keys of nodes (N, 3) on a grid with ``r`` cells (``r + 1`` nodes) per side."""
    n = r + 1
    return (ijk[:, 0] * n + ijk[:, 1]) * n + ijk[:, 2]


def cell_keys(ijk: np.ndarray, r: int) -> np.ndarray:
    """Flat int64 keys of cells (N, 3) on a grid with ``r`` cells per side."""
    return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]


def cells_from_keys(keys: np.ndarray, r: int) -> np.ndarray:
    """Inverse of :func:`cell_keys`: (N, 3) int64."""
    return np.stack([keys // (r * r), (keys // r) % r, keys % r], axis=1)


def node_positions(ijk: np.ndarray, r: int, cell: float | None = None) -> np.ndarray:
    """Unit-box positions (N, 3) float64 of nodes on the ``r``-cell grid (cell size ``cell``,
    default ``2 * GRID_HALF / r``)."""
    return -GRID_HALF + ijk * (2.0 * GRID_HALF / r if cell is None else cell)


@dataclass
class SparseField:
    """Function values at the nodes around the zero level set of the finest grid.

    Attributes
    ----------
    resolution : int
        Cells per side of the finest grid over the box ``[-GRID_HALF, GRID_HALF]^3``.
    keys : (T,) int64
        Hash table (open addressing, -1 for an empty slot; see :mod:`nkf_model.surface._flood_kernels`) of
        the :func:`node_keys` of the nodes with known values, on the padded grid of
        ``grid_cells`` cells per side (see :func:`levels`).
    values : (T,) float64
        Function values in the slots of ``keys``.
    band : (B, 3) int64
        Finest-grid cells (each index below ``resolution``) whose eight corners are known and change
        sign.
    evaluations : int
        Number of points at which the function was evaluated, over all levels.
    level_evaluations : list of (int, int)
        (cells per side, points evaluated) for each level.
    grid_cells : int
        Cells per side of the padded finest grid (>= ``resolution``).
    """

    resolution: int
    keys: np.ndarray
    values: np.ndarray
    band: np.ndarray
    evaluations: int
    level_evaluations: list
    grid_cells: int = 0

    def __post_init__(self):
        if not self.grid_cells:
            self.grid_cells = self.resolution

    def lookup(self, ijk: np.ndarray) -> np.ndarray:
        """Values at nodes (N, 3); NaN where unknown."""
        return _fk.lookup(self.keys, self.values, np.ascontiguousarray(node_keys(ijk, self.grid_cells)))


def _crossing_dense(v: np.ndarray) -> np.ndarray:
    """Cells (N, 3) of a dense node array (r+1, r+1, r+1) whose corners are not all of one sign."""
    neg = v < 0
    anyneg = np.zeros(tuple(d - 1 for d in v.shape), dtype=bool)
    allneg = np.ones_like(anyneg)
    for a, b, c in _CORNERS:
        sub = neg[a : a + anyneg.shape[0], b : b + anyneg.shape[1], c : c + anyneg.shape[2]]
        anyneg |= sub
        allneg &= sub
    return np.argwhere(anyneg & ~allneg).astype(np.int64)


def evaluate_sparse(
    f: Callable[[np.ndarray], np.ndarray],
    resolution: int,
    *,
    chunk: int = 65536,
    cancel_poll: Callable[[], None] | None = None,
    step: Callable[[float], None] | None = None,
    seeds: np.ndarray | None = None,
    close: bool = False,
    node_f: Callable[[np.ndarray, np.ndarray, tuple], np.ndarray] | None = None,
) -> SparseField:
    """Evaluate ``f`` coarse to fine around its zero level set.

    Parameters
    ----------
    f : callable
        ``f(points)`` with unit-box points (N, 3) float64, returning (N,) float64.
    resolution : int
        Cells per side of the finest grid.
    chunk : int
        Points per call of ``f``.
    check : callable
        Raises to cancel; called between chunks.
    step : callable
        ``step(fraction)`` progress within this stage.
    seeds : (S, 3) float, optional
        Unit-box points known to lie on the surface (the input points). The cells holding them are
        refined at every level, so no part of the surface near the data can be missed by the coarse
        grid.
    close : bool
        Treat the function as positive (outside) on the grid's faces, so that the mesh is capped
        where the zero level set would run out of the grid (a watertight mesh).
    node_f : callable, optional
        Called instead of ``f`` as ``node_f(points, keys, level)`` with the same points and chunks,
        the nodes' :func:`node_keys` (K,) int64 and ``level = (r, cell)`` (cells per side of that
        level's grid and its cell size): the node ``keys[i]`` of ``level`` is always at ``points[i]``,
        so a caller can keep what does not change between calls per node (the learned features at the
        grid's nodes: ``nkf_model.pipeline.fitted``). It must return what ``f(points)`` returns.

    Returns
    -------
    SparseField
    """
    lv = levels(resolution)
    finest_cell = 2.0 * GRID_HALF / resolution
    top = lv[-1]

    def seed_cells(r):
        if seeds is None or len(seeds) == 0:
            return np.zeros((0, 3), dtype=np.int64)
        h = finest_cell * top / r
        c = np.floor((np.asarray(seeds, dtype=np.float64) + GRID_HALF) / h).astype(np.int64)
        c = np.clip(c, 0, r - 1)
        return cells_from_keys(np.unique(cell_keys(c, r)), r)
    total_done = 0
    per_level = []

    def run(ijk, r, expected_rest):
        nonlocal total_done
        out = np.empty(len(ijk))
        cell = finest_cell * top / r
        pts = node_positions(ijk, r, cell)
        nkeys = None if node_f is None else node_keys(ijk, r)
        for s in range(0, len(ijk), chunk):
            if cancel_poll is not None:
                cancel_poll()
            if node_f is None:
                out[s : s + chunk] = f(pts[s : s + chunk])
            else:
                out[s : s + chunk] = node_f(pts[s : s + chunk], nkeys[s : s + chunk], (r, cell))
            if step is not None:
                done = total_done + min(len(ijk), s + chunk)
                step(done / max(1, done + expected_rest + (len(ijk) - min(len(ijk), s + chunk))))
        total_done += len(ijk)
        if close:
            # Nodes on or past the grid's faces count as outside (|f|), so that a surface that runs
            # into the grid's bounds is capped there instead of left open.
            fine_ijk = ijk * (top // r)
            edge = ((fine_ijk <= 0) | (fine_ijk >= resolution)).any(axis=1)
            out[edge] = np.abs(out[edge])
        return out

    r = lv[0]
    g = np.arange(r + 1, dtype=np.int64)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    # Rough guess of the work left after the coarse grid: each finer level costs about as much.
    dense = run(nodes, r, expected_rest=len(nodes) * (len(lv) - 1))
    per_level.append((r, len(nodes)))
    crossing = _crossing_dense(dense.reshape(r + 1, r + 1, r + 1))
    keys, values = _fk.new_table(len(nodes))
    _fk.insert(keys, values, node_keys(nodes, r), dense)

    for li in range(1, len(lv)):
        r_prev, r = lv[li - 1], lv[li]
        remaining_levels = len(lv) - 1 - li
        extra = seed_cells(r_prev)
        if len(extra):
            crossing = cells_from_keys(np.union1d(cell_keys(crossing, r_prev), cell_keys(extra, r_prev)), r_prev)
        # Flood fill along the surface: evaluate the children of the coarse crossing cells, then of
        # every coarse cell the fine surface runs into, until the fine band is closed. The node
        # values of this level and the parents already visited live in hash tables (compiled loops
        # in nkf_model.surface._flood_kernels); only the function evaluations run here.
        tk, tv = _fk.new_table(27 * len(crossing))
        dk, dv = _fk.new_table(7 * len(crossing))
        fine = []
        frontier = np.ascontiguousarray(crossing, dtype=np.int64)
        evaluated = 0
        while len(frontier):
            tk, tv = _fk.grow(tk, tv, 27 * len(frontier))
            dk, dv = _fk.grow(dk, dv, 7 * len(frontier))
            if cancel_poll is not None:
                cancel_poll()
            slots, todo_ijk, todo_slots = _fk.gather(frontier, r, tk, tv, keys, values, r_prev, dk)
            tv[todo_slots] = run(todo_ijk, r, expected_rest=4 * len(todo_slots) * remaining_levels)
            evaluated += len(todo_slots)
            if cancel_poll is not None:
                cancel_poll()
            cells, frontier = _fk.advance(frontier, slots, tv, r_prev, dk)
            fine.append(cells)
        keys, values = tk, tv
        per_level.append((r, evaluated))
        # A fine cell is the child of only one parent, and each parent is visited once: no repeats.
        crossing = np.concatenate(fine) if fine else np.zeros((0, 3), dtype=np.int64)
    band = crossing[(crossing < resolution).all(axis=1)]

    if step is not None:
        step(1.0)
    return SparseField(
        resolution=resolution,
        keys=keys,
        values=values,
        band=band,
        evaluations=total_done,
        level_evaluations=per_level,
        grid_cells=top,
    )


def evaluate_dense(f: Callable[[np.ndarray], np.ndarray], resolution: int, chunk: int = 65536) -> np.ndarray:
    """All ``(R+1)^3`` node values as an array indexed ``[i, j, k]`` (for tests and comparisons)."""
    g = np.arange(resolution + 1, dtype=np.int64)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = node_positions(nodes, resolution)
    out = np.concatenate([f(pts[s : s + chunk]) for s in range(0, len(pts), chunk)])
    return out.reshape(resolution + 1, resolution + 1, resolution + 1)
