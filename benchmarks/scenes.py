"""Synthetic scans of rooms furnished with corpus meshes: test data for open, unoriented, large inputs.

:func:`make_scene` builds a room: a floor, two or three walls (one-sided, facing into the room) and
several corpus meshes standing on the floor, scaled to furniture size, turned about the vertical
axis, each with its own colour. :func:`scan` simulates a scanner at a few positions inside the room:
it samples the surfaces densely, keeps only the samples that some scanner sees (a cube-map depth
buffer per scanner, :mod:`benchmarks._raster_kernels`, and front-facing), draws the requested number
of points, and adds range noise along the line of sight of the scanner that saw each point. The
hidden parts (the floor under the objects, their backs against a wall, the outside of the walls)
have no points, as in a real scan.

Units are metres. Everything is NumPy, SciPy and numba; seeds make every scene reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nkf_model.train import corpus, metrics

from . import _raster_kernels as rk

ROOM = (4.0, 3.5, 2.4)  # width (x), depth (y), wall height (z), metres
CUBE_SIZE = 768  # pixels per cube-map face
NEAR = 0.05


@dataclass
class Scene:
    """Triangles of a room and the scanner positions.

    Attributes
    ----------
    vertices : (V, 3) float64
        Metres; z up, the floor at z = 0.
    faces : (F, 3) int64
        Counter-clockwise seen from the side the surface faces.
    face_colors : (F, 3) uint8
        Colour of each triangle.
    part : (F,) int64
        0 floor, 1 walls, 2... objects.
    viewpoints : (K, 3) float64
        Scanner positions.
    objects : list of str
        Names of the corpus meshes placed in the room.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_colors: np.ndarray
    part: np.ndarray
    viewpoints: np.ndarray
    objects: list


@dataclass
class Scan:
    """Scanned points of a scene.

    Attributes
    ----------
    points : (N, 3) float64
        Noisy positions (metres).
    normals : (N, 3) float64
        True unit normals of the surfaces the points came from (a scanner does not measure them;
        benchmarks use them as the "given normals" case).
    colors : (N, 3) uint8
    seen_by : (N,) int64
        Index of the scanner that saw each point.
    reference_points, reference_normals : (M, 3) float64
        Dense noiseless samples of every visible surface, for accuracy metrics.
    """

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    seen_by: np.ndarray
    reference_points: np.ndarray
    reference_normals: np.ndarray


def _grid_quad(origin, du, dv, nu, nv):
    """A rectangle ``origin + s du + t dv`` cut into 2 nu nv triangles facing ``du x dv``."""
    s = np.linspace(0.0, 1.0, nu + 1)
    t = np.linspace(0.0, 1.0, nv + 1)
    ss, tt = np.meshgrid(s, t, indexing="ij")
    v = origin + ss.reshape(-1, 1) * du + tt.reshape(-1, 1) * dv
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f


