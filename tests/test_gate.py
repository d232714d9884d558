"""The learned kernel's gate on held-out sources (benchmarks/gate.py) and the record that makes
``nkf`` the default method (nkf_model.options)."""

from __future__ import annotations

import json

import pytest
from nkf_helpers import tiny_weights

from benchmarks import gate
from nkf_model.options import GATE_SPLIT, gate_passed, weights_gate
from nkf_model.train import corpus

MESHES = ["a", "b", "c"]


def _rows(delta_win: float, delta_tie: float, worst: float = 0.0):
    """Rows of bench.main_table with splines at 0.5 IoU and nkf shifted by the given amounts; mesh
    "c" additionally loses ``worst`` at 300 points."""
    rows = []
    for key in gate.WIN + gate.NOT_BEHIND:
        d = delta_win if key in gate.WIN else delta_tie
        label, noise = key
        for method, shift in (("splines", 0.0), ("nkf", d)):
            results = [{"mesh": m, "iou": 0.5 + shift - (worst if (method == "nkf" and m == "c" and label == "300")
                                                           else 0.0) + (worst / 2 if method == "nkf" and m != "c"
                                                                        and label == "300" else 0.0),
                        "chamfer_l1": 0.01, "normal_consistency": 0.9} for m in MESHES]
            rows.append((label, 128, noise, method, results))
    return rows


def test_a_run_that_wins_everywhere_passes():
    v = gate.verdict(_rows(0.03, 0.0), MESHES, overhead_extra=0.1)
    assert v["passed"] and v["split"] == GATE_SPLIT and v["meshes"] == 3
    assert all(c["passed"] for c in v["conditions"])


@pytest.mark.parametrize("win,tie,extra,failing", [
    (0.019, 0.0, 0.1, "300 points, noise 0.0"),             # short of the margin
    (0.03, -0.0021, 0.1, "3000 points, noise 0.0"),         # behind at 3,000 points
    (0.03, 0.0, 0.31, "extra time at 1,000 points"),        # too slow
    (0.03, 0.0, None, "extra time at 1,000 points"),        # overhead not measured
])
def test_each_condition_can_fail(win, tie, extra, failing):
    v = gate.verdict(_rows(win, tie), MESHES, overhead_extra=extra)
    assert not v["passed"]
    assert [c["name"] for c in v["conditions"] if not c["passed"]][0] == failing


def test_harm_on_one_mesh_fails_although_the_mean_wins():
    v = gate.verdict(_rows(0.03, 0.0, worst=0.09), MESHES, overhead_extra=0.1)  # mesh c: 0.03 - 0.09 = -0.06
    harm = [c for c in v["conditions"] if c["name"] == "no harm on any mesh"][0]
    assert not harm["passed"] and "c, 300 points" in harm["detail"] and not v["passed"]
    ok = [c for c in v["conditions"] if c["name"].startswith("300 points")]
    assert all(c["passed"] for c in ok)  # the mean still wins by the margin


def test_a_condition_not_measured_on_every_mesh_fails():
    rows = [(lab, r, n, m, res[:2]) if lab == "1000" else (lab, r, n, m, res) for lab, r, n, m, res in _rows(0.03, 0.0)]
    v = gate.verdict(rows, MESHES, overhead_extra=0.1)
    assert not v["passed"]
    assert {c["name"] for c in v["conditions"] if not c["passed"]} >= {"1000 points, noise 0.0", "no harm on any mesh"}


def test_the_stamp_is_what_makes_weights_the_default(tmp_path):
    w = tiny_weights(tmp_path / "w.safetensors")
    assert weights_gate(w) is None and not gate_passed(weights_gate(w))
    v = gate.verdict(_rows(0.03, 0.0), MESHES, overhead_extra=0.1)
    out = gate.stamp(w, tmp_path / "stamped.safetensors", dict(v, measured="2026-12-03"))
    rec = weights_gate(out)
    assert gate_passed(rec) and rec["meshes"] == 3
    failed = gate.stamp(w, tmp_path / "failed.safetensors", dict(v, passed=False))
    assert weights_gate(failed) is not None and not gate_passed(weights_gate(failed))
    # A record for another split (the old val split shares sources with train) does not count.
    other = gate.stamp(w, tmp_path / "val.safetensors", dict(v, split="val"))
    assert not gate_passed(weights_gate(other))
    # The stamped copy keeps the tensors and the rest of the metadata: it still loads as weights.
    from nkf_model.kernel.weights import read_weights
    t0, m0, _ = read_weights(w, "numpy")
    t1, m1, _ = read_weights(out, "numpy")
    assert t0.keys() == t1.keys() and all((t0[k] == t1[k]).all() for k in t0)
    assert {k: v for k, v in m1.items() if k != "gate"} == m0


def test_broken_files_have_no_record(tmp_path):
    (tmp_path / "junk").write_bytes(b"\xff" * 64)
    (tmp_path / "short").write_bytes(b"\x10\x00")
    bad = tmp_path / "badjson"
    header = json.dumps({"__metadata__": {"gate": "{not json"}}).encode()
    bad.write_bytes(len(header).to_bytes(8, "little") + header)
    for p in ("junk", "short", "badjson", "missing"):
        assert weights_gate(tmp_path / p) is None


def test_the_gate_runs_on_the_held_out_sources_only():
    pairs = gate.heldout_entries()
    train, held = corpus.source_split()
    assert {e.name for _, e in pairs} == {e.name for v in held.values() for e in v}
    assert not {e.name for _, e in pairs} & {e.name for e in train}
    sel = corpus.validation_subset(held, 6)
    rest = gate.heldout_entries(exclude_selection=6)
    assert len(rest) == len(pairs) - sum(len(v) for v in sel.values())
    assert not {e.name for _, e in rest} & {e.name for v in sel.values() for e in v}
