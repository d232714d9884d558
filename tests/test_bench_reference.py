"""The normals benchmark says which references are no solid (holes, faces pointing inward)."""

import numpy as np
from scan_shapes import cube_mesh

from benchmarks.bench_normals import format_table
from nkf_model.train import metrics


def _cube():
    return cube_mesh(0.4)


def _queries(n=4000):
    return metrics.volume_points(n, np.random.default_rng(0))


def test_a_closed_consistent_mesh_is_unambiguous():
    v, f = _cube()
    w = metrics.winding_number(v, f, _queries())
    assert abs(np.mean(w > 0.5) - 0.8 ** 3 / 1.1 ** 3) < 0.03  # the cube's share of the padded box
    assert metrics.ambiguous_share(w) < 0.005


def test_inward_faces_and_holes_make_the_reference_ambiguous():
    v, f = _cube()
    flipped = f.copy()
    flipped[:2] = flipped[:2, ::-1]  # one side of the cube points inward
    assert metrics.ambiguous_share(metrics.winding_number(v, flipped, _queries())) > 0.2
    open_box = f[2:]  # one side missing
    assert metrics.ambiguous_share(metrics.winding_number(v, open_box, _queries())) > 0.05
    # Overlapping closed parts (winding number 2) are no ambiguity.
    assert metrics.ambiguous_share(np.array([0.0, 1.0, 2.0, 1.02, -0.01])) == 0.0
    assert metrics.ambiguous_share(np.array([0.5, -0.6, 1.4, 0.0])) == 0.75


def _row(name, true, est, ambiguous):
    s = {"chamfer_l1": 0.004, "normal_consistency": 0.9, "fscore": 0.9}
    return {"mesh": name, "agree": 0.95, "t_est": 1.0, "ambiguous": ambiguous,
            "true": dict(s, iou=true), "est": dict(s, iou=est)}


def test_the_table_lists_ambiguous_references_and_keeps_the_verdict():
    rows = [_row("solid", 0.9, 0.9, 0.0), _row("open", 0.6, 0.2, 0.22)]
    text = format_table(rows, 10000, 0.0, 256)
    assert "FAIL" in text  # 0.2 lost on average: the listed reference still counts
    assert "open 22.0% (loss +0.400)" in text and "100% of the summed loss" in text
    assert "solid 0.0%" not in text
    assert "no solid" not in format_table([_row("solid", 0.9, 0.89, 0.0)], 10000, 0.0, 256)