def _rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_scene(seed: int = 0, n_objects: int = 4, split: str = "val", walls: int = 3,
               names: list | None = None) -> Scene:
    """A room with ``n_objects`` corpus meshes of ``split`` (or the named ones) on its floor.

    Objects are scaled to 0.5-1.1 m, placed without overlapping (bounding circles) and at least
    0.2 m from the walls; three scanners stand at 1.5-1.7 m height in the free floor area.
    """
    rng = np.random.default_rng(seed)
    w, d, h = ROOM
    parts_v, parts_f, parts_c, parts_p = [], [], [], []

    def add(v, f, color, part):
        parts_f.append(f + sum(len(x) for x in parts_v))
        parts_v.append(v)
        parts_c.append(np.tile(np.asarray(color, dtype=np.uint8), (len(f), 1)))
        parts_p.append(np.full(len(f), part))

    # Floor (faces up) with a two-tone checker pattern of 0.5 m tiles, so colours have structure.
    fv, ff = _grid_quad(np.zeros(3), np.array([w, 0, 0]), np.array([0, d, 0]), 40, 35)
    centre = fv[ff].mean(axis=1)
    checker = (np.floor(centre[:, 0] / 0.5) + np.floor(centre[:, 1] / 0.5)) % 2
    parts_f.append(ff)
    parts_v.append(fv)
    parts_c.append(np.where(checker[:, None] > 0, [150, 120, 90], [110, 85, 60]).astype(np.uint8))
    parts_p.append(np.zeros(len(ff), dtype=np.int64))
    # Walls facing into the room: y = d (back), x = 0 (left), x = w (right).
    wall_color = (200, 195, 180)
    add(*_grid_quad(np.array([0, d, 0]), np.array([w, 0, 0]), np.array([0, 0, h]), 40, 24), wall_color, 1)
    add(*_grid_quad(np.array([0, 0, 0]), np.array([0, d, 0]), np.array([0, 0, h]), 35, 24), wall_color, 1)
    if walls >= 3:
        add(*_grid_quad(np.array([w, d, 0]), np.array([0, -d, 0]), np.array([0, 0, h]), 35, 24), wall_color, 1)

    entries = [e for e in corpus.manifest() if e.split == split]
    if names:
        pick = [e for e in entries if e.name in set(names)]
    else:
        pick = [entries[i] for i in rng.choice(len(entries), size=n_objects, replace=False)]
    placed = []  # (x, y, radius)
    for k, e in enumerate(pick):
        v, f = corpus.load(e)
        v = v - v.min(axis=0)
        size = rng.uniform(0.5, 1.1)
        v = v * (size / float(v.max()))
        v = v - np.array([*(0.5 * (v.max(axis=0)[:2])), 0.0])
        v = v @ _rotation_z(rng.uniform(0, 2 * np.pi)).T
        radius = float(np.linalg.norm(v[:, :2], axis=1).max())
        for _ in range(200):
            x = rng.uniform(0.2 + radius, w - 0.2 - radius)
            y = rng.uniform(0.2 + radius, d - 0.2 - radius)
            if all(np.hypot(x - a, y - b) > radius + r + 0.1 for a, b, r in placed):
                break
        placed.append((x, y, radius))
        hue = rng.uniform(0, 1)
        color = (np.array([np.cos(2 * np.pi * (hue + t)) for t in (0, 1 / 3, 2 / 3)]) * 80 + 150).astype(np.uint8)
        add(v + np.array([x, y, 0.0]), f, color, 2 + k)
    vertices = np.concatenate(parts_v)
    faces = np.concatenate(parts_f)
    # Scanners in the free floor area, away from objects.
    viewpoints = []
    for _ in range(3):
        for _ in range(500):
            x, y = rng.uniform(0.5, w - 0.5), rng.uniform(0.4, d - 0.6)
            if all(np.hypot(x - a, y - b) > r + 0.35 for a, b, r in placed) and all(
                np.hypot(x - p[0], y - p[1]) > 0.8 for p in viewpoints
            ):
                break
        viewpoints.append((x, y, rng.uniform(1.5, 1.7)))
    return Scene(
        vertices=vertices,
        faces=faces,
        face_colors=np.concatenate(parts_c),
        part=np.concatenate(parts_p),
        viewpoints=np.asarray(viewpoints, dtype=np.float64),
        objects=[e.name for e in pick],
    )


