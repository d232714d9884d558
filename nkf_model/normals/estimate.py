"""Normals for point clouds that have none: PCA estimation and consistent orientation.

Two steps, both on the CPU with SciPy:

1. :func:`pca_normals`: the normal of each point is the direction of least variance of its ``k``
   nearest neighbours (a KD-tree query and a batched 3x3 eigen-decomposition), refitted twice with
   weights ``exp(-(r / sigma)^2)`` of each neighbour's distance ``r`` to the current plane, starting
   from the 7 nearest: on a plate thinner than the neighbourhood, plain PCA mixes both faces into a
   meaningless normal, the reweighted fit keeps to the point's own face. Its sign is arbitrary.
2. :func:`orient_normals`: consistent signs, in six steps.

   a. Seeds from views. Every point is drawn as a disc in its tangent plane into depth buffers: 64
      orthographic views from all around (``"outward"``, closed objects), from the upper half
      (``"up"``, terrain), or the six cube-map faces of each scanner position (``"viewpoint"``).
      A point seen face-on votes for the side of its normal that faces the viewer; points whose
      votes agree (at least half of the weight, seen in about 3 views or more; one clear view
      for scanners) are seeds. Points seen from almost nowhere (inside a cup, between touching
      parts) are not.
      Thin walls: where the two faces of a wall are closer than the views' depth tolerance, the
      views see both; a point whose neighbours include another layer on the viewer's side
      (:func:`layer_sides`) is hidden from that view, so the inner face of a thin-walled cup is
      not seeded with its outer face's sign.
      Thin parts: where the two faces of a plate are closer than the views' depth tolerance, a
      view sees both and its votes cancel. There a point whose nearby parallel points all lie on
      one side of its plane (the plate's other face) is seeded with the normal pointing away from
      them (:func:`layer_votes`); that holds for a solid plate and not for the facing sides of a
      narrow gap, so it is used only on connected layer regions whose view-seeded points agree
      with it and lie on both faces (:func:`_layer_seeds`), and only in the global fit of step c,
      not as a seed of b. Both faces, because a misregistered scan is layered too: two copies of
      one surface, the inner one hidden from every view, so the seeds on the outer one agree with
      their votes by construction while the inner one's votes point inward.
   b. Propagation from the seeds along a minimum spanning tree of the neighbour graph (Hoppe et
      al., SIGGRAPH 1992; the seeds hang from a virtual root). Edge ``(i, j)`` with unit offset
      ``d`` costs ``1 - |n_i . n_j| + min(a, 2 - a)``, ``a = |n_i . d| + |n_j . d|``: cheap both
      along the surface (``a`` near 0, the normals agree) and straight across a thin plate or a
      narrow gap (``a`` near 2, the outward normals point opposite ways; Hoppe's rule would make
      them agree and fail there); at sharp edges (normals over 60 degrees apart) the edge is taken
      as convex.
   c. Clean-up: an undecided piece (joined by confident edges) flips as a whole when its edges to
      decided points vote against it; then all confident edges and seeds vote at once in one
      sparse least-squares fit of real-valued signs (:func:`_harmonic_signs`, a signed harmonic
      propagation: one wrong edge no longer flips a whole branch of the tree); then single points
      flip where their neighbours and views clearly disagree with them (iterated conditional
      modes).
   d. Closed objects (``"outward"``): the winding number of the oriented cloud (:func:`_winding_signs`).
      Its gradient at a point, from the rest of the surface, points inward; points the views did
      not seed take the sign that agrees with it, a few rounds over. That reaches faces hidden
      inside other parts and behind lids, which the graph decides poorly.
   e. Closed objects of at most 20,000 points: a small network trained on the corpus's ``train``
      split reads every step's evidence per point and flips the signs it finds still wrong
      (:mod:`nkf_model.normals.sign_check`).
   f. Hoppe's tangent-plane propagation from the result, each piece taking the side most of its
      points have, kept only when it agrees clearly better with the edge relations
      (:func:`nkf_model.normals.consistent.tangent_plane_check`): views that look into an unscanned
      opening seed whole faces from the inside, and this takes them back.

Noise: the noise level of the cloud (the flattest quarter's plane-fit residual) widens the depth
tolerance of the views and keeps offsets along the normals that are within the noise from being
read as "across a thin plate". Overlapping scans that do not register exactly are layered all over,
copies of one surface a fraction of a spacing apart on either side of each other; where the signs of
the propagation read so (:func:`layer_balance`), the orientation stops there and starts again with
twice the noise level, so that those offsets are noise, not thin parts, and with views whose discs
reach only each point's neighbours (:func:`splat_radii`: dense range images need no wider ones, and
wider ones hide thin rods). Large clouds are voted on a random subset of 40,000 points.

All positions are in the caller's units; the functions are scale-free (neighbour offsets are
normalised).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

from ..errors import InvalidParameterError
from . import sign_check
from ._pca_kernels import weighted_planes
from ._propagate import first_points, spanning_order
from ._propagate import propagate_signs as _propagate_signs
from .edges import SIG_NOISE, WINDING_EXCLUDE, across_significant, edge_relation, relation_matrix

DEFAULT_K = 16  # neighbours for the PCA fit
# Above this many points the signs come from a voxel-averaged copy of at most this many points
# (:func:`_estimate_coarse`), each point taking the sign its COARSE_VOTERS nearest coarse normals vote for.
COARSE_POINTS = 50_000
COARSE_VOTERS = 4
# Inputs of IRREGULAR_MIN_POINTS or more (up to COARSE_POINTS) are oriented on their regular points
# (_estimate_regular): those whose IRREGULAR_NEIGHBOURS nearest neighbours lie within IRREGULAR_RATIO
# times the median mean distance. Measured (2026-12-06, docs/real_scans.md): on the simulated all-round
# scan of quaternius__Tree4 (1,448 mixed pixels left by the outlier test) 3.6 % of the surface points'
# signs wrong -> 1.9 % (1.1 % of its surface points and 341 of the mixed pixels left out), F-score
# 0.956 -> 0.976, and its turntable scan in one piece instead of two; bench_range_scans' all-round
# means Chamfer-L1 0.00262 -> 0.00260, F 0.9491 -> 0.9506; the normal-estimation benchmark (clean
# samples of 10,000 points, where the left-out points are sampling chance) 0.0176 -> 0.0178 IoU lost.
IRREGULAR_NEIGHBOURS = 16
IRREGULAR_RATIO = 1.6
IRREGULAR_MIN_POINTS = 10_000
DEFAULT_GRAPH_K = 10  # neighbours per point in the orientation graph
INITIAL_K = 7  # neighbours of the first plane fit
REWEIGHTS = 2  # refits with weights that fade off the plane
SIGMA = 1.0  # width of that fade, in mean distances to the 4 nearest neighbours
ORIENTATIONS = ("outward", "up", "viewpoint")
_CHUNK = 25_000  # points per KD-tree query / eigen-decomposition batch (about 0.2 s)

CancelPoll = Optional[Callable[[], None]]


@dataclass
class OrientationInfo:
    """What :func:`orient_normals` did.

    Attributes
    ----------
    orientation : str
        The hint used: ``"outward"``, ``"up"`` or ``"viewpoint"``.
    pieces : int
        Connected pieces of the neighbour graph (each oriented on its own).
    seeded : int
        Points whose sign the views decided (the rest was propagated from them).
    spacing : float
        Median nearest-neighbour distance of the points, in their units.
    learned_check : bool
        Whether the learned sign check ran (:mod:`nkf_model.normals.sign_check`: ``"outward"``, at most
        :data:`~nkf_model.normals.sign_check.MAX_POINTS` points, ``safetensors`` installed).
    learned_flips : int
        Points it flipped.
    consistent_flips : int
        Points the last check (:func:`nkf_model.normals.consistent.tangent_plane_check`) flipped.
    misregistered : bool
        Whether the cloud read as overlapping scans that do not register exactly (:func:`layer_balance`)
        and was oriented again with a wider noise level.
    """

    orientation: str
    pieces: int
    seeded: int = 0
    spacing: float = 0.0
    learned_check: bool = False
    learned_flips: int = 0
    consistent_flips: int = 0
    misregistered: bool = False


def check_viewpoints(viewpoints) -> Optional[np.ndarray]:
    """``None``, or viewpoints as a (K, 3) float64 array; raises :class:`InvalidParameterError`."""
    if viewpoints is None:
        return None
    try:
        v = np.asarray(viewpoints, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"viewpoints must be numbers (x, y, z), got {viewpoints!r}") from None
    if v.ndim == 1:
        v = v[None, :]
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise InvalidParameterError(f"viewpoints must have shape (3,) or (K, 3), got {np.shape(viewpoints)}")
    if not np.isfinite(v).all():
        raise InvalidParameterError("viewpoints must be finite")
    return v


def check_orientation(orientation, viewpoints) -> str:
    """The orientation rule to use: ``orientation`` if given, else ``"viewpoint"`` when viewpoints
    are given, else ``"outward"``."""
    if orientation is None:
        return "viewpoint" if viewpoints is not None else "outward"
    if orientation not in ORIENTATIONS:
        raise InvalidParameterError(f"orientation must be one of {', '.join(ORIENTATIONS)}; got {orientation!r}")
    if orientation == "viewpoint" and viewpoints is None:
        raise InvalidParameterError("orientation 'viewpoint' needs the scanner positions: pass viewpoints")
    return orientation


def pca_normals(points: np.ndarray, k: int = DEFAULT_K, tree: Optional[cKDTree] = None, cancel_poll: CancelPoll = None,
                at: Optional[np.ndarray] = None):
    """Unoriented unit normals by PCA over the ``k`` nearest neighbours.

    Parameters
    ----------
    points : (N, 3) float64
        Positions (any units).
    k : int
        Neighbours per point, the point itself included (clipped to N).
    tree : cKDTree, optional
        A tree already built on ``points``.
    at : (M,) int64, optional
        Only these points' normals (their neighbours still come from all of ``points``); default all.

    Returns
    -------
    normals : (N, 3) float64
        Unit vectors, sign arbitrary (M rows with ``at``).
    residual : (N,) float64
        (M rows with ``at``.) Weighted root-mean-square distance of the neighbours to the fitted plane (weights of the
        last refit), in the units of ``points``: the local noise level (0 on an exact plane).
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    k = int(min(max(k, 3), len(p)))
    tree = tree if tree is not None else cKDTree(p)
    q = p if at is None else p[at]
    n = len(q)
    normals = np.empty((n, 3))
    residual = np.empty(n)
    k0 = min(k, INITIAL_K)
    for s in range(0, n, _CHUNK):
        if cancel_poll is not None:
            cancel_poll()
        e = min(n, s + _CHUNK)
        dist, idx = tree.query(q[s:e], k=k, workers=-1)
        nb = p[idx]  # (c, k, 3)
        sigma = SIGMA * dist[:, 1 : min(k, 5)].mean(axis=1) + 1e-300
        # Two starts: the few nearest neighbours (one face of a thin plate) and all k (plain PCA).
        # Each is refitted with weights that fade off its plane; the fit that keeps the most
        # neighbours on its plane wins. Noise: the spread of the neighbours that the fit kept
        # (weights near 1) around the plane; the other face of a thin plate has weights near 0
        # and does not inflate it.
        weighted_planes(nb, sigma, k0, REWEIGHTS, normals[s:e], residual[s:e])
    return normals, residual


