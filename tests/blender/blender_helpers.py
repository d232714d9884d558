"""Test data and small helpers for the Blender tests (no fixtures here; see conftest.py)."""

from __future__ import annotations

import importlib
import threading
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
PKG = "bl_ext.user_default.nkf_blender"
NKF_THREAD_NAMES = ("nkf-reconstruct", "nkf-pip-reader")


def ext(module: str = ""):
    """A module of the installed extension (looked up each time: re-enabling may reload it)."""
    return importlib.import_module(f"{PKG}.{module}" if module else PKG)


def nkf_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name in NKF_THREAD_NAMES and t.is_alive()]


def fibonacci_sphere(n: int, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """``n`` evenly spread points on a sphere and their outward unit normals, float64."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    d = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return d * radius + np.asarray(center, dtype=np.float64), d


def write_ply(path: Path, points, normals=None, colors=None) -> Path:
    """A binary PLY point cloud: x y z, plus nx ny nz when ``normals`` is given, plus red green blue
    (uchar) when ``colors`` (N, 3) uint8 is given."""
    from nkf_model.io.files import write_point_cloud

    return write_point_cloud(path, points, normals, colors)


def import_ply(bpy, path: Path):
    """``bpy.ops.wm.ply_import`` and return the imported (active) object."""
    before = set(bpy.data.objects)
    assert bpy.ops.wm.ply_import(filepath=str(path)) == {"FINISHED"}
    new = [o for o in bpy.data.objects if o not in before]
    assert len(new) == 1
    return new[0]


def read_vectors(attr_owner, name: str) -> np.ndarray:
    attr = attr_owner.attributes[name]
    buf = np.empty(len(attr.data) * 3, dtype=np.float32)
    attr.data.foreach_get("vector", buf)
    return buf.reshape(-1, 3)


def world_vertices(obj) -> np.ndarray:
    """The object's vertex positions in world coordinates, float64."""
    v = read_vectors(obj.data, "position").astype(np.float64)
    m = np.array(obj.matrix_world, dtype=np.float64)
    return v @ m[:3, :3].T + m[:3, 3]


def snapshot(bpy) -> dict:
    """Names of every object and mesh, and each object's positions/normals and matrix."""
    state = {
        "objects": sorted(o.name for o in bpy.data.objects),
        "meshes": sorted(m.name for m in bpy.data.meshes),
    }
    for o in bpy.data.objects:
        entry = {"matrix": [list(r) for r in o.matrix_world]}
        data = o.data
        if data is not None and hasattr(data, "attributes"):
            for a in data.attributes:
                if a.data_type == "FLOAT_VECTOR" and a.domain == "POINT":
                    entry[a.name] = read_vectors(data, a.name).tobytes()
            entry["attribute_names"] = sorted(a.name for a in data.attributes)
        state[o.name] = entry
    return state


def holdable_warm_up(release: threading.Event, record):
    """A stand-in for ``nkf_model.pipeline.warmup.warm_up``: calls ``record(steps)``, reports 25 %,
    then waits for ``release`` (or raises ``Cancelled`` once the cancel event is set)."""
    from nkf_model import Cancelled

    def fake(progress=None, cancel=None, methods=("splines", "nkf"), steps=None):
        record(steps)
        progress(0.25, "exact solve, Neural Splines")
        while not release.wait(0.02):
            if cancel is not None and cancel.is_set():
                raise Cancelled("the preparation was cancelled")
        progress(1.0, "done")
        return {}

    return fake
