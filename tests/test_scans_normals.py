"""Normal estimation and orientation (issue 5): spheres, boxes, thin plates, nearby sheets, hints."""

from __future__ import annotations

import numpy as np
import pytest
from scan_shapes import box_points, open_box_points
from shapes import sphere_points

import nkf_model
from nkf_model.errors import InvalidParameterError
from nkf_model.normals.estimate import estimate_normals, pca_normals


def agreement(estimated, true):
    return float((np.sum(estimated * true, axis=1) > 0).mean())


def test_pca_normals_are_unit_and_fit_planes():
    p, n = box_points(2000, seed=3)
    e, residual = pca_normals(p, 16)
    assert np.allclose(np.linalg.norm(e, axis=1), 1.0)
    # Away from the box's edges every neighbourhood is planar: the normal is exact up to sign.
    inner = (np.abs(p) < 0.4).sum(axis=1) == 2
    assert np.median(np.abs(np.sum(e[inner] * n[inner], axis=1))) > 0.999
    assert np.median(residual[inner]) < 1e-9


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_sign_agreement_above_99_percent(shape):
    p, n = sphere_points(3000, seed=1) if shape == "sphere" else box_points(3000, seed=1)
    e, info = estimate_normals(p)
    assert info.orientation == "outward"
    assert agreement(e, n) > 0.99


def test_orientation_is_invariant_to_scale_and_offset():
    p, n = sphere_points(2000, seed=4)
    e1, _ = estimate_normals(p)
    e2, _ = estimate_normals(p * 1e-3 + 1e5)
    assert agreement(e1, n) > 0.99 and agreement(e2, n) > 0.99


def test_thin_plate():
    # 1 x 1 x 0.04 slab: the two large faces are 4 point spacings apart, closer than the
    # neighbourhoods, so plain propagation gives both faces the same direction.
    p, n = box_points(4000, size=(1.0, 1.0, 0.04), seed=2)
    e, _ = estimate_normals(p)
    assert agreement(e, n) > 0.95
    top = n[:, 2] > 0.5
    bottom = n[:, 2] < -0.5
    assert (e[top, 2] > 0).mean() > 0.95 and (e[bottom, 2] < 0).mean() > 0.95


def test_two_nearby_sheets():
    # Two slabs 0.03 apart (about 2 spacings): the facing sides point at each other, into the gap.
    a, na = box_points(3000, size=(1.0, 1.0, 0.1), center=(0, 0, 0.065), seed=3)
    b, nb = box_points(3000, size=(1.0, 1.0, 0.1), center=(0, 0, -0.065), seed=4)
    p, n = np.r_[a, b], np.r_[na, nb]
    e, _ = estimate_normals(p)
    assert agreement(e, n) > 0.93
    gap_upper = np.abs(p[:, 2] - 0.015) < 1e-9
    assert (e[gap_upper, 2] < 0).mean() > 0.85  # the upper slab's lower face points down, into the gap


def test_layer_votes_point_away_from_the_other_face_of_a_thin_plate():
    # A 0.006 slab, under a point spacing thick: each face's other face lies on one side.
    from scipy.spatial import cKDTree

    from nkf_model.normals.estimate import layer_votes, median_spacing

    p, n = box_points(4000, size=(1.0, 1.0, 0.006), seed=2)
    tree = cKDTree(p)
    e, _ = pca_normals(p, tree=tree)
    votes = layer_votes(p, e, median_spacing(p, tree), tree)
    voted = votes != 0
    assert voted.mean() > 0.5
    assert agreement(e[voted] * votes[voted, None], n[voted]) > 0.98


def test_inner_faces_of_thin_walls_are_not_seen_through_the_outer_faces():
    # A cup-shaped box whose walls are 0.01 thick, under a point spacing (0.0136): from outside,
    # every view sees both faces of a wall within its depth tolerance. The inner face is told
    # apart by its neighbours (the outer face lies between it and the viewer), so it is not
    # seeded with the outer face's sign (agreement 0.57 without that).
    p, n = open_box_points(8000, wall=0.01)
    e, info = estimate_normals(p)
    assert info.spacing > 0.01
    assert agreement(e, n) > 0.93
    inner = (np.abs(p[:, :2]) <= 0.49 + 1e-9).all(axis=1) & (p[:, 2] >= -0.49 - 1e-9)  # the faces looking in
    assert inner.sum() > 2000
    assert agreement(e[inner], n[inner]) > 0.93


