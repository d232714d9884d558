"""The learned kernel's safeguard against balloons: a surface that bulges far beyond sparse points.

At 300 points the learned kernel sometimes closes a limb or an open side with a large smooth bulge
where the data-free kernel (Neural Splines) stays near the points. On the 128 held-out meshes of
the gate (docs/nkf.md, "The gate on held-out sources") the six inputs whose learned surface reached
beyond 0.3 of the points' bounding-box diagonal outside that box were all losses, four of them
catastrophic (Animated_Human -0.77 IoU); on the other 122 the learned surface reached at most 0.14,
and where the data-free one reached as far (Peach, Spider, Trex) the learned one was not worse.

The check: the fitted function's sign on a coarse lattice of the grid's box, at the nodes farther
than ``REACH_MARGIN`` diagonals outside the points' box. The *reach* of a function is the largest
such distance (in diagonals, the Chebyshev distance to the box) of a node it puts inside (value
below 0). When the learned function reaches ``REACH_LIMIT`` or more, the data-free kernel is fitted
to the same points too, and used instead when its reach is at least ``REACH_MARGIN`` smaller.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Lattice nodes per side over the grid's box (unit-box units): 24 nodes, 0.048 apart in the box
# of half-width 0.55; the balloons measured were 0.3 to 0.5 diagonals beyond the points' box.
CHECK_NODES = 24
# Reach (diagonals beyond the points' box) from which the learned surface is compared with the
# data-free one: above every learned surface that did not lose (at most 0.14), below every
# balloon (at least 0.32).
REACH_LIMIT = 0.2
# The data-free surface is used when it reaches at least this much less far; nodes closer than this
# to the points' box are not looked at.
REACH_MARGIN = 0.1


@dataclass
class CheckNodes:
    """Lattice nodes beyond the points' box.

    Attributes
    ----------
    points : (Q, 3) float64
        Nodes (unit-box units) farther than ``REACH_MARGIN`` diagonals outside the points' box.
    reach : (Q,) float64
        Their Chebyshev distance to that box, in diagonals of it.
    """

    points: np.ndarray
    reach: np.ndarray

    @classmethod
    def around(cls, x: np.ndarray, box_half: float, nodes: int = CHECK_NODES) -> CheckNodes:
        """The nodes of a ``nodes``-per-side lattice of ``[-box_half, box_half]^3`` beyond the box of
        ``x`` (N, 3) by more than ``REACH_MARGIN`` of its diagonal."""
        lo, hi = x.min(axis=0), x.max(axis=0)
        diag = float(np.linalg.norm(hi - lo))
        g = np.linspace(-box_half, box_half, nodes)
        q = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        rel = np.maximum(lo - q, q - hi).max(axis=1) / max(diag, 1e-12)
        keep = rel > REACH_MARGIN
        return cls(np.ascontiguousarray(q[keep]), rel[keep])

    def reach_of(self, values: np.ndarray) -> float:
        """How far (diagonals) a function with ``values`` (Q,) at the nodes puts inside beyond the box:
        the largest ``reach`` of a node with a negative value, 0 if none."""
        inside = np.asarray(values) < 0
        return float(self.reach[inside].max()) if inside.any() else 0.0


@dataclass
class BalloonCheck:
    """What the check found (``Mesh.stats["balloon_check"]``).

    Attributes
    ----------
    learned_reach : float
        How far the learned surface reaches beyond the points' box, in diagonals (0: not beyond
        ``REACH_MARGIN``).
    data_free_reach : float or None
        The same for the data-free kernel's surface; None when it was not fitted (the learned reach
        was under ``REACH_LIMIT``).
    used : str
        ``"nkf"`` or ``"splines"``: whose function the mesh comes from.
    """

    learned_reach: float
    data_free_reach: float | None
    used: str

    @property
    def fell_back(self) -> bool:
        return self.used == "splines"

    def message(self) -> str:
        """One line for the user when the check fell back, else ''."""
        if not self.fell_back:
            return ""
        return (
            f"the learned kernel's surface bulged {self.learned_reach:.2f} of the points' diagonal beyond them "
            f"(the data-free kernel's: {self.data_free_reach:.2f}): used the data-free kernel (splines) for this "
            "fit; the balloon check off (Check Learned Surface, --no-balloon-check) keeps the learned one"
        )


def needs_data_free(learned_reach: float) -> bool:
    """Whether a learned surface reaching ``learned_reach`` diagonals beyond the points is compared
    with the data-free one."""
    return learned_reach >= REACH_LIMIT


def prefer_data_free(learned_reach: float, data_free_reach: float) -> bool:
    """Whether the data-free surface replaces a learned one that reaches ``learned_reach``."""
    return needs_data_free(learned_reach) and data_free_reach <= learned_reach - REACH_MARGIN