_AXES = [(np.array(a), np.array(b), np.array(c)) for a, b, c in (
    ((0, 1, 0), (0, 0, 1), (1, 0, 0)), ((0, 1, 0), (0, 0, 1), (-1, 0, 0)),
    ((1, 0, 0), (0, 0, 1), (0, 1, 0)), ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    ((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((1, 0, 0), (0, 1, 0), (0, 0, -1)),
)]


def visible_from(scene: Scene, points: np.ndarray, normals: np.ndarray, viewpoint: np.ndarray,
                 size: int = CUBE_SIZE) -> np.ndarray:
    """Mask (N,) of surface points that the scanner at ``viewpoint`` sees (front-facing and not
    occluded, by a six-face cube map of depth buffers)."""
    rel_v = scene.vertices - viewpoint
    rel_p = points - viewpoint
    dist = np.linalg.norm(rel_p, axis=1)
    cos = -np.sum(normals * rel_p, axis=1) / np.maximum(dist, 1e-12)
    seen = np.zeros(len(points), dtype=bool)
    for a, b, c in _AXES:
        cam = np.stack([rel_v @ a, rel_v @ b, rel_v @ c], axis=-1)[scene.faces]
        zbuf = rk.rasterise_faces(np.ascontiguousarray(cam), size, NEAR)[0]
        pa, pb, pw = rel_p @ a, rel_p @ b, rel_p @ c
        inside = (pw > NEAR) & (np.abs(pa) <= pw) & (np.abs(pb) <= pw)
        depth = rk.lookup_depth(zbuf, pa, pb, pw)
        tol = pw * (0.004 + 3.0 / size / np.maximum(np.abs(cos), 0.1))
        seen |= inside & (pw <= depth + tol)
    return seen & (cos > 0.05)


def scan(scene: Scene, n_points: int, noise: float = 0.003, seed: int = 0, oversample: int = 6,
         reference: int = 200_000) -> Scan:
    """Scan ``scene`` with its scanners and return ``n_points`` noisy points.

    Parameters
    ----------
    n_points : int
        Points in the scan (drawn uniformly from everything any scanner sees).
    noise : float
        Standard deviation of the range noise along each point's line of sight, metres.
    oversample : int
        Surface samples drawn per output point before the visibility test.
    reference : int
        Noiseless visible samples kept for accuracy metrics.
    """
    rng = np.random.default_rng(seed)
    total = oversample * n_points + reference
    pts, nrm, face_of = _sample(scene.vertices, scene.faces, total, rng)
    seen_by = np.full(len(pts), -1)
    for k, vp in enumerate(scene.viewpoints):
        vis = visible_from(scene, pts, nrm, vp) & (seen_by < 0)
        seen_by[vis] = k
    visible = np.flatnonzero(seen_by >= 0)
    rng.shuffle(visible)
    ref = visible[:reference]
    use = visible[reference : reference + n_points]
    if len(use) < n_points:
        raise ValueError(f"only {len(use)} visible samples; raise oversample")
    p = pts[use]
    ray = p - scene.viewpoints[seen_by[use]]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    p = p + ray * rng.normal(scale=noise, size=(len(p), 1))
    return Scan(
        points=p,
        normals=nrm[use],
        colors=scene.face_colors[face_of[use]],
        seen_by=seen_by[use],
        reference_points=pts[ref],
        reference_normals=nrm[ref],
    )


def _sample(vertices, faces, n, rng):
    """``n`` points uniform by area: positions (n, 3), unit normals (n, 3), face index (n,)
    (:func:`nkf_model.train.metrics.sample_surface`)."""
    return metrics.sample_surface(vertices, faces, n, rng, return_faces=True)


def main(argv=None) -> int:
    """``python -m benchmarks.scenes OUT.ply``: write a synthetic room scan (x y z red green blue,
    no normals, as a scanner gives it) and print the scanner positions as ``--viewpoint`` options."""
    import argparse

    from nkf_model.io.files import write_point_cloud

    ap = argparse.ArgumentParser(prog="python -m benchmarks.scenes", description=main.__doc__.split("\n")[0])
    ap.add_argument("output", help="PLY file to write")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--objects", type=int, default=4)
    ap.add_argument("--noise", type=float, default=0.003, help="range noise, metres (default 0.003)")
    ap.add_argument("--with-normals", action="store_true", help="also write the true normals")
    args = ap.parse_args(argv)
    scene = make_scene(seed=args.seed, n_objects=args.objects)
    s = scan(scene, args.points, noise=args.noise, seed=args.seed)
    write_point_cloud(args.output, s.points, s.normals if args.with_normals else None, s.colors)
    print(f"{args.output}: {len(s.points):,} points of a {ROOM[0]:g} x {ROOM[1]:g} m room with "
          f"{', '.join(scene.objects)}")
    print("scanner positions: " + " ".join(f"--viewpoint {x:.2f} {y:.2f} {z:.2f}" for x, y, z in scene.viewpoints))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
