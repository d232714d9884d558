"""Check the CUDA path against the CPU: reconstruct the bundled sample (and a 20k-point cloud for the
PoU solver) on both devices and compare the meshes.

    python scripts/cuda_check.py [--weights W.safetensors]

Prints one row per method and solver: times on each device, triangle counts, and the symmetric
Chamfer-L1 distance between the CPU and CUDA meshes (in units of the input's bounding box).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nkf_model.io.files import read_point_cloud
from nkf_model.kernel.engines import cuda_available
from nkf_model.pipeline import reconstruct


def _chamfer(a, b):
    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    args = ap.parse_args()
    if not cuda_available():
        print("no CUDA device; nothing to compare")
        return 1
    pc = read_point_cloud(Path(__file__).resolve().parent.parent / "nkf_model" / "data" / "sample.ply")
    rng = np.random.default_rng(0)
    big = rng.normal(size=(20000, 3))
    big /= np.linalg.norm(big, axis=1, keepdims=True)
    runs = [("splines", pc.points, pc.normals, {}), ("splines (20k, PoU)", big, big, {})]
    if args.weights:
        runs.append(("nkf", pc.points, pc.normals, {"weights": args.weights}))
    print(f"{'method':<22}{'cpu s':>8}{'cuda s':>8}{'cpu tris':>10}{'cuda tris':>10}{'chamfer':>10}")
    for name, p, n, kw in runs:
        meth = "nkf" if name == "nkf" else "splines"
        out = {}
        for dev in ("cpu", "cuda"):
            reconstruct(p[:500], n[:500], method=meth, device=dev, resolution=64, **kw)  # warm-up
            t = time.perf_counter()
            out[dev] = (reconstruct(p, n, method=meth, device=dev, **kw), time.perf_counter() - t)
        (mc, tc), (mg, tg) = out["cpu"], out["cuda"]
        ext = float(np.ptp(p, axis=0).max())
        print(f"{name:<22}{tc:>8.2f}{tg:>8.2f}{len(mc.faces):>10}{len(mg.faces):>10}"
              f"{_chamfer(mc.vertices, mg.vertices) / ext:>10.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