@pytest.mark.parametrize("refined", [None, 2500])
def test_faces_hidden_inside_another_part_follow_the_winding_number(refined, monkeypatch):
    # A table top with a rail that reaches into it (two boxes, each sampled whole, as a mesh of
    # parts is): the rail's faces inside the top are hidden from every view and meet the top's
    # faces at a T, where the neighbour graph guesses. The winding number's field of the rest
    # orients them (0.70 of them right without that step). With ``refined``, only that many
    # points are refined and their field decides the rest (the path of large inputs).
    from nkf_model.normals import estimate as normals

    if refined:
        monkeypatch.setattr(normals, "WINDING_POINTS", refined)
    top, n_top = box_points(3000, size=(1.0, 1.0, 0.1), seed=0)
    rail, n_rail = box_points(1200, size=(0.1, 0.8, 0.27), center=(0.3, 0.0, -0.115), seed=1)
    p, n = np.r_[top, rail], np.r_[n_top, n_rail]
    hidden = np.r_[(np.abs(top - (0.3, 0.0, -0.115)) < np.array([0.05, 0.4, 0.135]) - 1e-9).all(axis=1),
                   (np.abs(rail) < np.array([0.5, 0.5, 0.05]) - 1e-9).all(axis=1)]
    assert hidden.sum() > 400
    e, _ = estimate_normals(p)
    assert agreement(e[hidden], n[hidden]) > 0.9
    assert agreement(e, n) > 0.97


def test_a_curved_sheet_is_no_layer_of_itself():
    # On a sphere about 10 point spacings in radius, neighbours 3 spacings away lie 0.45 spacings
    # below the tangent plane and their normals within 25 degrees: the old test took 94 % of the
    # points for layers. Offsets explained by the bending (t * tan(theta / 2)) do not count.
    from scipy.spatial import cKDTree

    from nkf_model.normals.estimate import layer_sides, median_spacing

    p, _ = sphere_points(300, seed=1)
    tree = cKDTree(p)
    e, _ = pca_normals(p, tree=tree)
    spacing = median_spacing(p, tree)
    assert 8 < 1 / spacing < 12
    above, below = layer_sides(p, e, spacing, tree)
    assert ((above > 0) | (below > 0)).mean() < 0.02


def test_hidden_thin_plate_between_two_others():
    # Three 0.006 slabs stacked 0.08 apart: the middle one's faces are hidden from the views
    # (grazing from the sides, covered from above and below), so only its rims are seeded. Its
    # layer votes, trusted where they agree with those seeds, orient it (0.86 without them).
    ps, ns = [], []
    for k, z in enumerate((-0.08, 0.0, 0.08)):
        p, n = box_points(3000, size=(1.0, 1.0, 0.006), center=(0, 0, z), seed=10 + k)
        ps.append(p)
        ns.append(n)
    p, n = np.concatenate(ps), np.concatenate(ns)
    e, _ = estimate_normals(p)
    middle = np.abs(p[:, 2]) < 0.02
    assert agreement(e[middle], n[middle]) > 0.95


def test_misregistered_copies_of_a_surface_are_no_thin_plate():
    # A box scanned twice, the second copy 0.01 (0.4 spacings) outside the first: layered like a
    # thin plate, but the views see only the outer copy, so its seeds agree with the layer votes
    # while the hidden inner copy's votes point inward. Those votes were trusted (3,295 layer
    # seeds, 92 % of them wrong; 60 % of the signs right in the end); a plate is seen from both
    # sides, a misregistered surface from one, and now no votes are used.
    from scipy.spatial import cKDTree

    from nkf_model.normals import estimate

    a, na = box_points(4000, seed=1)
    b, nb = box_points(4000, size=(1.02, 1.02, 1.02), seed=2)
    p, n = np.r_[a, b], np.r_[na, nb]
    tree = cKDTree(p)
    e, residual = pca_normals(p, tree=tree)
    noise = np.full(len(p), float(np.quantile(residual, estimate.NOISE_QUANTILE)))
    _, state, _ = estimate._orient(p, e, orientation="outward", viewpoints=None, k=estimate.DEFAULT_GRAPH_K,
                                   tree=tree, noise=noise, residual=residual, cancel_poll=None)
    assert np.array_equal(state.layer_seed, state.view_seed)  # no layer votes joined the seeds
    e, _ = estimate_normals(p)
    assert agreement(e, n) > 0.99


