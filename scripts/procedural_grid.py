"""Draw a grid of procedural training shapes (nkf_model.train.procedural) to a PNG.

    python scripts/procedural_grid.py --out docs/procedural-shapes.png --rows 5 --cols 6

Each panel shows one shape's marching-cubes surface, lit from the upper left, in the corpus's unit
box; the title is its seed and family. Rows cycle through the families.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="docs/procedural-shapes.png")
    ap.add_argument("--rows", type=int, default=5)
    ap.add_argument("--cols", type=int, default=6)
    ap.add_argument("--start", type=int, default=0, help="first seed")
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from nkf_model.train import procedural as P

    spec = P.ProceduralSpec()
    fig = plt.figure(figsize=(2.2 * args.cols, 2.3 * args.rows))
    light = np.array([-0.4, -0.6, 0.7])
    light /= np.linalg.norm(light)
    colours = {"furniture": (0.85, 0.62, 0.38), "mechanical": (0.6, 0.68, 0.78), "organic": (0.85, 0.55, 0.55),
               "tube": (0.55, 0.78, 0.55), "shell": (0.78, 0.72, 0.5)}
    for r in range(args.rows):
        fam = P.FAMILIES[r % len(P.FAMILIES)]
        for c in range(args.cols):
            seed = args.start + r * args.cols + c
            _, f = P.make_shape(seed, spec, family=fam)
            v, faces = P.surface_mesh(f, 56)
            tri = v[faces]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
            ax = fig.add_subplot(args.rows, args.cols, r * args.cols + c + 1, projection="3d")
            ax.add_collection3d(Poly3DCollection(tri, facecolors=np.array(colours[fam])[None] * shade[:, None],
                                                 edgecolors="none"))
            lo, hi = v.min(axis=0), v.max(axis=0)
            ctr, h = 0.5 * (lo + hi), 0.5 * (hi - lo).max()
            ax.set_xlim(ctr[0] - h, ctr[0] + h)
            ax.set_ylim(ctr[1] - h, ctr[1] + h)
            ax.set_zlim(ctr[2] - h, ctr[2] + h)
            ax.view_init(elev=22, azim=-60)
            ax.set_axis_off()
            ax.set_title(f"{fam} {seed}", fontsize=8)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
