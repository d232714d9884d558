"""The whole pipeline: shapes, mesh validity, frames, progress and cancel."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree
from shapes import sphere_points, torus_distance, torus_points

import nkf_model
from nkf_model.surface.mesh import Mesh


def edge_use_counts(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed, counts = np.unique(e, axis=0, return_counts=True)
    undirected = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)[1]
    return directed, counts, undirected


def assert_watertight_outward(mesh: Mesh):
    f = mesh.faces
    _, counts, undirected = edge_use_counts(f)
    assert (undirected == 2).all(), "every edge is shared by exactly two triangles"
    assert (counts == 1).all(), "consistent winding: each directed edge is used once"
    # Outward: the signed volume is positive.
    v = mesh.vertices.astype(np.float64) - mesh.vertices.mean(axis=0)
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    assert vol > 0


def test_sphere_within_chamfer_bound(sphere500):
    p, n = sphere500
    m = nkf_model.reconstruct(p, n, method="splines", resolution=64, device="cpu")
    assert m.vertices.dtype == np.float32 and m.vertices.shape[1] == 3
    assert m.faces.dtype == np.int32 and m.faces.shape[1] == 3
    assert m.normals.shape == m.vertices.shape
    r = np.linalg.norm(m.vertices, axis=1)
    # Chamfer-style bound: every vertex within 1 % of the radius, and every input point close to the mesh.
    assert np.abs(r - 1).max() < 0.01
    d, _ = cKDTree(m.vertices).query(p)
    assert d.max() < 0.05
    assert_watertight_outward(m)
    # Vertex normals point out of the sphere.
    assert (np.sum(m.normals * m.vertices, axis=1) > 0).mean() > 0.999


def test_torus_within_chamfer_bound():
    p, n = torus_points(1500, seed=2)
    m = nkf_model.reconstruct(p, n, resolution=96, device="cpu")
    assert_watertight_outward(m)
    to_surface = torus_distance(m.vertices.astype(np.float64))
    to_mesh, _ = cKDTree(m.vertices).query(p)
    chamfer = 0.5 * (to_surface.mean() + to_mesh.mean())
    assert chamfer < 0.01, chamfer
    assert to_surface.max() < 0.03
    # Genus one: V - E + F = 0.
    e = np.unique(np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]]), axis=1), axis=0)
    assert len(m.vertices) - len(e) + len(m.faces) == 0


@pytest.mark.parametrize("center,radius", [((1e6, -2e6, 5e5), 3.0), ((0.0, 0.0, 0.0), 1e-5), ((7.0, 8.0, 9.0), 1e4)])
def test_output_in_the_input_frame(center, radius):
    """Coordinates around 1e6, tiny objects and large ones come back where they were."""
    p, n = sphere_points(400, radius=radius, center=center, seed=3)
    m = nkf_model.reconstruct(p, n, method="splines", resolution=48, device="cpu")
    local = m.local_vertices.astype(np.float64)
    world = m.center + local
    r = np.linalg.norm(world - np.asarray(center), axis=1)
    assert np.abs(r / radius - 1).max() < 0.02
    np.testing.assert_allclose(m.center, center, atol=radius * 0.05)
    # float32 vertices are as close as float32 allows.
    np.testing.assert_allclose(m.vertices, world, rtol=2e-7 * 4, atol=radius * 1e-4)


def test_falkon_solver_on_request():
    p, n = sphere_points(1200, seed=4)
    m = nkf_model.reconstruct(p, n, resolution=48, device="cpu", max_centres=1000, solver="falkon")
    assert m.stats["solver"] == "falkon" and m.stats["centres"] == 1000
    r = np.linalg.norm(m.vertices, axis=1)
    assert np.abs(r - 1).max() < 0.02
    assert_watertight_outward(m)


def test_progress_is_monotonic_and_names_every_stage(sphere500):
    p, n = sphere500
    calls = []
    nkf_model.reconstruct(p, n, resolution=64, device="cpu", progress=lambda f, s: calls.append((f, s)))
    fr = [f for f, _ in calls]
    assert fr == sorted(fr) and fr[0] >= 0 and fr[-1] == 1.0
    stages = [s for _, s in calls]
    for s in ("normalise", "augment", "solve", "evaluate", "mesh", "done"):
        assert s in stages
    assert stages[-1] == "done"
    assert len(calls) > 10  # between chunks, not only between stages


@pytest.fixture(scope="module")
def compiled():
    """numba compiles each kernel on its first call in a fresh environment (seconds, and not
    interruptible); the half-second promise is about the work, so compile first."""
    p, n = sphere_points(400, seed=9)
    nkf_model.reconstruct(p, n, resolution=32, device="cpu")
    nkf_model.reconstruct(p, n, resolution=32, device="cpu", max_centres=300)


@pytest.mark.parametrize("stage", ["solve", "evaluate", "mesh"])
def test_cancel_stops_within_half_a_second(stage, compiled):
    p, n = sphere_points(2500, seed=5)
    cancel = threading.Event()
    seen = {}

    def progress(f, s):
        if s == stage and "t" not in seen:
            seen["t"] = time.perf_counter()
            cancel.set()

    t0 = time.perf_counter()
    with pytest.raises(nkf_model.Cancelled):
        nkf_model.reconstruct(p, n, resolution=256, device="cpu", progress=progress, cancel=cancel)
    assert "t" in seen
    assert time.perf_counter() - seen["t"] < 0.5
    assert time.perf_counter() - t0 < 60


def test_cancel_from_another_thread(compiled):
    p, n = sphere_points(6000, seed=6)
    cancel = threading.Event()
    result = {}

    def work():
        try:
            nkf_model.reconstruct(p, n, resolution=256, device="cpu", cancel=cancel)
            result["r"] = "finished"
        except nkf_model.Cancelled:
            result["r"] = "cancelled"
            result["t"] = time.perf_counter()

    th = threading.Thread(target=work)
    th.start()
    time.sleep(0.5)
    t_set = time.perf_counter()
    cancel.set()
    th.join(5)
    assert not th.is_alive()
    assert result["r"] == "cancelled"
    assert result["t"] - t_set < 0.5


def test_already_set_cancel_does_nothing(sphere500):
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(nkf_model.Cancelled):
        nkf_model.reconstruct(*sphere500, cancel=cancel)


def test_deterministic(sphere500):
    a = nkf_model.reconstruct(*sphere500, resolution=32, device="cpu")
    b = nkf_model.reconstruct(*sphere500, resolution=32, device="cpu")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_torch_engine_agrees_with_numba(sphere500):
    """The CUDA path is PyTorch float64; run on the CPU it must agree with the numba engine.
    Stated tolerance: vertex positions within 1e-6 of the unit box."""
    import sys

    from nkf_model.kernel.engines import TorchEngine

    rec = sys.modules["nkf_model.pipeline.reconstruct"]

    p, n = sphere500
    a = nkf_model.reconstruct(p, n, resolution=40, device="cpu")
    orig = rec.select_engine
    rec.select_engine = lambda device: TorchEngine("cpu")
    try:
        b = nkf_model.reconstruct(p, n, resolution=40, device="cpu")
    finally:
        rec.select_engine = orig
    assert b.stats["engine"] == "torch:cpu"
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.local_vertices / a.scale, b.local_vertices / b.scale, atol=1e-6)


def _boundary_edges(faces):
    f = np.asarray(faces, dtype=np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e[:, 0] * (int(f.max()) + 1) + e[:, 1], axis=0, return_counts=True)
    return int((counts == 1).sum())


def test_close_caps_a_surface_that_runs_out_of_the_grid(tmp_path):
    # A wavy sheet across the whole bounding box: its inside (below) runs into the grid's bounds.
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, size=(1500, 2))
    z = 0.1 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
    p = np.column_stack([xy, z])
    dzdx = 0.3 * np.cos(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
    dzdy = -0.2 * np.sin(3 * xy[:, 0]) * np.sin(2 * xy[:, 1])
    n = np.column_stack([-dzdx, -dzdy, np.ones(len(p))])
    open_mesh = nkf_model.reconstruct(p, n, resolution=48)
    closed = nkf_model.reconstruct(p, n, resolution=48, close=True)
    assert _boundary_edges(open_mesh.faces) > 0
    assert _boundary_edges(closed.faces) == 0 and closed.stats["close"]
    # The cap adds surface at the grid's faces and leaves the sheet itself where it was.
    from scipy.spatial import cKDTree

    d, _ = cKDTree(closed.vertices).query(open_mesh.vertices)
    assert len(closed.faces) > len(open_mesh.faces) and np.mean(d < 1e-6) > 0.9


def test_auto_device_keeps_the_partition_of_unity_on_the_cpu(monkeypatch):
    """With a GPU engine available, "auto" still runs the PoU's fused CPU loop (the GPU path goes
    patch by patch); smaller inputs stay on the GPU engine. A CPU-backed engine stands in for CUDA."""
    import sys

    from nkf_model.kernel.engines import TorchEngine

    rec = sys.modules["nkf_model.pipeline.reconstruct"]

    class FakeCuda(TorchEngine):
        def __init__(self):
            super().__init__("cpu")
            self.device = "cuda"

    monkeypatch.setattr(rec, "select_engine", lambda device: FakeCuda())
    p, n = sphere_points(4000, seed=3)
    assert nkf_model.reconstruct(p, n, resolution=32).stats["engine"].startswith("numba")
    assert nkf_model.reconstruct(p[:500], n[:500], resolution=32).stats["engine"] == "torch:cuda"
