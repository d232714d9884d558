"""Hoppe's tangent-plane sign propagation (nkf_model.normals.consistent)."""

import numpy as np
import pytest

from nkf_model.normals.consistent import consistent_signs


def test_random_signs_on_a_sphere_become_outward_from_a_mostly_right_reference():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    flips = np.where(rng.random(3000) < 0.5, -1.0, 1.0)
    n = p * flips[:, None]
    ref = flips.copy()
    ref[:600] *= -1  # a reference wrong on 20 % of the points
    s, pieces = consistent_signs(p, n, reference=ref)
    assert pieces == 1
    assert np.all(np.einsum("ij,ij->i", n * s[:, None], p) > 0)


def _winding(state):
    from nkf_model.normals.estimate import winding_field

    return lambda poll: winding_field(state.points, state.normals, state.spacing, poll)


def _state(points):
    from nkf_model.normals import estimate

    sign, state, _ = estimate._estimate(points, estimate.DEFAULT_K, "outward", None)
    return sign, state


def test_the_check_takes_back_a_face_seeded_from_the_inside():
    # Views that look into an unscanned opening seed a whole face with the wrong side; the check
    # flips it back (a cap of the sphere given the wrong sign, as the orientation left it).
    from nkf_model.normals.consistent import tangent_plane_check

    rng = np.random.default_rng(1)
    p = rng.normal(size=(12000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    sign, state = _state(p)
    oriented = state.normals * sign[:, None]
    assert np.mean(np.einsum("ij,ij->i", oriented, p) > 0) > 0.99
    wrong = sign.copy()
    cap = p[:, 2] < -0.8  # about 10 % of the sphere
    wrong[cap] *= -1
    for winding in (None, _winding(state)):  # the winding number agrees (a closed object)
        fixed, flips = tangent_plane_check(state, wrong, winding=winding)
        assert flips >= cap.sum() * 0.95
        assert np.mean(np.einsum("ij,ij->i", state.normals * fixed[:, None], p) > 0) > 0.99


def test_the_check_leaves_thin_walls_alone(monkeypatch):
    # A cup whose walls are thinner than the spacing: the propagation crosses the wall and would make
    # the inner face agree with the outer one; the check keeps the orientation.
    from scan_shapes import open_box_points

    from nkf_model.normals import consistent

    p, n = open_box_points(12000, wall=0.008)
    sign, state = _state(p)
    assert state.spacing > 0.008
    assert np.mean(np.einsum("ij,ij->i", state.normals * sign[:, None], n) > 0) > 0.93
    kept, flips = consistent.tangent_plane_check(state, sign)
    assert flips == 0 and np.array_equal(kept, sign)
    monkeypatch.setattr(consistent, "MAX_FLIPS", 1.0)  # what the share test stops
    worse, flips = consistent.tangent_plane_check(state, sign)
    assert np.mean(np.einsum("ij,ij->i", state.normals * worse[:, None], n) > 0) < 0.8


def test_the_check_leaves_small_clouds_alone():
    from nkf_model.normals import consistent

    rng = np.random.default_rng(2)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    sign, state = _state(p)
    wrong = sign.copy()
    wrong[p[:, 2] < -0.8] *= -1
    assert consistent.tangent_plane_check(state, wrong) == (wrong, 0)


def test_the_check_leaves_thin_branches_alone():
    # 10,000 points of a rifle (thin barrel, sling, sights): the propagation runs along the thin parts
    # and flips 18 % of the points for a gain in agreement of only 1.4 %; the old rule (gain above
    # 0.1 %, at most 20 % flipped) took it and left 19 % of the signs wrong instead of 6 %. A right
    # correction gains at least 0.2 per share flipped (consistent.GAIN_PER_FLIP).
    from scipy.spatial import cKDTree

    from nkf_model.normals.estimate import estimate_normals
    from nkf_model.points.normalise import Normalisation
    from nkf_model.train import corpus, metrics

    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    v, f = corpus.load({e.name: e for e in corpus.manifest()}["quaternius__Sniper_rifle"])
    p, _ = metrics.sample_surface(v, f, 10_000, np.random.default_rng(0))
    x = Normalisation.fit(p).to_unit(p)
    nrm, info = estimate_normals(x, orientation="outward")
    rp, rn = metrics.sample_surface(v, f, 200_000, np.random.default_rng(1))
    _, i = cKDTree(rp).query(p)
    wrong = float(np.mean(np.einsum("ij,ij->i", nrm, rn[i]) < 0))
    assert info.consistent_flips == 0
    assert wrong < 0.1, wrong


def _corpus_samples(name, n):
    from nkf_model.train import corpus

    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    e = {e.name: e for e in corpus.manifest()}[name]
    v, f = corpus.load(e)
    return corpus.sample_input(v, f, n, 0.0, corpus.stable_seed("input", e.name, n, 0.0))


def test_the_check_asks_the_rest_of_a_closed_object():
    # 10,000 points of quaternius__Windmill (thin blades and struts), as the normal-estimation
    # benchmark samples them: the propagation flips 29 % of the points and passes the relation tests
    # (gain 6 %, 0.21 per share flipped), but it runs along the thin parts and leaves 33 % of the
    # signs wrong instead of 11 %. The winding number of the points it does not flip backs their old
    # signs at 35 % of them (consistent.REST_SUPPORT: at most 20 %), so the orientation's signs stay.
    from nkf_model.normals import consistent, sign_check

    p, n = _corpus_samples("quaternius__Windmill", 10_000)
    _, state = _state(p)
    sign, _ = sign_check.flip_wrong(state)  # as estimate_normals: the learned check comes first
    kept, flips = consistent.tangent_plane_check(state, sign, winding=_winding(state))
    assert flips == 0 and np.array_equal(kept, sign)
    open_, flips_open = consistent.tangent_plane_check(state, sign)
    assert flips_open > 0.2 * len(p)  # what the relation tests alone let through

    def wrong(s):
        return float(np.mean(np.einsum("ij,ij->i", state.normals * s[:, None], n) < 0))

    assert wrong(kept) < 0.15 and wrong(open_) > 0.25, (wrong(kept), wrong(open_))


def test_irregular_points_are_left_out_of_the_orientation(monkeypatch):
    # A simulated all-round scan of quaternius__Tree4 (37,344 points after the outlier test): 1,448
    # mixed pixels are left, a spacing or a few off the crown's surface. Oriented with them, 3.6 % of
    # the surface points' signs came out wrong (webbing between the crown's lobes, F-score 0.956);
    # oriented on the points with a regular neighbourhood and the rest signed by their neighbours,
    # 1.9 % (F-score 0.976). Since layer votes need seeds on both faces (a misregistered scan's
    # hidden copy no longer votes): 2.6 % with them, 1.2 % without. Measured on the first orientation:
    # the scan reads as misregistered and is oriented again, which leaves 0.47 % and 0.42 %.
    from benchmarks.bench_range_scans import DEFAULT_SCANS
    from benchmarks.range_scans import range_scan
    from nkf_model.normals import estimate
    from nkf_model.points.normalise import Normalisation
    from nkf_model.points.outliers import sparse_outliers
    from nkf_model.train import corpus

    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    e = {e.name: e for e in corpus.manifest()}["quaternius__Tree4"]
    v, f = corpus.load(e)
    sc = range_scan(v, f, seed=corpus.stable_seed(e.name, 0),
                    **{**DEFAULT_SCANS, "elevations": (40.0, 10.0, -30.0), "noise": 0.001, "misregistration": 0.002})
    x = Normalisation.fit(sc.points).to_unit(sc.points)
    keep = ~sparse_outliers(x)
    x, surface, truth = x[keep], ~sc.outlier[keep], sc.true_normals[keep]

    monkeypatch.setattr(estimate, "MISREGISTERED_LAYERS", 2.0)  # no second orientation

    def wrong():
        nrm, _ = estimate.estimate_normals(x)
        return float(np.mean(np.einsum("ij,ij->i", nrm[surface], truth[surface]) < 0))

    regular = wrong()
    monkeypatch.setattr(estimate, "IRREGULAR_MIN_POINTS", 10**9)
    everything = wrong()
    assert regular < 0.02 and everything > 0.02, (regular, everything)