def test_misregistered_scans_are_told_from_thin_parts_and_oriented_again():
    # Four scans of a box, each turned by up to 4 degrees and shifted by 0.004: copies of one surface
    # that cross each other, so their other layers lie outward about as often as inward. A thin plate
    # (its other face always inward) and a clean box are no such thing.
    from benchmarks.range_scans import _rotation  # the simulated scans' own misregistration turn

    rng = np.random.default_rng(0)
    parts, normals = [], []
    for s in range(4):
        p, n = box_points(3000, seed=s)
        r = _rotation(rng.normal(size=3), np.radians(4.0) * rng.uniform(0.5, 1.0))
        parts.append(p @ r.T + rng.normal(scale=0.004, size=3))
        normals.append(n @ r.T)
    p, n = np.concatenate(parts), np.concatenate(normals)
    e, info = estimate_normals(p)
    assert info.misregistered
    assert agreement(e, n) > 0.98  # 0.9844 oriented once, 0.9908 again
    for p, n in (box_points(12000, seed=9), box_points(4000, size=(1.0, 1.0, 0.006), seed=2)):
        e, info = estimate_normals(p)
        assert not info.misregistered
        assert agreement(e, n) > 0.97


def test_the_misregistration_rule_reads_the_layer_share_and_balance():
    # misregistered(): more than MISREGISTERED_LAYERS of the points with another layer, and outward-only
    # layer points more than MISREGISTERED_BALANCE of the inward-only ones (signs +1: "above" is outward).
    from nkf_model.normals.estimate import MISREGISTERED_BALANCE, MISREGISTERED_LAYERS, misregistered

    def cloud(share, outward_of_inward, n=10_000):
        layer = int(share * n)
        out = int(round(layer * outward_of_inward / (1 + outward_of_inward)))
        above, below = np.zeros(n, np.int64), np.zeros(n, np.int64)
        above[:out] = 1
        below[out:layer] = 1
        return above, below, np.ones(n)

    # Windmill's all-round scan (0.64 / 0.51) and the dense noisy Tank3 samples (0.667 / 1.14) are
    # flagged; the clean samples are not: rough meshes have many layers, all inward (base_link 0.93 /
    # 0.03), and below 0.6 (Tank3 at 10,000 points 0.50 / 0.75; the dragon 0.52 / 0.98).
    assert misregistered(*cloud(0.64, 0.51)) and misregistered(*cloud(0.667, 1.14))
    assert not misregistered(*cloud(0.93, 0.03))
    assert not misregistered(*cloud(0.50, 0.75)) and not misregistered(*cloud(0.52, 0.98))
    assert not misregistered(*cloud(MISREGISTERED_LAYERS - 0.01, 1.0))
    assert not misregistered(*cloud(0.9, MISREGISTERED_BALANCE - 0.02))


def test_views_drawn_once_vote_as_a_fresh_drawing_at_every_noise_level():
    # Depth buffers drawn once (view_depths) and read with several tolerances must vote as drawing
    # the views again with each tolerance. A box with a lid
    # floating just above it: the lid hides the top from some views within one tolerance, not the other.
    from nkf_model.normals.estimate import fibonacci_directions, median_spacing, view_depths, visibility_votes

    p, n = box_points(4000, seed=3)
    lid = p[:, 2] > 0.45
    p = np.concatenate([p, p[lid] + [0.0, 0.0, 0.02]])
    n = np.concatenate([n, n[lid]])
    spacing = median_spacing(p)
    dirs = -fibonacci_directions(16)
    drawn = list(view_depths(p, n, spacing, directions=dirs))
    layers = (p[:, 0] > 0.3, p[:, 1] > 0.3)
    seen = []
    for noise in (0.0, 0.01, 0.04):
        fresh = visibility_votes(p, n, spacing, directions=dirs, noise=noise, layers=layers)
        again = visibility_votes(p, n, spacing, noise=noise, layers=layers, depths=drawn)
        np.testing.assert_array_equal(fresh[0], again[0])
        np.testing.assert_array_equal(fresh[1], again[1])
        seen.append(int((fresh[1] > 0).sum()))
    assert seen[0] < seen[1] < seen[2], seen  # the tolerance matters here


