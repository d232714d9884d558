"""The simulated-scan benchmark's scores against the part of the reference a scanner saw."""

import numpy as np

from benchmarks.bench_range_scans import seen_metrics


def _square(n, x0, rng):
    """``n`` samples of the unit square at height 0 starting at ``x = x0``, normals +z."""
    p = np.column_stack([x0 + rng.random(n), rng.random(n), np.zeros(n)])
    return p, np.tile([0.0, 0.0, 1.0], (n, 1))


def test_seen_part_f_is_what_the_seen_part_alone_would_score():
    rng = np.random.default_rng(0)
    a, an = _square(20_000, 0.0, rng)
    b, bn = _square(20_000, 3.0, rng)  # never scanned: 3 units from every scan point
    ref, ref_n = np.vstack([a, b]), np.vstack([an, bn])
    scan = _square(5_000, 0.0, rng)[0]
    # The output is exactly the seen square: perfect where seen, nothing where not.
    out, out_n = _square(20_000, 0.0, rng)
    m = seen_metrics(out, out_n, ref, ref_n, scan, tau=0.02)
    assert abs(m["seen_share"] - 0.5) < 0.01
    assert abs(m["seen_part_f"] - 2 * 0.5 / 1.5) < 0.01
    assert m["seen_fscore"] > 0.99  # on the seen part it is perfect
    # It depends on the scan, not on the output.
    m2 = seen_metrics(ref, ref_n, ref, ref_n, scan, tau=0.02)
    assert m2["seen_part_f"] == m["seen_part_f"]
    far = seen_metrics(b, bn, ref, ref_n, scan, tau=0.02)  # only the unseen square: nothing scored as seen
    assert far["seen_part_f"] == m["seen_part_f"] and far["seen_fscore"] == 0.0
    # Everything seen: the seen part is the reference.
    m3 = seen_metrics(ref, ref_n, ref, ref_n, ref, tau=0.02)
    assert m3["seen_part_f"] == 1.0
