"""Make the bundled sample point cloud ``nkf_model/data/sample.ply``.

Samples 5,000 oriented points uniformly by area on "Blub" (Keenan Crane's fish, via the cinolib
examples in ``../shared/data/meshes``: ``cinolib__blub_triangulated.ply``) and writes them as a binary
PLY with ``x y z nx ny nz`` (float32). Positions are in the corpus's unit box, scaled by 2 (so the fish
is 2 units long, a natural size in Blender); normals point out of the surface. Deterministic (seeded).

    python scripts/make_sample.py [--meshes DIR] [--points N] [--out PATH]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nkf_model.io.files import read_mesh, write_point_cloud
from nkf_model.train import corpus
from nkf_model.train.metrics import sample_surface

SOURCE = "cinolib__blub_triangulated.ply"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", type=Path, default=corpus.corpus_dir())
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=2022)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "nkf_model/data/sample.ply")
    args = ap.parse_args(argv)
    v, f = read_mesh(args.meshes / SOURCE)
    pts, nrm = sample_surface(v, f, args.points, np.random.default_rng(args.seed))
    write_point_cloud(args.out, 2.0 * pts, nrm)
    print(f"{args.out}: {args.points} oriented points from {SOURCE} ({args.out.stat().st_size:,} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