def _graph(points, normals, tree, k, cancel_poll: CancelPoll, noise=None):
    """Symmetric k-nearest-neighbour graph with orientation costs as a sparse matrix."""
    n = len(points)
    k = int(min(k + 1, n))
    rows, cols, cost = [], [], []
    for s in range(0, n, _CHUNK):
        if cancel_poll is not None:
            cancel_poll()
        e = min(n, s + _CHUNK)
        dist, idx = tree.query(points[s:e], k=k, workers=-1)
        i = np.repeat(np.arange(s, e), k - 1)
        j = idx[:, 1:].reshape(-1)
        d = dist[:, 1:].reshape(-1)
        ok = (j < n) & (d > 0)
        i, j, d = i[ok], j[ok], d[ok]
        off = (points[j] - points[i]) / d[:, None]
        cos = np.abs(np.sum(normals[i] * normals[j], axis=1))
        across = np.abs(np.sum(normals[i] * off, axis=1)) + np.abs(np.sum(normals[j] * off, axis=1))
        # Along the surface (offset in both tangent planes) or straight across a thin plate or gap
        # (offset along both normals): either is a confident edge; anything between is not. An
        # offset along the normals within the noise is noise: the edge runs along the surface.
        sig = across_significant(across, d, i, j, noise)
        c = (1.0 - cos) + np.where(sig, np.minimum(across, 2.0 - across), 0.3 * across)
        rows.append(i)
        cols.append(j)
        cost.append(c + 1e-9)  # explicit zeros would be read as missing edges
    g = coo_matrix((np.concatenate(cost), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    return g.maximum(g.T)  # symmetric (an edge found from either end)


def fibonacci_directions(n: int, upper_only: bool = False) -> np.ndarray:
    """``n`` unit vectors (n, 3) spread evenly over the sphere (or the upper half, z > 0)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n if upper_only else 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _basis(d):
    """Two unit vectors (3,), (3,) completing the unit direction ``d`` to an orthonormal basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(d, helper)
    a /= np.linalg.norm(a)
    return a, np.cross(d, a)


def visibility_votes(points, normals, spacing, *, directions=None, viewpoints=None, noise: float = 0.0,
                     layers=None, cancel_poll: CancelPoll = None, depths=None, follow_neighbours: bool = False):
    """Signed votes (N,) for each normal from the views in which its point is visible.

    A view is an orthographic projection along one of ``directions`` (unit vectors pointing from
    the viewer into the scene), or a pinhole camera at one of ``viewpoints`` (six 90-degree faces of
    a cube map). Each point is drawn as a disc in its tangent plane (radius: :func:`splat_radii`,
    3 spacings, or with ``follow_neighbours`` 1 to 3) into a depth buffer; a point is visible when
    nothing lies more than ``spacing / 2`` (plus :data:`TOL_NOISE` noise levels) in front of it.
    A visible point whose normal makes an angle under 78 degrees with the line of sight votes
    ``+|cos|`` if its normal faces the viewer and ``-|cos|`` if not; the votes are summed.
    ``layers``: two (N,) bool arrays, whether another layer lies on the side each normal points to
    and on the other side (:func:`layer_sides`); a point with one on its viewer's side is hidden
    from that view, however close the layers are. ``depths``: :func:`view_depths` of the same
    points and views, as a list (one drawing for several noise levels). Returns votes (N,) and
    their weights (N,).
    """
    if depths is None:
        depths = view_depths(points, normals, spacing, directions=directions, viewpoints=viewpoints,
                             cancel_poll=cancel_poll, follow_neighbours=follow_neighbours)
    n = len(points)
    votes = np.zeros(n)
    weight = np.zeros(n)
    tol = 0.5 * spacing + TOL_NOISE * noise
    for margin, cosang in depths:
        use = (margin <= tol) & (np.abs(cosang) > 0.2)
        if layers is not None:
            # Another layer between the point and the viewer hides it, however close.
            use &= ~np.where(cosang < 0, layers[0], layers[1])
        votes[use] -= cosang[use]  # the normal faces the viewer when it points against the ray
        weight[use] += np.abs(cosang[use])
    return votes, weight


def view_depths(points, normals, spacing, *, directions=None, viewpoints=None, cancel_poll: CancelPoll = None,
                follow_neighbours: bool = False):
    """Each view's depth buffer, read at every point: ``(margin (N,), cos (N,))`` per view, one view
    at a time (a generator), for :func:`visibility_votes` (views and drawing as there).

    ``margin``: how far the point lies behind the nearest drawn surface at its pixel, in the units of
    ``points`` (infinite outside the image); ``cos``: the cosine between its normal and the line of
    sight. Neither depends on the noise level, so one drawing serves every depth tolerance.
    ``follow_neighbours``: discs as :func:`splat_radii` draws them for misregistered scans."""
    from . import _orient_kernels as ok

    p = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    radius = splat_radii(p, spacing, follow_neighbours)
    pixel = 0.5 * spacing
    views = []  # (origin (3,), a, b, d, perspective)
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    if directions is not None:
        for d in np.asarray(directions, dtype=np.float64):
            d = d / np.linalg.norm(d)
            a, b = _basis(d)
            views.append((centre, a, b, d, False))
    if viewpoints is not None:
        axes = np.eye(3)
        for s in np.asarray(viewpoints, dtype=np.float64):
            for k in range(3):
                for sgn in (1.0, -1.0):
                    d = sgn * axes[k]
                    a, b = _basis(d)
                    views.append((s, a, b, d, True))
    for origin, a, b, d, perspective in views:
        if cancel_poll is not None:
            cancel_poll()
        rel = p - origin
        u = rel @ a
        v = rel @ b
        w = rel @ d
        na, nb_, nd = nrm @ a, nrm @ b, nrm @ d
        if perspective:
            front = w > 1e-9 * max(1.0, float(np.abs(w).max()))
            wf = np.where(front, w, np.inf)
            u = np.where(front, u / wf, np.inf)
            v = np.where(front, v / wf, np.inf)
            dist = np.linalg.norm(rel, axis=1)
            ray = rel / np.maximum(dist, 1e-300)[:, None]
            cosang = np.sum(nrm * ray, axis=1)
            inside = front & (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
            # Angular disc radius and pixel size at each point's distance.
            wmin = float(w[inside].min()) if inside.any() else 1.0
            pix = pixel / max(float(np.median(w[inside])) if inside.any() else 1.0, wmin)
            margin = ok.zbuffer_margin(u, v, dist, np.zeros_like(u), np.zeros_like(u), radius / np.maximum(w, 1e-300),
                                       inside, pix, -1.0, 1.0)
        else:
            cosang = nd
            slope_u = np.clip(-na / np.where(np.abs(nd) > 1e-6, nd, 1e-6), -3.0, 3.0)
            slope_v = np.clip(-nb_ / np.where(np.abs(nd) > 1e-6, nd, 1e-6), -3.0, 3.0)
            half = float(max(np.abs(u).max(), np.abs(v).max()) + radius.max())
            margin = ok.zbuffer_margin(u, v, w, slope_u, slope_v, radius,
                                       np.ones(len(p), dtype=np.bool_), pixel, -half, half)
        yield margin, cosang


def splat_radii(points: np.ndarray, spacing: float, follow_neighbours: bool = False) -> np.ndarray:
    """Disc radius (N,) of each point in the visibility views, in the units of ``points``.

    :data:`SPLAT_RADIUS` spacings; with ``follow_neighbours`` each disc reaches only the point's
    :data:`SPLAT_NEIGHBOUR`-th nearest neighbour (from :data:`SPLAT_MIN` to :data:`SPLAT_RADIUS`
    spacings): wide enough to close the gaps between dense points, no wider, since a disc in the
    tangent plane stands off a curved surface (by r^2 / 2R) and on a rod a few spacings across hides
    the points next to it from every view. Used for clouds read as misregistered scans
    (:func:`misregistered`); on clean 10,000-point samples it cost the normal gate (docs/real_scans.md).
    """
    n = len(points)
    if not follow_neighbours or n <= SPLAT_NEIGHBOUR:
        return np.full(n, SPLAT_RADIUS * spacing)
    d, _ = cKDTree(points).query(points, k=SPLAT_NEIGHBOUR + 1)
    return np.clip(d[:, -1], SPLAT_MIN * spacing, SPLAT_RADIUS * spacing)


CONSENSUS_ROUNDS = 30


def _consensus(g, points, normals, sign, votes, cancel_poll: CancelPoll, rounds: int = CONSENSUS_ROUNDS, noise=None):
    """Flip isolated wrong signs: repeatedly give each point the sign its neighbours and its own
    view votes agree on (iterated conditional modes on ``-sum_ij A_ij s_i s_j - sum_i v_i s_i``).
    Only points whose evidence clearly disagrees with their sign flip, so the iteration settles."""
    a = relation_matrix(g, points, normals, noise)
    s = sign.copy()
    for _ in range(rounds):
        if cancel_poll is not None:
            cancel_poll()
        field = a @ s + votes
        flip = field * s < -0.5
        if not flip.any():
            break
        s[flip] *= -1.0
    return s


def _components(n, rows, cols):
    """Connected components ``(count, labels (n,))`` of the graph on ``n`` points with edges
    ``(rows[e], cols[e])``."""
    from scipy.sparse.csgraph import connected_components  # only when estimating: not on every import

    return connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)


def _flip_pieces(g, points, normals, sign, seed, cancel_poll: CancelPoll, rounds: int = 3, noise=None):
    """Flip whole undecided pieces that disagree with their surroundings.

    Points the views did not decide, joined by confident edges (cost < 0.5), form pieces (say the
    hidden facing sides of two objects that nearly touch). The spanning tree ties each piece to the
    rest by one edge, which at a sharp edge is a guess; here every edge between the piece and the
    rest votes, and the piece flips when the votes (``sum r_ij s_i s_j``) say it disagrees."""
    g = g.tocoo()
    i, j, cost = g.row, g.col, g.data
    free = seed == 0
    inner = free[i] & free[j] & (cost < 0.5)
    n = len(sign)
    n_pieces, labels = _components(n, i[inner], j[inner])
    rel = edge_relation(points, normals, i, j, noise)
    boundary = free[i] & (labels[i] != labels[j])
    bi, bj, br = i[boundary], j[boundary], rel[boundary]
    # Edges to points the views decided count fully; to other undecided pieces (which may be
    # wrong themselves) a quarter.
    bw = np.where(free[bj], 0.25, 1.0)
    s = sign.copy()
    for _ in range(rounds):
        if cancel_poll is not None:
            cancel_poll()
        vote = np.bincount(labels[bi], weights=bw * br * s[bi] * s[bj], minlength=n_pieces)
        flip = vote < 0
        if not flip.any():
            break
        s[free & flip[labels]] *= -1.0
    return s


def layer_sides(points, normals, spacing, tree, noise: float = 0.0, cancel_poll: CancelPoll = None, index=None):
    """Points of another layer above and below each point's plane: counts (N,), (N,) (int64), or
    (M,), (M,) for the points ``index`` (M,) only.

    Among the :data:`LAYER_K` nearest neighbours within :data:`LAYER_RADIUS` spacings, those with
    nearly parallel normals (``|n_i . n_j| > LAYER_PARALLEL``) whose offset ``h`` along ``n_i``
    exceeds :data:`LAYER_OFFSET` spacings (and :data:`SIG_NOISE` noise levels) beyond what the
    surface's bending explains belong to another layer: the other face of a thin part, or the far
    side of a narrow gap. A neighbour on the same curved sheet, at lateral distance ``t`` with
    normals ``theta`` apart, lies ``t * tan(theta / 2)`` off the plane (exact on a circle), so
    only ``|h| - t * tan(theta / 2)`` counts: the inside of a bowl is no layer.
    ``above`` counts the layer points on the side ``n_i`` points to, ``below`` the others.
    """
    p = points
    index = np.arange(len(p)) if index is None else np.asarray(index)
    n = len(index)
    k = int(min(LAYER_K + 1, len(p)))
    above = np.zeros(n, dtype=np.int64)
    below = np.zeros(n, dtype=np.int64)
    reach = LAYER_RADIUS * spacing
    min_h = max(LAYER_OFFSET * spacing, SIG_NOISE * noise)
    for s in range(0, n, _CHUNK):
        if cancel_poll is not None:
            cancel_poll()
        e = min(n, s + _CHUNK)
        q = index[s:e]
        dist, idx = tree.query(p[q], k=k, workers=-1)
        dist, idx = dist[:, 1:], idx[:, 1:]
        nrm = normals[q]
        h = np.einsum("cki,ci->ck", p[idx] - p[q, None, :], nrm)
        cos = np.minimum(np.abs(np.einsum("cki,ci->ck", normals[idx], nrm)), 1.0)
        lateral = np.sqrt(np.maximum(dist * dist - h * h, 0.0))
        bend = lateral * np.sqrt((1.0 - cos) / (1.0 + cos))  # t * tan(theta / 2)
        near = (dist < reach) & (cos > LAYER_PARALLEL)
        off = np.abs(h) - bend > min_h
        above[s:e] = (near & off & (h > 0)).sum(axis=1)
        below[s:e] = (near & off & (h < 0)).sum(axis=1)
    return above, below


def layer_votes(points, normals, spacing, tree, noise: float = 0.0, cancel_poll: CancelPoll = None,
                sides=None) -> np.ndarray:
    """Which side of each point its thin part's other face lies on: votes (N,) in {-1, 0, +1}.

    From :func:`layer_sides` (or ``sides``, its result): when at least :data:`LAYER_MIN` layer
    points lie below the plane and none above, the vote is +1 (for a solid plate, the outward
    normal points away from its other face); the mirror case gives -1; anything else (no other
    layer, layers on both sides) gives 0.
    """
    above, below = sides if sides is not None else layer_sides(points, normals, spacing, tree, noise, cancel_poll)
    return np.where((below >= LAYER_MIN) & (above == 0), 1.0,
                    np.where((above >= LAYER_MIN) & (below == 0), -1.0, 0.0))


def _layer_seeds(g, points, normals, votes, seed, spacing: float) -> np.ndarray:
    """Seeds (N,) extended by the layer votes where the views left points undecided.

    Layer points (``votes != 0``) joined by edges of the neighbour graph ``g`` with parallel normals
    (not around a sharp edge, onto another face) form regions; a region's votes are used when at
    least :data:`LAYER_CHECKS` of its points were also seeded by the views, at least
    :data:`LAYER_AGREEMENT` of those agree with their votes, and at least :data:`LAYER_OPPOSED` of
    them face a view-seeded point of the other face (:func:`_facing_seeds`): the views saw the
    part from both sides, so it is a solid plate. A narrow gap between two parts (its facing sides
    point into it, against the votes) is hidden from the views and gets no seeds; two misregistered
    copies of one surface (a scan) are seen from one side only: the outer copy's seeds agree with
    their votes, the hidden inner copy's votes point inward (77 to 90 % of them wrong on simulated
    range scans, docs/real_scans.md). Both keep the propagated signs.

    ``points`` (N, 3) and ``spacing`` (their median spacing) are in the same units."""
    layer = votes != 0
    both = layer & (seed != 0)
    if both.sum() < LAYER_CHECKS:  # no region can be trusted (smooth closed shapes, most inputs)
        return seed
    g = g.tocoo()
    par = np.abs(np.sum(normals[g.row] * normals[g.col], axis=1)) > LAYER_PARALLEL
    inner = layer[g.row] & layer[g.col] & par
    n_regions, labels = _components(len(votes), g.row[inner], g.col[inner])
    checked = np.bincount(labels[both], minlength=n_regions)
    agreed = np.bincount(labels[both], weights=(seed[both] == votes[both]).astype(float), minlength=n_regions)
    idx = np.flatnonzero(both)
    facing = _facing_seeds(points[idx], normals[idx] * seed[idx, None], LAYER_RADIUS * spacing)
    opposed = np.bincount(labels[idx], weights=facing.astype(float), minlength=n_regions)
    trusted = (checked >= LAYER_CHECKS) & (agreed >= LAYER_AGREEMENT * checked) & (opposed >= LAYER_OPPOSED)
    use = layer & (seed == 0) & trusted[labels]
    return np.where(use, votes, seed)


def _facing_seeds(points, oriented, radius: float) -> np.ndarray:
    """Which of the seeded ``points`` (M, 3) have another within ``radius`` whose ``oriented``
    normal (M, 3) points the opposite way (cosine below -0.5): bool (M,)."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    out = np.zeros(len(points), dtype=bool)
    if len(pairs):
        opp = pairs[np.sum(oriented[pairs[:, 0]] * oriented[pairs[:, 1]], axis=1) < -0.5]
        out[opp[:, 0]] = True
        out[opp[:, 1]] = True
    return out


def _seeded_propagation(g, points, normals, seed_sign, noise=None):
    """Orient every point from the seeds: ``seed_sign`` (N,) is +1/-1 for seeds, 0 elsewhere.

    Seeds hang from a virtual root; the rest joins the seeds along the minimum spanning tree of the
    neighbour graph ``g`` and takes its sign from its parent. Pieces without any seed start from
    their first point with its current sign. Returns signs (N,) and the number of pieces.
    """
    from scipy.sparse.csgraph import connected_components

    n = normals.shape[0]
    n_pieces, labels = connected_components(g, directed=False)
    seeded_piece = np.zeros(n_pieces, dtype=bool)
    seeded_piece[labels[seed_sign != 0]] = True
    roots = np.concatenate([np.flatnonzero(seed_sign != 0), first_points(labels, n_pieces)[~seeded_piece]])
    order, pred = spanning_order(g, roots)
    start = np.where(seed_sign != 0, seed_sign, 1.0)
    relation = np.ones(n)
    child = np.flatnonzero(pred >= 0)
    relation[child] = edge_relation(points, normals, pred[child], child, noise)
    sign = _propagate_signs(order, pred, relation, start)
    return sign, int(n_pieces)


def _harmonic_signs(g, points, normals, sign, seed, noise=None, cancel_poll: CancelPoll = None):
    """Signs (N,) from a global least-squares fit over the confident edges, seeded by the views.

    The spanning tree takes each point's sign along one path from a seed, so one wrong edge on that
    path flips everything behind it. Here every confident edge (cost below
    :data:`HARMONIC_COST`) and every seed votes at once: the real-valued ``s`` minimising::

        sum_ij w_ij (s_i - r_ij s_j)^2 + sum_i c_i (s_i - v_i)^2

        w_ij = exp(-cost_ij / HARMONIC_COST), r_ij = edge_relation(i, j)
        c_i = HARMONIC_SEED for seeds (v_i = the views' sign), 1e-6 * HARMONIC_SEED elsewhere
        (v_i = ``sign``, so pieces without seeds or confident edges keep their sign)

    solves one sparse, symmetric positive definite system (a signed graph Laplacian plus a
    diagonal), and the new sign is the sign of ``s``: a signed version of harmonic label
    propagation, where a point's sign comes from all the paths to all seeds, weighted.
    """
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    g = g.tocoo()
    keep = g.data < HARMONIC_COST
    i, j = g.row[keep], g.col[keep]
    rel = edge_relation(points, normals, i, j, noise)
    w = np.exp(-g.data[keep] / HARMONIC_COST)
    a = coo_matrix((w * rel, (i, j)), shape=g.shape).tocsr()
    degree = np.asarray(abs(a).sum(axis=1)).ravel()
    c = np.where(seed != 0, HARMONIC_SEED, 1e-6 * HARMONIC_SEED)
    v = np.where(seed != 0, seed, sign)
    if cancel_poll is not None:
        cancel_poll()
    s = spsolve((diags(degree + c) - a).tocsc(), c * v)
    return np.where(s >= 0, 1.0, -1.0)


def _subset(n: int, cap: int, spacing: float, seed: int):
    """Indices (M,) of a fixed random subset of at most ``cap`` of ``n`` points, and its spacing."""
    if n <= cap:
        return np.arange(n), spacing
    sub = np.sort(np.random.default_rng(seed).choice(n, cap, replace=False))
    return sub, spacing * float(np.sqrt(n / cap))


def winding_field(points, normals, spacing: float, cancel_poll: CancelPoll = None):
    """The winding-number gradient the orientation uses (:class:`~nkf_model.points.winding.WindingGradient`,
    leaving out :data:`WINDING_EXCLUDE` spacings around each query), over at most
    :data:`WINDING_POINTS` points (a fixed random subset above).

    Parameters
    ----------
    points, normals : (N, 3) float64
        More than ``AREA_NEIGHBOURS`` points; unit normals of any sign.
    spacing : float
        Median point spacing, in the units of ``points``.

    Returns
    -------
    field : WindingGradient
        Call it with the signs of ``sub`` (and optionally queries).
    sub : (M,) int64
        The points it holds.
    """
    from ..points.winding import WindingGradient

    sub, sub_spacing = _subset(len(points), WINDING_POINTS, spacing, seed=1)
    field = WindingGradient(points[sub], normals[sub], WINDING_EXCLUDE * sub_spacing, cancel_poll=cancel_poll)
    return field, sub


def _winding_signs(points, normals, sign, fixed, layer, spacing, cancel_poll: CancelPoll = None):
    """Signs (N,) refined by the winding number of the oriented cloud (closed objects only).

    For a consistently oriented closed surface the winding number's gradient at each point, from
    the rest of the surface (:class:`~nkf_model.points.winding.WindingGradient`, leaving out the
    :data:`WINDING_EXCLUDE` spacings around it), points inward; Lin et al. (SIGGRAPH Asia 2024,
    "winding number normal consistency") orient by iterating that. Here each point not in
    ``fixed`` (N,) bool (the views' seeds) takes the sign that makes ``-g`` agree with its normal,
    for :data:`WINDING_ROUNDS` rounds or until nothing flips. The field reaches into hidden places
    the views and the neighbour graph decide poorly (a box behind a lid, the inside of a tank's
    tracks), but not across thin parts: both faces of a plate lie within the left-out radius, so
    their field comes from the rest of the shape. There (``layer`` (N,) bool) a point follows it
    only where the field is strong: ``|g . n| * spacing`` at least :data:`WINDING_LAYER_FIELD`.
    Above :data:`WINDING_POINTS` points, a random subset is refined and then the field of the
    subset decides the rest once. Returns the signs and the field when it holds every point
    (else None).
    """
    from ..points.winding import AREA_NEIGHBOURS

    n = len(points)
    if n <= AREA_NEIGHBOURS:
        return sign, None
    field, sub = winding_field(points, normals, spacing, cancel_poll)
    need = np.where(layer, WINDING_LAYER_FIELD, 0.0)

    def follow(s, g, idx):
        f = -np.sum(g * normals[idx], axis=1) * spacing
        free = ~fixed[idx] & (np.abs(f) >= need[idx]) & (f != 0)
        return np.where(free, np.where(f > 0, 1.0, -1.0), s[idx])

    s = sign.copy()
    for _ in range(WINDING_ROUNDS):
        new = follow(s, field(s[sub], cancel_poll=cancel_poll), sub)
        changed = bool((new != s[sub]).any())
        s[sub] = new
        if not changed:
            break
    if len(sub) < n:
        rest = np.setdiff1d(np.arange(n), sub)
        s[rest] = follow(s, field(s[sub], points[rest], cancel_poll=cancel_poll), rest)
        return s, None
    return s, field


N_VIEWS = 64  # orthographic views for "outward" (all around) and "up" (upper half)
VIEW_POINTS = 40_000  # points drawn into the views at most
# A point's sign is taken from the views when the votes agree this much (|sum| / sum of |votes|);
# otherwise it is propagated from its neighbours.
VOTE_AGREEMENT = 0.5
# ... and when their total weight (about the number of views that saw the point face-on) is at least
# this: points seen from only one or two views are mostly seen through gaps between the discs.
VOTE_WEIGHT = 3.0
TOL_NOISE = 1.5  # depth tolerance of the views, in noise levels (on top of half a spacing)
HARMONIC_COST = 0.1  # edges cheaper than this join the global sign fit (_harmonic_signs)
HARMONIC_SEED = 0.01  # weight of a seed's sign in that fit, against 1 for a confident edge
NOISE_QUANTILE = 0.25  # the noise level is this quantile of the points' plane-fit residuals
SPLAT_RADIUS = 3.0  # disc radius of each point in the visibility views, in point spacings
SPLAT_NEIGHBOUR = 6  # misregistered scans: each disc reaches this neighbour ...
SPLAT_MIN = 1.0  # ... with a radius of at least this many point spacings
VIEWPOINT_VOTE_WEIGHT = 0.25
# Winding-number refinement (_winding_signs), chosen on the val meshes (docs/scans.md).
WINDING_ROUNDS = 10
WINDING_LAYER_FIELD = 0.08  # field a layer point needs to follow it (|g . n| * spacing)
WINDING_POINTS = 20_000  # points refined at most (a random subset above)
# Thin parts (layer_votes, _layer_seeds); measured on the val meshes with thin parts (docs/scans.md).
LAYER_K = 24  # neighbours searched for the other face
LAYER_RADIUS = 3.0  # ... within this many spacings
LAYER_PARALLEL = 0.9  # |cos| between the normals of the two faces
LAYER_OFFSET = 0.3  # offset along the normal, in spacings, that counts as the other face
LAYER_MIN = 2  # points of the other face needed
LAYER_CHECKS = 3  # view-seeded points a layer region needs ...
LAYER_AGREEMENT = 0.8  # ... and the share of them that must agree with its votes
LAYER_OPPOSED = 3  # ... and how many of them must face a seeded point of the other face
# Misregistered overlapping scans (layer_balance on the propagation's signs), chosen on the val meshes'
# all-round scans and clean samples (docs/real_scans.md).
MISREGISTERED_LAYERS = 0.6  # share of points with another layer ...
MISREGISTERED_BALANCE = 0.45  # ... and outward-only layer points more than this share of inward-only ones
MISREGISTERED_NOISE = 2.0  # the noise level of the second orientation, in first noise levels


def median_spacing(points: np.ndarray, tree: Optional[cKDTree] = None, sample: int = 20000) -> float:
    """Median distance from a point to its nearest neighbour (on a fixed subsample of at most
    ``sample`` points), in the units of ``points``."""
    p = np.asarray(points, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(p)
    idx = np.random.default_rng(0).choice(len(p), min(sample, len(p)), replace=False)
    d, _ = tree.query(p[idx], k=2, workers=-1)
    return float(np.median(d[:, 1]))


def orient_normals(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    orientation: str = "outward",
    viewpoints=None,
    k: int = DEFAULT_GRAPH_K,
    tree: Optional[cKDTree] = None,
    noise: Optional[np.ndarray] = None,
    residual: Optional[np.ndarray] = None,
    learned: bool = True,
    cancel_poll: CancelPoll = None,
):
    """Give unoriented unit normals consistent signs.

    Parameters
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals of arbitrary sign (for example from :func:`pca_normals`).
    orientation : {"outward", "up", "viewpoint"}
        Which views vote (see the module docstring).
    viewpoints : (3,) or (K, 3) float, optional
        Scanner positions, in the same frame as ``points`` (needed for ``"viewpoint"``).
    k : int
        Neighbours per point in the propagation graph.
    noise : (N,) float64, optional
        Local noise level of each point (the ``residual`` of :func:`pca_normals`), in the units of
        ``points``: offsets within it are not read as geometry.
    residual : (N,) float64, optional
        Each point's own plane-fit residual (``noise`` when not given), read by the learned sign
        check.
    learned : bool
        For ``"outward"``: finish with the learned sign check (:mod:`nkf_model.normals.sign_check`, clouds
        of at most :data:`~nkf_model.normals.sign_check.MAX_POINTS` points).

    Returns
    -------
    normals : (N, 3) float64
        Oriented unit normals.
    info : OrientationInfo
    """
    sign, state, info = _orient(points, normals, orientation=orientation, viewpoints=viewpoints, k=k, tree=tree,
                                noise=noise, residual=residual, cancel_poll=cancel_poll)
    return _checked(sign, state, info, learned, cancel_poll)


def _checked(sign, state, info, learned: bool, cancel_poll: CancelPoll):
    """Oriented normals (N, 3) and ``info``, after the learned sign check where it applies and the
    tangent-plane check (step f)."""
    from .consistent import tangent_plane_check  # SciPy's graph module: only when estimating

    if learned and info.orientation == "outward":
        sign, flips = sign_check.flip_wrong(state, cancel_poll=cancel_poll)
        info.learned_check, info.learned_flips = flips is not None, flips or 0
    winding = None
    if info.orientation == "outward":  # closed objects: the winding number backs the check

        def winding(poll):
            return winding_field(state.points, state.normals, state.spacing, poll)

    sign, info.consistent_flips = tangent_plane_check(state, sign, cancel_poll, winding=winding)
    return state.normals * sign[:, None], info


def _orient(points, normals, *, orientation, viewpoints, k, tree, noise, residual, cancel_poll,
            stop_if_misregistered: bool = False, follow_neighbours: bool = False):
    """Signs (N,), the :class:`~nkf_model.normals.sign_check.OrientationState` behind them and the
    :class:`OrientationInfo`: :func:`orient_normals` without the learned check (also used to
    train it).

    ``stop_if_misregistered``: return ``None`` as soon as the signs of the propagation read as
    misregistered overlapping scans (:func:`misregistered`), before the costlier global steps, so that
    the caller can orient again with a wider noise level. ``follow_neighbours``: the views' discs
    (:func:`splat_radii`)."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    vp = check_viewpoints(viewpoints)
    orientation = check_orientation(orientation, vp)
    tree = tree if tree is not None else cKDTree(p)
    spacing = median_spacing(p, tree)
    # The views see a random subset of at most VIEW_POINTS points (drawn as larger discs): enough
    # to seed the propagation, at a bounded cost.
    n = len(p)
    sub, view_spacing = _subset(n, VIEW_POINTS, spacing, seed=0)
    noise_level = 0.0 if noise is None else float(np.median(noise))
    # Layers closer than the views' depth tolerance (the two faces of a thin wall) are told apart
    # by their neighbours: a point with another layer on its viewer's side is hidden. Objects
    # need them for every point (layer votes, the winding-number step); scans for the views'.
    if orientation == "viewpoint":
        sides = None
        layers = tuple(c > 0 for c in layer_sides(p, nrm, spacing, tree, noise_level, cancel_poll, index=sub))
        sv, sw = visibility_votes(p[sub], nrm[sub], view_spacing, viewpoints=vp, noise=noise_level,
                                  layers=layers, cancel_poll=cancel_poll)
    else:
        sides = layer_sides(p, nrm, spacing, tree, noise_level, cancel_poll)
        layers = (sides[0][sub] > 0, sides[1][sub] > 0)
        dirs = fibonacci_directions(N_VIEWS, upper_only=orientation == "up")
        sv, sw = visibility_votes(p[sub], nrm[sub], view_spacing, directions=-dirs, noise=noise_level,
                                  layers=layers, cancel_poll=cancel_poll, follow_neighbours=follow_neighbours)
    votes = np.zeros(n)
    weight = np.zeros(n)
    votes[sub], weight[sub] = sv, sw
    agree = np.divide(np.abs(votes), weight, out=np.zeros_like(votes), where=weight > 0)
    # A few scanners give few views: one clear view decides there.
    min_weight = VOTE_WEIGHT if orientation != "viewpoint" else VIEWPOINT_VOTE_WEIGHT
    seed = np.where((agree >= VOTE_AGREEMENT) & (weight >= min_weight), np.sign(votes), 0.0)
    if cancel_poll is not None:
        cancel_poll()
    g = _graph(p, nrm, tree, k, cancel_poll, noise)
    n_seeded = int((seed != 0).sum())
    view_seed = seed
    sign, pieces = _seeded_propagation(g, p, nrm, seed, noise)
    sign = _flip_pieces(g, p, nrm, sign, seed, cancel_poll, noise=noise)
    if stop_if_misregistered and orientation != "viewpoint" and misregistered(sides[0], sides[1], sign):
        return None
    if orientation != "viewpoint":
        # Thin parts with both faces sampled belong to objects (a scanner sees one side of each
        # surface). Their layer votes join the global fit only: as hard seeds of the spanning tree,
        # a few wrong ones (the facing sides of a narrow gap) would decide everything behind them.
        lv = layer_votes(p, nrm, spacing, tree, sides=sides)
        seed = _layer_seeds(g, p, nrm, lv, seed, spacing)
    sign = _harmonic_signs(g, p, nrm, sign, seed, noise, cancel_poll)
    sign = _consensus(g, p, nrm, sign, votes, cancel_poll, noise=noise)
    if orientation == "outward":
        # Closed objects: the winding number's field says which side is in where the views saw
        # nothing (open scans and terrain have no inside).
        sign, winding = _winding_signs(p, nrm, sign, view_seed != 0, (sides[0] > 0) | (sides[1] > 0), spacing,
                                       cancel_poll)
    else:
        winding = None
    info = OrientationInfo(orientation=orientation, pieces=pieces,
                           seeded=n_seeded, spacing=spacing)
    if sides is None:  # viewpoint: no layer votes
        sides = (np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64))
        lv = np.zeros(n)
    res = residual if residual is not None else (noise if noise is not None else np.zeros(n))
    state = sign_check.OrientationState(
        points=p, normals=nrm, sign=sign, votes=votes, weight=weight, view_seed=view_seed, layer_seed=seed,
        layer_vote=lv, above=sides[0], below=sides[1], graph=g, residual=np.asarray(res, dtype=np.float64),
        spacing=spacing, winding=winding, noise=noise,
    )
    return sign, state, info


def estimate_normals(
    points: np.ndarray,
    *,
    k: int = DEFAULT_K,
    orientation: Optional[str] = None,
    viewpoints=None,
    cancel_poll: CancelPoll = None,
    check: CancelPoll = None,
):
    """Oriented unit normals for a point cloud without normals.

    Parameters
    ----------
    points : (N, 3) float
        Positions in any units (finite, no exact duplicates: see :func:`nkf_model.points.clean.clean_points`).
    k : int
        Neighbours for the PCA fit (the orientation graph uses :data:`DEFAULT_GRAPH_K`).
    orientation : {"outward", "up", "viewpoint"} or None
        Rule for each piece's global sign; ``None`` picks ``"viewpoint"`` when ``viewpoints`` are
        given, else ``"outward"``.
    viewpoints : (3,) or (K, 3) float, optional
        Scanner or camera positions in the frame of ``points``.
    cancel_poll : callable, optional
        Called between chunks of work; raises (e.g. :class:`~nkf_model.errors.Cancelled`) to stop.
        ``check`` is its former name, still accepted.

    Returns
    -------
    normals : (N, 3) float64
        Oriented unit normals.
    info : OrientationInfo
    """
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 3 <= k <= 200:
        raise InvalidParameterError(f"normal neighbours k must be an integer from 3 to 200, got {k!r}")
    if cancel_poll is None:
        cancel_poll = check
    vp = check_viewpoints(viewpoints)
    orientation = check_orientation(orientation, vp)
    if len(points) > COARSE_POINTS:
        return _estimate_coarse(points, k, orientation, vp, cancel_poll)
    if len(points) >= IRREGULAR_MIN_POINTS:
        return _estimate_regular(points, k, orientation, vp, cancel_poll)
    return _checked(*_estimate(points, k, orientation, vp, cancel_poll), learned=True, cancel_poll=cancel_poll)


def _vote_signs(points, normals, oriented_points, oriented) -> np.ndarray:
    """``normals`` (M, 3) of ``points`` (M, 3), each with the sign its :data:`COARSE_VOTERS` nearest
    ``oriented`` normals (at ``oriented_points``) vote for, weighted by one over their distance."""
    d, idx = cKDTree(oriented_points).query(points, k=COARSE_VOTERS)
    w = 1.0 / np.maximum(d, 1e-12)
    vote = np.einsum("nk,nk->n", w, np.einsum("nkj,nj->nk", oriented[idx], normals))
    return np.where(vote[:, None] < 0, -normals, normals)


def _estimate_regular(points, k: int, orientation: str, viewpoints, cancel_poll: CancelPoll = None):
    """Orient the points whose neighbourhood is regular, then give the rest the sign of their oriented
    neighbours.

    A point whose :data:`IRREGULAR_NEIGHBOURS` nearest neighbours lie farther than
    :data:`IRREGULAR_RATIO` times the cloud's median (mean distance) sits in a sparse, irregular spot:
    mostly mixed pixels the outlier test left (they lie a spacing or a few off the surface, in streaks
    behind silhouettes), whose own PCA normals are poor and whose edges mislead the orientation graph.
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    tree = cKDTree(p)
    d, _ = tree.query(p, k=IRREGULAR_NEIGHBOURS + 1)
    spread = d[:, 1:].mean(axis=1)
    regular = spread <= IRREGULAR_RATIO * float(np.median(spread))
    if regular.all():
        return _checked(*_estimate(p, k, orientation, viewpoints, cancel_poll), learned=True,
                        cancel_poll=cancel_poll)
    oriented, info = _checked(*_estimate(p[regular], k, orientation, viewpoints, cancel_poll), learned=True,
                              cancel_poll=cancel_poll)
    rest = np.flatnonzero(~regular)
    own, _ = pca_normals(p, k, tree=tree, cancel_poll=cancel_poll, at=rest)
    nrm = np.empty_like(p)
    nrm[regular] = oriented
    nrm[rest] = _vote_signs(p[rest], own, p[regular], oriented)
    return nrm, info


def _estimate_coarse(points, k: int, orientation: str, viewpoints, cancel_poll: CancelPoll = None):
    """Dense input: orient a voxel-averaged copy of at most :data:`COARSE_POINTS` points, then give
    each point's own PCA normal the sign of the coarse normals around it.

    On dense noisy input (noise of half the point spacing) the orientation graph's neighbours lie
    within the noise of each other and its relations fail; averaged into voxels a few spacings wide,
    the noise falls well below the new spacing. Measured on 300,000 points sampled from
    quaternius__Sofa with Gaussian noise of half the point spacing: 26.8 % of the signs wrong
    oriented at full density (100 s); 19.2 % this way (26 to 36 s, 2026-12-03), the same as on clean
    samples of that mesh at 10,000 and 47,000 points (13.3 %, 16.1 %: its parts overlap, and the
    faces inside others count as wrong whichever way they point). On quaternius__Donut, which has no
    such faces: 0.00 % this way (docs/real_scans.md).
    """
    from ..points.voxel_reduce import voxel_for_count, voxel_reduce

    p = np.ascontiguousarray(points, dtype=np.float64)
    red = voxel_reduce(p, None, None, voxel_for_count(p, COARSE_POINTS, start=median_spacing(p)))
    coarse, info = _checked(*_estimate(red.points, k, orientation, viewpoints, cancel_poll), learned=True,
                            cancel_poll=cancel_poll)
    nrm, _ = pca_normals(p, k, tree=cKDTree(p), cancel_poll=cancel_poll)
    return _vote_signs(p, nrm, red.points, coarse), info


def _estimate(points, k: int, orientation: str, viewpoints, cancel_poll: CancelPoll = None):
    """PCA normals of ``points`` oriented without the learned check: what :func:`_orient`
    returns (also used to train the check, :mod:`nkf_model.train.sign_check_training`)."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    tree = cKDTree(p)
    nrm, residual = pca_normals(p, k, tree=tree, cancel_poll=cancel_poll)
    # One noise level for the whole cloud, from its flattest quarter: residuals also grow with
    # curvature and at sharp edges, where offsets along the normals are geometry, not noise.
    noise = np.full(len(p), float(np.quantile(residual, NOISE_QUANTILE)))
    first = _orient(p, nrm, orientation=orientation, viewpoints=viewpoints, k=DEFAULT_GRAPH_K, tree=tree,
                    noise=noise, residual=residual, cancel_poll=cancel_poll, stop_if_misregistered=True)
    if first is not None:
        return first
    # Overlapping scans that do not register exactly: the offsets between the copies of one surface
    # are no thin parts. Orient again with them inside the noise level, and views whose discs follow
    # the dense range images' neighbours (thin rods stay visible).
    sign, state, info = _orient(p, nrm, orientation=orientation, viewpoints=viewpoints, k=DEFAULT_GRAPH_K,
                                tree=tree, noise=MISREGISTERED_NOISE * noise, residual=residual,
                                cancel_poll=cancel_poll, follow_neighbours=True)
    info.misregistered = True
    return sign, state, info


def misregistered(above, below, sign) -> bool:
    """Whether a cloud reads as overlapping scans that do not register exactly: over
    :data:`MISREGISTERED_LAYERS` of its points have another layer, and the layer points whose other
    layer lies only outward number over :data:`MISREGISTERED_BALANCE` of those whose other layer lies
    only inward (:func:`layer_balance`; arguments as there)."""
    share, outward, inward = layer_balance(above, below, sign)
    return share > MISREGISTERED_LAYERS and outward > MISREGISTERED_BALANCE * inward > 0


def layer_balance(above, below, sign) -> tuple[float, float, float]:
    """Where a cloud's other layers lie: the share of points with another layer nearby, and among
    those the shares whose other layer lies only outward (the side their oriented normal points to)
    and only inward.

    ``above``, ``below`` (N,): :func:`layer_sides` of the unoriented normals; ``sign`` (N,) +1/-1 the
    orientation's signs. The other face of a solid part lies inward (the far side of a narrow gap
    outward, less often); two misregistered copies of one surface lie on either side of each other as
    often, since they swap sides where they cross. With the signs of the propagation (what
    :func:`_orient` decides on): clean 10,000-point samples of the 52 `val` meshes (and 20,000 and
    50,000 of 32 of them) with over 60 % layer points have outward at most 0.24 of inward (rough
    meshes: PineTreeTall 0.24, textured-0008192 0.09, base_link 0.03), and those with outward over 0.45
    of inward at most 50 % layer points (Tank3 at 10,000 points, 0.75); all-round simulated scans
    (misregistration 0.002 of the diagonal) have 61 to 97 % layer points, outward 0.04 (base_link
    again) to 1.47 of inward, 48 of 52 over both thresholds; dense noisy samples (300,000 points, noise
    half the spacing) of Tank3 0.67 / 1.14 (flagged: its estimated normals then give the true normals'
    Chamfer-L1); the dragon 0.52 / 0.98 (docs/real_scans.md). The finished orientation reads outward
    layers more often (on the 45 scans its signs flagged at 0.5, a median 1 / 0.86 times as often).
    """
    up = np.where(sign > 0, above, below)
    down = np.where(sign > 0, below, above)
    layer = (up > 0) | (down > 0)
    if not layer.any():
        return 0.0, 0.0, 0.0
    return (float(layer.mean()), float(((up > 0) & (down == 0))[layer].mean()),
            float(((down > 0) & (up == 0))[layer].mean()))