def test_viewpoint_hint_orients_an_open_sheet_towards_the_scanner():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, size=(3000, 2))
    p = np.c_[xy, 0.05 * np.sin(2 * xy[:, 0])]  # a gently curved open sheet
    for z, sign in ((3.0, 1.0), (-3.0, -1.0)):
        e, info = estimate_normals(p, viewpoints=[0.0, 0.0, z])
        assert info.orientation == "viewpoint"
        assert (np.sign(e[:, 2]) == sign).mean() > 0.99


def test_up_hint():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1, 1, size=(2000, 2))
    p = np.c_[xy, 0.1 * np.cos(3 * xy[:, 1])]
    e, _ = estimate_normals(p, orientation="up")
    assert (e[:, 2] > 0).mean() > 0.99


def test_bad_hints_are_clear_errors():
    p, _ = sphere_points(200)
    with pytest.raises(InvalidParameterError, match="viewpoints"):
        estimate_normals(p, orientation="viewpoint")
    with pytest.raises(InvalidParameterError, match="shape"):
        estimate_normals(p, viewpoints=[[1.0, 2.0]])
    with pytest.raises(InvalidParameterError, match="orientation"):
        estimate_normals(p, orientation="sideways")
    with pytest.raises(InvalidParameterError, match="neighbours"):
        estimate_normals(p, k=1)


def test_reconstruct_estimates_missing_normals_and_says_so():
    p, _ = sphere_points(1500, seed=5)
    with pytest.warns(nkf_model.InputWarning, match="no normals given"):
        m = nkf_model.reconstruct(p, None, resolution=48, device="cpu")
    assert m.stats["normals"] == "estimated"
    assert m.stats["orientation"]["learned_check"] is True
    assert 0 <= m.stats["orientation"]["flipped_by_learned_check"] <= 15
    assert m.stats["orientation"]["flipped_by_tangent_planes"] == 0  # under 10,000 points: never runs
    assert m.stats["orientation"]["misregistered"] is False  # one clean sampling of a sphere
    assert np.abs(np.linalg.norm(m.vertices, axis=1) - 1).max() < 0.03
    # normals_mode="estimate" ignores given normals (here deliberately wrong ones).
    m2 = nkf_model.reconstruct(p, -p, resolution=48, device="cpu", normals_mode="estimate")
    assert m2.stats["normals"] == "estimated"
    assert np.abs(np.linalg.norm(m2.vertices, axis=1) - 1).max() < 0.03
    with pytest.raises(nkf_model.MissingNormalsError):
        nkf_model.reconstruct(p, None, normals_mode="given")
    with pytest.raises(InvalidParameterError, match="normals_mode"):
        nkf_model.reconstruct(p, None, normals_mode="guess")


def test_global_sign_fit_outvotes_a_wrong_branch():
    # A sphere whose spanning tree went wrong on a cap of unseeded points: the signs of the cap
    # are flipped. The least-squares fit over confident edges restores them from the seeds (6,000
    # points: dense enough that most neighbours on the curved surface are confident edges).
    from scipy.spatial import cKDTree

    from nkf_model.normals.estimate import _graph, _harmonic_signs

    p, n = sphere_points(6000, seed=5)
    e, _ = pca_normals(p, 16)
    truth = np.where(np.sum(e * n, axis=1) > 0, 1.0, -1.0)
    rng = np.random.default_rng(0)
    cap = p[:, 2] > 0.5
    seed = np.where(~cap & (rng.random(len(p)) < 0.2), truth, 0.0)
    wrong = np.where(cap, -truth, truth)
    g = _graph(p, e, cKDTree(p), 10, None)
    fixed = _harmonic_signs(g, p, e, wrong, seed)
    assert (wrong == truth).mean() < 0.9
    assert (fixed == truth).mean() > 0.99


