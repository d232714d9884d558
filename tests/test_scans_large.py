"""A million-point scan read from PLY, reduced and reconstructed in a test-sized configuration."""

from __future__ import annotations

import time

import numpy as np
from shapes import torus_distance, torus_points

import nkf_model
from nkf_model.io.files import read_point_cloud, write_point_cloud


def test_million_points_from_ply(tmp_path):
    p, n = torus_points(1_000_000, seed=7)
    rng = np.random.default_rng(0)
    p = p + rng.normal(scale=0.002, size=p.shape)  # scanner noise
    colors = (np.clip(p * 0.4 + 0.5, 0, 1) * 255).astype(np.uint8)
    path = write_point_cloud(tmp_path / "scan.ply", p, None, colors)  # positions and colours, no normals
    cloud = read_point_cloud(path)
    assert len(cloud.points) == 1_000_000 and cloud.normals is None and cloud.colors is not None

    est = nkf_model.estimate(len(cloud.points), resolution=64, estimate_normals=True, reduce_to=20_000)
    assert est.reduced and est.points_solved == 20_000
    t0 = time.perf_counter()
    m = nkf_model.reconstruct(cloud.points, None, colors=cloud.colors, resolution=64, reduce_to=20_000,
                              normals_mode="estimate", device="cpu")
    elapsed = time.perf_counter() - t0
    red = m.stats["reduction"]
    assert red["from"] == 1_000_000 and 5_000 < red["to"] <= 20_000 and red["voxel"] > 0
    assert m.stats["points_used"] == red["to"] and m.stats["normals"] == "estimated"
    d = torus_distance(m.vertices.astype(np.float64))
    assert d.mean() < 0.01 and np.quantile(d, 0.99) < 0.03
    assert m.colors is not None and len(m.colors) == len(m.vertices)
    # Colours follow position (red grows with x): the mesh keeps that gradient.
    corr = np.corrcoef(m.vertices[:, 0], m.colors[:, 0].astype(float))[0, 1]
    assert corr > 0.95
    assert elapsed < 120  # a sanity bound, not a benchmark (those are in docs/scans.md)
