"""Point-cloud readers: time and peak memory per format, against the size of the arrays kept.

    python -m benchmarks.bench_formats [--points 2000000] [--out DIR]

Writes one file per format (LAS, LAZ, E57 with two scans, XYZ text, PCD binary, PCD
binary_compressed, binary PLY) holding the same points in map coordinates (offset 4.5e6 m),
then reads each in a fresh process (``nkf_model.io.files.read_point_cloud``) and reports the
seconds, the peak resident memory above what the process held before the read (``VmHWM`` less
``VmRSS`` just before; the libraries, numba's LZF loop included, are loaded before that), the bytes
of the arrays kept, their ratio, and the largest distance
between the points read (plus their offset) and the points written. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MAP = np.array([4_500_000.0, 5_400_000.0, 250.0])

CHILD = r"""
import json, sys, time
import numpy as np
import laspy, pye57, plyfile  # loaded before the baseline is taken
import nkf_model.io.files, nkf_model.io.las, nkf_model.io.e57, nkf_model.io.text, nkf_model.io.pcd, nkf_model.io.ply
nkf_model.io.pcd.lzf_decompress(bytes([0, 65]), 1, compiled=True)  # numba: a fixed cost, not the file's

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024

path, ref = sys.argv[1], sys.argv[2]
want = np.load(ref)
base = status("VmRSS:")
# The high-water mark counts from process start: reset it where the kernel allows (Linux >= 4.0).
try:
    open("/proc/self/clear_refs", "w").write("5")
except OSError:
    pass
t = time.perf_counter()
c = nkf_model.io.files.read_point_cloud(path)
sec = time.perf_counter() - t
peak = status("VmHWM:")
kept = sum(a.nbytes for a in (c.points, c.normals, c.colors, c.intensity, c.classification) if a is not None)
err = float(np.abs(c.absolute_points() - want).max())
print(json.dumps(dict(seconds=sec, extra=peak - base, kept=kept, n=len(c.points), err=err, what=c.describe())))
"""


def write_all(folder: Path, n: int) -> dict[str, tuple[Path, np.ndarray]]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from pointcloud_files import pcd_bytes, sphere, write_e57, write_las

    from nkf_model.io.files import write_point_cloud

    p, nrm = sphere(n, seed=0, radius=50.0)
    pts = np.round((p + MAP) / 1e-3) * 1e-3  # millimetres, as a LAS scale of 0.001 holds them
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(n, 3))
    files = {}
    t = time.perf_counter()
    files["LAS 1.2 fmt 3"] = write_las(folder / "a.las", pts, rgb=rgb * 257, intensity=rng.integers(0, 4000, n),
                                       classification=rng.choice([2, 6], n), scale=1e-3), pts
    files["LAZ 1.2 fmt 3"] = write_las(folder / "a.laz", pts, rgb=rgb * 257, intensity=rng.integers(0, 4000, n),
                                       classification=rng.choice([2, 6], n), scale=1e-3), pts
    half = n // 2
    t1, t2 = MAP + [60.0, 0, 0], MAP + [-60.0, 0, 0]
    files["E57, 2 scans"] = write_e57(folder / "a.e57", [
        {"xyz": pts[:half] - t1, "translation": t1, "rgb": rgb[:half], "intensity": rng.random(half)},
        {"xyz": pts[half:] - t2, "translation": t2, "rgb": rgb[half:], "intensity": rng.random(n - half)},
    ]), pts
    with open(folder / "a.xyz", "w") as fh:
        for s in range(0, n, 200_000):
            np.savetxt(fh, np.c_[pts[s:s + 200_000], rgb[s:s + 200_000]], fmt="%.3f %.3f %.3f %d %d %d")
    files["XYZ text (x y z r g b)"] = folder / "a.xyz", pts
    # PCD, PLY: float32 positions around the origin (as PCL and most PLY writers store them).
    local = p.astype(np.float32)
    fields = {"x": local[:, 0], "y": local[:, 1], "z": local[:, 2], "normal_x": nrm[:, 0],
              "normal_y": nrm[:, 1], "normal_z": nrm[:, 2]}
    (folder / "a.pcd").write_bytes(pcd_bytes(fields, "binary"))
    files["PCD binary"] = folder / "a.pcd", local.astype(np.float64)
    # binary_compressed: the same columns as one LZF stream of literal runs (valid LZF, written fast;
    # random floats barely compress anyway, and the reader's work is per run either way).
    raw = b"".join(np.ascontiguousarray(v, "<f4").tobytes() for v in fields.values())
    runs = np.frombuffer(raw + bytes(-len(raw) % 32), np.uint8).reshape(-1, 32)
    stream = np.concatenate([np.full((len(runs), 1), 31, np.uint8), runs], axis=1).tobytes()
    tail = len(raw) % 32
    if tail:  # the last run is shorter
        stream = stream[: -33] + bytes([tail - 1]) + raw[-tail:]
    head = pcd_bytes({k: v[:1] for k, v in fields.items()}, "binary").split(b"DATA binary")[0]
    head = head.replace(b"WIDTH 1", f"WIDTH {n}".encode()).replace(b"POINTS 1", f"POINTS {n}".encode())
    (folder / "c.pcd").write_bytes(head + b"DATA binary_compressed\n"
                                   + np.array([len(stream), len(raw)], "<u4").tobytes() + stream)
    files["PCD binary_compressed"] = folder / "c.pcd", local.astype(np.float64)
    write_point_cloud(folder / "a.ply", local, nrm, rgb.astype(np.uint8))
    files["PLY binary"] = folder / "a.ply", local.astype(np.float64)
    print(f"wrote the files in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--out", default=None, help="folder for the files (default: a temporary one)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.out or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        files = write_all(folder, args.points)
        print("| format | points | file MB | read s | points/s | arrays kept MB | peak above start MB | peak / kept "
              "| max error (m) |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
        for name, (path, want) in files.items():
            ref = folder / "want.npy"
            np.save(ref, want)
            run = subprocess.run([sys.executable, "-c", CHILD, str(path), str(ref)], capture_output=True, text=True)
            if run.returncode != 0:
                print(f"| {name} | failed: {run.stderr.strip().splitlines()[-1]} |")
                continue
            r = json.loads(run.stdout.strip().splitlines()[-1])
            print(f"| {name} | {r['n']:,} | {path.stat().st_size / 1e6:,.0f} | {r['seconds']:.2f} "
                  f"| {r['n'] / r['seconds'] / 1e6:.2f} M | {r['kept'] / 1e6:,.0f} | {r['extra'] / 1e6:,.0f} "
                  f"| {r['extra'] / r['kept']:.2f} | {r['err']:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