def test_pca_normals_at_a_subset_are_the_rows_of_the_whole():
    from nkf_model.normals.estimate import pca_normals

    rng = np.random.default_rng(0)
    p = rng.normal(size=(30_000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p += rng.normal(scale=0.003, size=p.shape)
    at = np.sort(rng.choice(len(p), 700, replace=False))
    whole, res_whole = pca_normals(p)
    part, res_part = pca_normals(p, at=at)
    assert part.shape == (700, 3)
    assert np.array_equal(whole[at], part) and np.array_equal(res_whole[at], res_part)


def _planes_by_eigh(nb, sigma, k0, reweights):
    """The weighted plane fits of ``pca_normals`` written with NumPy and LAPACK's eigh (the
    implementation before the compiled one): the reference the compiled fits must reproduce."""
    c, k, _ = nb.shape
    normals, residual = np.empty((c, 3)), np.empty(c)
    best = np.full(c, -1.0)
    for first in dict.fromkeys((k0, k)):
        w = np.zeros((c, k))
        w[:, :first] = 1.0
        for _ in range(reweights + 1):
            ws = w / w.sum(axis=1, keepdims=True)
            d = nb - np.einsum("ck,cki->ci", ws, nb)[:, None, :]
            normal = np.linalg.eigh(np.einsum("ck,cki,ckj->cij", ws, d, d))[1][:, :, 0]
            r = np.einsum("cki,ci->ck", d, normal)
            w = np.exp(-((r / sigma[:, None]) ** 2))
        score = w.sum(axis=1)
        better = score > best
        best[better] = score[better]
        normals[better] = normal[better]
        residual[better] = np.sqrt(np.sum(w / score[:, None] * r * r, axis=1))[better]
    return normals, residual


@pytest.mark.parametrize("shape", ["noisy sphere", "thin plate", "repeated points"])
def test_compiled_plane_fits_match_eigh(shape):
    from scipy.spatial import cKDTree

    from nkf_model.normals._pca_kernels import weighted_planes

    rng = np.random.default_rng(5)
    if shape == "noisy sphere":
        p = rng.normal(size=(3000, 3))
        p = p / np.linalg.norm(p, axis=1, keepdims=True) + rng.normal(scale=0.01, size=(3000, 3))
    elif shape == "thin plate":  # two faces 0.01 apart: the first start keeps one face
        p = rng.uniform(-1, 1, (3000, 3))
        p[:, 2] = np.where(rng.random(3000) < 0.5, 0.0, 0.01)
    else:
        p = np.repeat(rng.uniform(size=(300, 3)), 3, axis=0)
    dist, idx = cKDTree(p).query(p, k=16)
    nb, sigma = p[idx], dist[:, 1:5].mean(axis=1) + 1e-300
    want_n, want_r = _planes_by_eigh(nb, sigma, 7, 2)
    got_n, got_r = np.empty((len(p), 3)), np.empty(len(p))
    weighted_planes(nb, sigma, 7, 2, got_n, got_r)
    assert np.allclose(np.linalg.norm(got_n, axis=1), 1.0)
    assert np.max(1.0 - np.abs(np.sum(got_n * want_n, axis=1))) < 1e-9
    assert np.allclose(got_r, want_r, rtol=1e-7, atol=1e-15)


def _rod_votes(follow_neighbours):
    """Visibility votes on a rod 5 spacings across, sampled on a regular grid (as a range scanner
    samples it), with the rod's exact normals; and which points are rod points."""
    from nkf_model.normals import estimate as est

    spacing = 0.01
    radius = 2.5 * spacing
    ring = int(round(2 * np.pi * radius / spacing))
    t = np.linspace(0, 2 * np.pi, ring, endpoint=False)
    z = np.arange(-0.3, 0.3, spacing)
    tt, zz = np.meshgrid(t, z)
    n = np.c_[np.cos(tt.ravel()), np.sin(tt.ravel()), np.zeros(tt.size)]
    p = np.c_[radius * n[:, :2], zz.ravel()]
    votes, weight = est.visibility_votes(p, n, spacing, directions=-est.fibonacci_directions(64),
                                         follow_neighbours=follow_neighbours)
    return votes, weight, np.abs(p[:, 2]) < 0.2


def test_thin_rods_are_not_hidden_by_their_own_discs():
    # A disc in the tangent plane stands off a curved surface: discs of 3 spacings on a rod 5
    # spacings across hide the rod from every view (TargetWithArrows' arrows: few view seeds, signs
    # propagated in from elsewhere). Discs that reach only the neighbours (misregistered scans) do not.
    from nkf_model.normals.estimate import VOTE_AGREEMENT, VOTE_WEIGHT

    def seeds(votes, weight, middle):
        agree = np.divide(np.abs(votes), weight, out=np.zeros_like(votes), where=weight > 0)
        seed = np.where((agree >= VOTE_AGREEMENT) & (weight >= VOTE_WEIGHT), np.sign(votes), 0.0)
        return seed[middle]  # the open ends show the inside of the tube

    seed = seeds(*_rod_votes(False))  # every disc SPLAT_RADIUS
    assert (seed > 0).mean() < 0.5
    seed = seeds(*_rod_votes(True))
    assert (seed > 0).mean() > 0.9, (seed > 0).mean()
    assert not (seed < 0).any()
