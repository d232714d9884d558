"""Procedural training shapes: seeded, unlimited, watertight by construction, exact inside/outside.

Every shape is an implicit function ``f`` built from primitives (spheres, ellipsoids, bevelled
boxes, capped cylinders, tapered capsules, tori) with unions, smooth unions (fillets and blends),
subtractions (holes, slots) and shells. The inside is ``f < 0``, exactly: occupancy comes from the
sign of ``f`` at the query point, never from a mesh. The shape is finally intersected with the box
``[-1, 1]^3``, so it is bounded and its surface is closed.

Families (:data:`FAMILIES`):

* ``furniture``: tables, chairs, stools, shelves and cabinets, frames, lamps: thin bevelled plates,
  legs, rods and stretchers;
* ``mechanical``: plates and brackets with holes and slots, flanges and gears, trusses, pipe runs;
* ``organic``: bodies with legs, arms, necks, heads, ears, snouts and tails, joined by smooth
  unions; and blobs of smoothly merged ellipsoids;
* ``tube``: swept tubes along random smooth curves, open or closed, with varying radius;
* ``shell``: hollow spheres, boxes, cylinders and bowls, with holes through the wall.

:func:`shape_samples` returns the same arrays as a corpus mesh's training cache
(:func:`nkf_model.train.examples.samples_from_mesh`), in the corpus's unit box: surface points with
the normals of ``f`` (marching cubes on a grid finds the surface; each sample is then projected
onto ``f = 0`` by Newton steps, so it lies on the exact surface), uniform volume points and
near-surface points with their occupancy. :func:`nkf_model.train.examples.make_example` turns them
into training examples exactly as it does for corpus meshes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .examples import CACHE_VERSION, PAD

Field = Callable[[np.ndarray], np.ndarray]

FAMILIES = ("furniture", "mechanical", "organic", "tube", "shell")


@dataclass(frozen=True)
class ProceduralSpec:
    """Sample counts and the grid that finds the surface.

    ``grid``: marching-cubes cells per side of ``[-1, 1]^3``; parts thinner than about two cells
    are never made (every family keeps its thicknesses above :data:`MIN_THICKNESS`).
    ``weights``: relative frequency of each family in :data:`FAMILIES` order.
    """

    n_surface: int = 10000
    n_volume: int = 4096
    n_near: int = 4096
    grid: int = 72
    weights: tuple = (0.25, 0.2, 0.25, 0.12, 0.18)


MIN_THICKNESS = 0.07  # in the [-1, 1] construction frame: about 0.035 of the unit box


# --------------------------------------------------------------------------------------------
# Primitives: signed distances (exact or sign-exact bounds); p is (N, 3)


def _local(p, c, R):
    """Points in a primitive's frame: rotation R (3, 3, columns are the local axes) about centre c."""
    return (p - c) @ R if R is not None else p - c


def sphere(c, r) -> Field:
    c = np.asarray(c, float)
    return lambda p: np.linalg.norm(p - c, axis=1) - r


def ellipsoid(c, radii, R=None) -> Field:
    """Ellipsoid (sign exact; Inigo Quilez's bound for the distance)."""
    c = np.asarray(c, float)
    radii = np.asarray(radii, float)

    def f(p):
        q = _local(p, c, R)
        k0 = np.linalg.norm(q / radii, axis=1)
        k1 = np.maximum(np.linalg.norm(q / radii**2, axis=1), 1e-12)
        return k0 * (k0 - 1.0) / k1

    return f


def box(c, half, R=None, bevel=0.0) -> Field:
    """Box with half sides ``half``; ``bevel`` rounds its edges (the box's outer size stays ``half``)."""
    c = np.asarray(c, float)
    half = np.asarray(half, float)
    bevel = float(min(bevel, 0.9 * half.min()))

    def f(p):
        q = np.abs(_local(p, c, R)) - (half - bevel)
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0) - bevel

    return f


def cylinder(c, radius, half_height, R=None, bevel=0.0) -> Field:
    """Capped cylinder along the local z axis."""
    c = np.asarray(c, float)
    bevel = float(min(bevel, 0.9 * min(radius, half_height)))

    def f(p):
        q = _local(p, c, R)
        dx = np.linalg.norm(q[:, :2], axis=1) - (radius - bevel)
        dz = np.abs(q[:, 2]) - (half_height - bevel)
        out = np.sqrt(np.maximum(dx, 0.0) ** 2 + np.maximum(dz, 0.0) ** 2)
        return out + np.minimum(np.maximum(dx, dz), 0.0) - bevel

    return f


def capsule(a, b, ra, rb=None) -> Field:
    """Segment a-b swept by a ball whose radius goes linearly from ``ra`` to ``rb`` (a tapered rod)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    rb = ra if rb is None else rb
    ba = b - a
    bb = max(float(ba @ ba), 1e-12)

    def f(p):
        pa = p - a
        h = np.clip(pa @ ba / bb, 0.0, 1.0)
        return np.linalg.norm(pa - h[:, None] * ba, axis=1) - (ra + (rb - ra) * h)

    return f


def torus(c, major, minor, R=None) -> Field:
    c = np.asarray(c, float)

    def f(p):
        q = _local(p, c, R)
        return np.hypot(np.linalg.norm(q[:, :2], axis=1) - major, q[:, 2]) - minor

    return f


def _capsule_chain_py(p, curve, radii):
    out = np.full(len(p), np.inf)
    for i in range(len(curve) - 1):
        out = np.minimum(out, capsule(curve[i], curve[i + 1], radii[i], radii[i + 1])(p))
    return out


try:
    from numba import njit

    @njit(cache=True, nogil=True)
    def _capsule_chain(p, curve, radii):  # pragma: no cover - compiled twin of _capsule_chain_py
        out = np.empty(p.shape[0])
        k = curve.shape[0] - 1
        for n in range(p.shape[0]):
            best = np.inf
            for i in range(k):
                bx = curve[i + 1, 0] - curve[i, 0]
                by = curve[i + 1, 1] - curve[i, 1]
                bz = curve[i + 1, 2] - curve[i, 2]
                px = p[n, 0] - curve[i, 0]
                py = p[n, 1] - curve[i, 1]
                pz = p[n, 2] - curve[i, 2]
                bb = max(bx * bx + by * by + bz * bz, 1e-12)
                h = min(max((px * bx + py * by + pz * bz) / bb, 0.0), 1.0)
                dx = px - h * bx
                dy = py - h * by
                dz = pz - h * bz
                d = np.sqrt(dx * dx + dy * dy + dz * dz) - (radii[i] + (radii[i + 1] - radii[i]) * h)
                if d < best:
                    best = d
            out[n] = best
        return out
except ImportError:  # pragma: no cover - numba is a dependency
    _capsule_chain = _capsule_chain_py


def tube(curve, radii) -> Field:
    """A swept tube: the union of tapered capsules along the polyline ``curve`` (K, 3)."""
    curve = np.ascontiguousarray(curve, dtype=np.float64)
    radii = np.ascontiguousarray(radii, dtype=np.float64)
    return lambda p: _capsule_chain(np.ascontiguousarray(p, dtype=np.float64), curve, radii)


# --------------------------------------------------------------------------------------------
# Operations


def union(*fs) -> Field:
    def f(p):
        out = fs[0](p)
        for g in fs[1:]:
            out = np.minimum(out, g(p))
        return out

    return f


def smooth_union(k: float, *fs) -> Field:
    """Union with a fillet of size about ``k`` where parts meet (polynomial smooth minimum)."""
    def f(p):
        out = fs[0](p)
        for g in fs[1:]:
            b = g(p)
            h = np.clip(0.5 + 0.5 * (b - out) / k, 0.0, 1.0)
            out = b + (out - b) * h - k * h * (1.0 - h)
        return out

    return f


def subtract(a: Field, *holes: Field) -> Field:
    """``a`` minus every hole."""
    def f(p):
        out = a(p)
        for g in holes:
            out = np.maximum(out, -g(p))
        return out

    return f


def intersect(*fs) -> Field:
    def f(p):
        out = fs[0](p)
        for g in fs[1:]:
            out = np.maximum(out, g(p))
        return out

    return f


def shell(a: Field, thickness: float) -> Field:
    """A wall of ``thickness`` centred on the surface of ``a``."""
    return lambda p: np.abs(a(p)) - 0.5 * thickness


def half_space(normal, offset) -> Field:
    """``n . p - offset`` (inside where negative)."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    return lambda p: p @ n - offset


# --------------------------------------------------------------------------------------------
# Random helpers


def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def axis_rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


def frame_along(d) -> np.ndarray:
    """A rotation whose local z axis is the direction ``d``."""
    z = np.asarray(d, float)
    z = z / np.linalg.norm(z)
    t = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(t, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _thick(rng, lo=MIN_THICKNESS, hi=0.16):
    return float(rng.uniform(lo, hi))


def smooth_curve(rng, n: int = 24, closed: bool = False, extent: float = 0.8) -> np.ndarray:
    """A random smooth space curve (n, 3) inside ``[-extent, extent]^3`` (a few Fourier terms)."""
    t = np.linspace(0.0, 2 * np.pi if closed else np.pi, n, endpoint=not closed)
    if closed:
        t = np.append(t, t[0] + 2 * np.pi)
    k = np.arange(1, 4)
    amp = rng.normal(size=(3, 3, 2)) / k[None, :, None] ** 1.5
    phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
    c = np.zeros((len(t), 3))
    for d in range(3):
        for j, kk in enumerate(k):
            c[:, d] += amp[d, j, 0] * np.cos(kk * t + phase[d, j]) + amp[d, j, 1] * np.sin(kk * t)
    c -= 0.5 * (c.max(axis=0) + c.min(axis=0))
    c *= extent / max(np.abs(c).max(), 1e-9)
    return c


# --------------------------------------------------------------------------------------------
# Families


def _legs(rng, corners_xy, top_z, bottom_z, kind, size):
    parts = []
    for x, y in corners_xy:
        if kind == "round":
            parts.append(cylinder([x, y, 0.5 * (top_z + bottom_z)], size, 0.5 * (top_z - bottom_z)))
        elif kind == "splay":
            dx, dy = np.sign(x) * rng.uniform(0.0, 0.12), np.sign(y) * rng.uniform(0.0, 0.12)
            parts.append(capsule([x, y, top_z], [x + dx, y + dy, bottom_z + size], size, 0.8 * size))
        else:
            parts.append(box([x, y, 0.5 * (top_z + bottom_z)], [size, size, 0.5 * (top_z - bottom_z)],
                             bevel=0.3 * size))
    return parts


def furniture(rng) -> Field:
    kind = rng.choice(["table", "chair", "stool", "shelf", "cabinet", "frame", "lamp"])
    t = _thick(rng, MIN_THICKNESS, 0.12)
    bev = rng.uniform(0.0, 0.45) * t
    leg_kind = rng.choice(["square", "round", "splay"])
    leg = 0.5 * _thick(rng, MIN_THICKNESS, 0.14)
    if kind in ("table", "stool", "chair"):
        w = rng.uniform(0.35, 0.9) if kind != "stool" else rng.uniform(0.25, 0.5)
        d = rng.uniform(0.35, 0.9) if kind != "stool" else w * rng.uniform(0.8, 1.0)
        h = rng.uniform(0.3, 0.9) if kind != "chair" else rng.uniform(0.3, 0.5)
        top = h - 0.5 * t
        inset = rng.uniform(0.0, 0.15)
        xs, ys = w - leg - inset * w, d - leg - inset * d
        parts = [box([0, 0, h], [w, d, 0.5 * t], bevel=bev)]
        if kind == "stool" and rng.random() < 0.5:
            parts[0] = cylinder([0, 0, h], w, 0.5 * t, bevel=bev)
            xs = ys = w / np.sqrt(2) - leg
        corners = [(sx * xs, sy * ys) for sx in (-1, 1) for sy in (-1, 1)]
        if kind == "table" and rng.random() < 0.2:  # pedestal table
            parts += [cylinder([0, 0, 0.5 * (top - 0.9)], leg * 2, 0.5 * (top + 0.9)),
                      cylinder([0, 0, -0.9 + 0.5 * t], 0.5 * w, 0.5 * t, bevel=bev)]
        else:
            parts += _legs(rng, corners, top, -0.9, leg_kind, leg)
            if rng.random() < 0.5:  # stretchers between the legs
                z = rng.uniform(-0.7, 0.2 * top)
                r = max(0.5 * MIN_THICKNESS, 0.6 * leg)
                for (x0, y0), (x1, y1) in zip(corners, [corners[1], corners[3], corners[0], corners[2]]):
                    parts.append(capsule([x0, y0, z], [x1, y1, z], r))
            if kind == "table" and rng.random() < 0.3:  # lower shelf
                parts.append(box([0, 0, rng.uniform(-0.7, -0.3)], [xs, ys, 0.5 * t], bevel=bev))
        if kind == "chair":
            back_h = rng.uniform(0.4, 0.9)
            y0 = -d + 0.5 * t
            if rng.random() < 0.5:
                parts.append(box([0, y0, h + 0.5 * back_h], [w, 0.5 * t, 0.5 * back_h], bevel=bev))
            else:
                for sx in (-1, 1):
                    parts.append(box([sx * xs, y0, h + 0.5 * back_h], [leg, 0.5 * t, 0.5 * back_h], bevel=0.3 * leg))
                for z in np.linspace(h + 0.3 * back_h, h + back_h - leg, int(rng.integers(1, 4))):
                    parts.append(box([0, y0, z], [xs, 0.5 * t, max(leg, 0.5 * MIN_THICKNESS)], bevel=0.3 * leg))
            if rng.random() < 0.3:  # arm rests
                for sx in (-1, 1):
                    parts.append(box([sx * w, 0, h + 0.3], [0.5 * t, d, 0.5 * t], bevel=bev))
                    parts.append(capsule([sx * w, d - leg, h], [sx * w, d - leg, h + 0.3], leg))
        f = union(*parts)
    elif kind in ("shelf", "cabinet"):
        w, d, h = rng.uniform(0.4, 0.9), rng.uniform(0.2, 0.6), rng.uniform(0.5, 0.95)
        parts = [box([sx * (w - 0.5 * t), 0, 0], [0.5 * t, d, h], bevel=bev) for sx in (-1, 1)]
        n = int(rng.integers(2, 6))
        for z in np.linspace(-h + 0.5 * t, h - 0.5 * t, n):
            parts.append(box([0, 0, z], [w, d, 0.5 * t], bevel=bev))
        if kind == "cabinet" or rng.random() < 0.5:
            parts.append(box([0, -d + 0.5 * t, 0], [w, 0.5 * t, h], bevel=bev))
        if kind == "cabinet" and rng.random() < 0.6:  # doors, with handles
            parts.append(box([0, d - 0.5 * t, 0], [w, 0.5 * t, h], bevel=bev))
            for sx in (-1, 1):
                parts.append(capsule([sx * 0.15 * w, d + 0.04, -0.2 * h], [sx * 0.15 * w, d + 0.04, 0.2 * h],
                                     0.5 * MIN_THICKNESS))
        f = union(*parts)
    elif kind == "frame":
        w, d = rng.uniform(0.5, 0.95), rng.uniform(0.3, 0.95)
        bar = 0.5 * _thick(rng, MIN_THICKNESS, 0.16)
        parts = [box([0, sy * (d - bar), 0], [w, bar, bar], bevel=0.3 * bar) for sy in (-1, 1)]
        parts += [box([sx * (w - bar), 0, 0], [bar, d, bar], bevel=0.3 * bar) for sx in (-1, 1)]
        for _ in range(int(rng.integers(0, 3))):
            x0, x1 = rng.uniform(-w, w, size=2)
            parts.append(capsule([x0, -d + bar, 0], [x1, d - bar, 0], max(0.5 * MIN_THICKNESS, 0.6 * bar)))
        if rng.random() < 0.5:  # legs: a bed or a bench frame
            parts += _legs(rng, [(sx * (w - bar), sy * (d - bar)) for sx in (-1, 1) for sy in (-1, 1)],
                           0.0, -rng.uniform(0.3, 0.8), leg_kind, bar)
        f = union(*parts)
    else:  # lamp
        r = rng.uniform(0.2, 0.45)
        stem = 0.5 * _thick(rng, MIN_THICKNESS, 0.1)
        h = rng.uniform(0.4, 0.8)
        shade_r = rng.uniform(0.25, 0.5)
        shade_h = rng.uniform(0.15, 0.35)
        open_shade = intersect(shell(cylinder([0, 0, h], shade_r, shade_h), t),
                               box([0, 0, h], [1.0, 1.0, shade_h]))
        spokes = [capsule([0, 0, h], [shade_r * np.cos(a), shade_r * np.sin(a), h], 0.5 * MIN_THICKNESS)
                  for a in np.linspace(0, 2 * np.pi, int(rng.integers(2, 5)), endpoint=False)]
        f = union(cylinder([0, 0, -0.9 + 0.5 * t], r, 0.5 * t, bevel=bev), capsule([0, 0, -0.9], [0, 0, h], stem),
                  open_shade, *spokes)
    return f


def _holes(rng, n, plane_half, R, c, thick):
    """Cylindrical through-holes (and slots) across a plate of half sides ``plane_half`` (x, y)."""
    holes = []
    for _ in range(n):
        r = rng.uniform(MIN_THICKNESS, 0.35 * min(plane_half))
        x = rng.uniform(-plane_half[0] + r + MIN_THICKNESS, plane_half[0] - r - MIN_THICKNESS)
        y = rng.uniform(-plane_half[1] + r + MIN_THICKNESS, plane_half[1] - r - MIN_THICKNESS)
        ctr = c + R @ np.array([x, y, 0.0])
        if rng.random() < 0.25:  # a slot
            e = R @ np.array([rng.uniform(0.05, 0.25), 0, 0])
            holes.append(capsule(ctr - e - R[:, 2] * thick, ctr - e + R[:, 2] * thick, r))
            holes[-1] = union(holes[-1], capsule(ctr + e - R[:, 2] * thick, ctr + e + R[:, 2] * thick, r),
                              box(ctr, [np.linalg.norm(e), r, thick], R=R))
        else:
            holes.append(cylinder(ctr, r, thick, R=R))
    return holes


def mechanical(rng) -> Field:
    kind = rng.choice(["plate", "bracket", "flange", "gear", "truss", "pipes", "axle"])
    t = _thick(rng, MIN_THICKNESS, 0.2)
    bev = rng.uniform(0.0, 0.4) * t
    if kind == "plate":
        half = np.array([rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.9)])
        R = np.eye(3)
        f = box([0, 0, 0], [half[0], half[1], 0.5 * t], bevel=bev)
        if rng.random() < 0.4:  # a boss on top
            f = smooth_union(0.05, f, cylinder([0, 0, 0.5 * t + 0.1], rng.uniform(0.1, 0.3), 0.1 + 0.5 * t))
        f = subtract(f, *_holes(rng, int(rng.integers(1, 6)), half, R, np.zeros(3), 1.0))
    elif kind == "bracket":
        a, b = rng.uniform(0.4, 0.9, size=2)
        w = rng.uniform(0.2, 0.8)
        p1 = box([0, 0, -a + 0.5 * t], [b, w, 0.5 * t], bevel=bev)  # base
        p2 = box([-b + 0.5 * t, 0, 0], [0.5 * t, w, a], bevel=bev)  # wall
        parts = [p1, p2]
        if rng.random() < 0.5:  # gusset
            parts.append(intersect(box([0, 0, 0], [b, 0.5 * t, a]), half_space([1, 0, 1], -b * 0.3 - a * 0.3)))
        f = smooth_union(rng.uniform(0.02, 0.1), *parts)
        holes = _holes(rng, int(rng.integers(0, 3)), np.array([b, w]), np.eye(3), np.array([0, 0, -a]), 1.0)
        holes += _holes(rng, int(rng.integers(0, 3)), np.array([a, w]), axis_rotation(1, np.pi / 2),
                        np.array([-b, 0, 0]), 1.0)
        f = subtract(f, *holes)
    elif kind in ("flange", "gear"):
        r = rng.uniform(0.5, 0.9)
        h = 0.5 * t if kind == "flange" else rng.uniform(0.5 * MIN_THICKNESS, 0.25)
        parts = [cylinder([0, 0, 0], r, h, bevel=bev)]
        hub_r = rng.uniform(0.15, 0.35) * r
        parts.append(cylinder([0, 0, 0], hub_r + 0.08, h + rng.uniform(0.0, 0.4), bevel=0.3 * bev))
        if kind == "gear":
            n = int(rng.integers(8, 24))
            tooth = rng.uniform(0.06, 0.15)
            width = max(MIN_THICKNESS * 0.6, np.pi * r / n * rng.uniform(0.4, 0.8))
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
                parts.append(box([(r + 0.5 * tooth) * np.cos(a), (r + 0.5 * tooth) * np.sin(a), 0],
                                 [0.5 * tooth + 0.02, 0.5 * width, h], R=axis_rotation(2, a), bevel=0.2 * width))
        f = union(*parts)
        holes = [cylinder([0, 0, 0], hub_r, 2.0)]
        n = int(rng.integers(0, 8))
        rr = 0.5 * (hub_r + 0.08 + r)
        hr = min(0.4 * (r - hub_r - 0.08), 0.8 * np.pi * rr / max(n, 1) * 0.5)
        if hr > MIN_THICKNESS * 0.6:
            holes += [cylinder([rr * np.cos(a), rr * np.sin(a), 0], hr, 2.0)
                      for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
        f = subtract(f, *holes)
    elif kind == "truss":
        nx, ny, nz = rng.integers(2, 4, size=3)
        ext = rng.uniform(0.4, 0.85, size=3)
        grid = np.stack(np.meshgrid(*[np.linspace(-e, e, n) for e, n in zip(ext, (nx, ny, nz))], indexing="ij"),
                        axis=-1).reshape(-1, 3)
        r = 0.5 * _thick(rng, MIN_THICKNESS, 0.1)
        parts = []
        for i in range(len(grid)):
            for j in range(i + 1, len(grid)):
                d = np.abs(grid[i] - grid[j])
                steps = d / (2 * ext / (np.array([nx, ny, nz]) - 1))
                axis_edge = np.isclose(np.sort(steps), [0, 0, 1]).all()
                diag = np.isclose(np.sort(steps), [0, 1, 1]).all() and rng.random() < 0.3
                if axis_edge or diag:
                    parts.append(capsule(grid[i], grid[j], r))
        if rng.random() < 0.5:
            parts += [sphere(g, r * rng.uniform(1.3, 2.0)) for g in grid]
        f = union(*parts)
    elif kind == "pipes":
        parts = []
        r = rng.uniform(0.5 * MIN_THICKNESS + 0.02, 0.15)
        for _ in range(int(rng.integers(1, 4))):
            pts = [rng.uniform(-0.7, 0.7, size=3)]
            for _ in range(int(rng.integers(2, 5))):  # axis-aligned runs, like plumbing
                q = pts[-1].copy()
                ax = int(rng.integers(3))
                q[ax] = rng.uniform(-0.75, 0.75)
                pts.append(q)
            pts = np.array(pts)
            parts.append(smooth_union(r * 0.8, *[capsule(pts[i], pts[i + 1], r) for i in range(len(pts) - 1)]))
            for end in (pts[0], pts[-1]):  # flanges at the ends
                d = pts[1] - pts[0] if end is pts[0] else pts[-1] - pts[-2]
                parts.append(cylinder(end, r * rng.uniform(1.4, 2.0), 0.5 * MIN_THICKNESS + 0.01, R=frame_along(d)))
        f = union(*parts)
    else:  # axle with wheels or discs
        L = rng.uniform(0.5, 0.9)
        r = 0.5 * _thick(rng, MIN_THICKNESS, 0.15)
        R = frame_along([1, 0, 0])
        parts = [cylinder([0, 0, 0], r, L, R=R, bevel=0.3 * r)]
        for x in rng.uniform(-L, L, size=int(rng.integers(1, 5))):
            parts.append(cylinder([x, 0, 0], rng.uniform(2 * r, 0.7), 0.5 * _thick(rng, MIN_THICKNESS, 0.2),
                                  R=R, bevel=rng.uniform(0, 0.02)))
        f = union(*parts)
    return f


def organic(rng) -> Field:
    if rng.random() < 0.2:  # a blob of smoothly merged ellipsoids
        n = int(rng.integers(3, 9))
        parts = [ellipsoid(rng.uniform(-0.4, 0.4, size=3), rng.uniform(0.12, 0.45, size=3), random_rotation(rng))
                 for _ in range(n)]
        return smooth_union(rng.uniform(0.05, 0.25), *parts)
    biped = rng.random() < 0.35
    k = rng.uniform(0.03, 0.12)
    if biped:  # upright body, two legs, two arms, head on a short neck
        body_r = np.array([rng.uniform(0.18, 0.35), rng.uniform(0.12, 0.25), rng.uniform(0.25, 0.4)])
        body_c = np.array([0, 0, rng.uniform(-0.1, 0.15)])
        parts = [ellipsoid(body_c, body_r)]
        hip_z = body_c[2] - 0.7 * body_r[2]
        limb_r = rng.uniform(MIN_THICKNESS * 0.6, 0.1)
        for sx in (-1, 1):
            hip = np.array([sx * 0.5 * body_r[0], 0, hip_z])
            knee = hip + np.array([sx * rng.uniform(0, 0.1), rng.uniform(-0.1, 0.1), -rng.uniform(0.3, 0.45)])
            foot = np.array([knee[0], knee[1] + rng.uniform(-0.05, 0.1), -0.88])
            parts += [capsule(hip, knee, limb_r * 1.2, limb_r), capsule(knee, foot, limb_r, limb_r * 0.8),
                      ellipsoid(foot + [0, 0.05, 0], [limb_r * 1.2, limb_r * 2.2, limb_r])]
            sh = np.array([sx * 0.9 * body_r[0], 0, body_c[2] + 0.6 * body_r[2]])
            elbow = sh + np.array([sx * rng.uniform(0.1, 0.3), rng.uniform(-0.15, 0.15), -rng.uniform(0.0, 0.3)])
            hand = elbow + np.array([sx * rng.uniform(0.0, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.2)])
            parts += [capsule(sh, elbow, limb_r, 0.85 * limb_r), capsule(elbow, hand, 0.85 * limb_r, 0.7 * limb_r),
                      sphere(hand, limb_r * 1.1)]
        head_c = body_c + np.array([0, 0, body_r[2] + rng.uniform(0.12, 0.25)])
        head_r = rng.uniform(0.12, 0.22)
        parts += [capsule(body_c + [0, 0, 0.8 * body_r[2]], head_c, 0.6 * head_r), sphere(head_c, head_r)]
    else:  # quadruped (or more legs): horizontal body, neck, head, tail
        L = rng.uniform(0.35, 0.6)
        body_r = np.array([L, rng.uniform(0.12, 0.3), rng.uniform(0.12, 0.28)])
        body_c = np.array([0, 0, rng.uniform(-0.1, 0.3)])
        parts = [ellipsoid(body_c, body_r)]
        n_pairs = int(rng.choice([2, 2, 2, 3]))
        limb_r = rng.uniform(MIN_THICKNESS * 0.6, 0.09)
        for x in np.linspace(-0.7 * L, 0.7 * L, n_pairs):
            for sy in (-1, 1):
                hip = body_c + np.array([x, sy * 0.6 * body_r[1], -0.5 * body_r[2]])
                knee = np.array([x + rng.uniform(-0.1, 0.1), sy * rng.uniform(0.6, 1.2) * body_r[1],
                                 0.5 * (hip[2] - 0.9)])
                foot = np.array([knee[0] + rng.uniform(-0.05, 0.1), knee[1], -0.88])
                parts += [capsule(hip, knee, 1.3 * limb_r, limb_r), capsule(knee, foot, limb_r, 0.8 * limb_r)]
        neck_base = body_c + np.array([0.8 * L, 0, 0.3 * body_r[2]])
        head_c = neck_base + np.array([rng.uniform(0.05, 0.3), 0, rng.uniform(0.1, 0.5)])
        head_c = np.clip(head_c, -0.8, 0.8)
        head_r = rng.uniform(0.1, 0.2)
        parts += [capsule(neck_base, head_c, rng.uniform(0.5, 0.9) * body_r[2], 0.6 * head_r),
                  ellipsoid(head_c, head_r * np.array([1.2, 0.9, 0.9]))]
        if rng.random() < 0.7:  # snout
            parts.append(ellipsoid(head_c + [head_r, 0, -0.3 * head_r], head_r * np.array([0.8, 0.5, 0.45])))
        tail_root = body_c - np.array([0.9 * L, 0, -0.2 * body_r[2]])
        tail = tail_root + np.cumsum(rng.normal(scale=0.08, size=(6, 3)) + [-0.08, 0, 0.02], axis=0)
        tail = np.clip(np.vstack([tail_root, tail]), -0.9, 0.9)
        r0 = rng.uniform(0.05, 0.1)
        parts.append(tube(tail, np.linspace(r0, 0.5 * MIN_THICKNESS, len(tail))))
    if rng.random() < 0.7:  # ears or horns
        er = rng.uniform(0.04, 0.08)
        for sy in (-1, 1):
            base = head_c + np.array([0, sy * 0.6 * head_r, 0.6 * head_r])
            tip = base + np.array([rng.uniform(-0.1, 0.05), sy * rng.uniform(0.0, 0.12), rng.uniform(0.08, 0.2)])
            parts.append(capsule(base, tip, er, max(0.5 * MIN_THICKNESS, 0.4 * er)))
    return smooth_union(k, *parts)


def tubes(rng) -> Field:
    parts = []
    for _ in range(int(rng.integers(1, 4))):
        closed = rng.random() < 0.4
        n = int(rng.integers(16, 30))
        curve = smooth_curve(rng, n, closed, extent=rng.uniform(0.5, 0.85)) + rng.uniform(-0.1, 0.1, size=3)
        r0 = rng.uniform(0.5 * MIN_THICKNESS + 0.005, 0.18)
        radii = r0 * (1.0 + rng.uniform(-0.5, 0.5) * np.sin(np.linspace(0, rng.uniform(1, 4) * np.pi, len(curve))))
        parts.append(tube(curve, np.maximum(radii, 0.5 * MIN_THICKNESS)))
    return smooth_union(rng.uniform(0.01, 0.08), *parts)


def shells(rng) -> Field:
    kind = rng.choice(["sphere", "box", "cylinder", "bowl", "vase"])
    t = _thick(rng, MIN_THICKNESS, 0.14)
    R = random_rotation(rng) if rng.random() < 0.3 else None
    if kind == "sphere":
        base = ellipsoid([0, 0, 0], rng.uniform(0.5, 0.85, size=3), R)
    elif kind == "box":
        base = box([0, 0, 0], rng.uniform(0.4, 0.85, size=3), R, bevel=rng.uniform(0.0, 0.3))
    elif kind == "cylinder":
        base = cylinder([0, 0, 0], rng.uniform(0.4, 0.85), rng.uniform(0.3, 0.85), R, bevel=rng.uniform(0.0, 0.2))
    elif kind == "bowl":
        base = ellipsoid([0, 0, 0], [rng.uniform(0.5, 0.85)] * 2 + [rng.uniform(0.3, 0.85)])
    else:  # vase: a solid of revolution through random radii
        zs = np.linspace(-0.85, 0.85, 8)
        rs = np.clip(0.45 + np.cumsum(rng.normal(scale=0.12, size=8)), 0.15, 0.85)
        base = smooth_union(0.15, *[cylinder([0, 0, z], r, 0.12) for z, r in zip(zs, rs)])
    f = shell(base, t)
    cuts = []
    if kind in ("bowl", "vase", "cylinder") and rng.random() < 0.8:  # open at the top
        top = {"bowl": 0.3, "vase": 0.85, "cylinder": 0.3}[kind]  # the lowest top of the base
        cuts.append(half_space([0, 0, -1], -rng.uniform(0.0, top - 0.05)))
    for _ in range(int(rng.integers(1 if not cuts else 0, 6))):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        cuts.append(cylinder(d * 0.6, rng.uniform(0.08, 0.35), 0.6, R=frame_along(d)))
    return subtract(f, *cuts) if cuts else f


_MAKERS = {"furniture": furniture, "mechanical": mechanical, "organic": organic, "tube": tubes, "shell": shells}


def make_shape(seed: int, spec: ProceduralSpec = ProceduralSpec(), family: str | None = None) -> tuple[str, Field]:
    """The implicit function of shape number ``seed`` (and its family), bounded by ``[-1, 1]^3``."""
    rng = np.random.default_rng([0x5AFE, seed])
    if family is None:
        w = np.asarray(spec.weights, float)
        family = FAMILIES[int(rng.choice(len(FAMILIES), p=w / w.sum()))]
    f = _MAKERS[family](rng)
    bound = box([0, 0, 0], [0.98, 0.98, 0.98])
    return family, intersect(f, bound)


# --------------------------------------------------------------------------------------------
# Samples


def _gradient(f: Field, p: np.ndarray, h: float = 1e-4) -> np.ndarray:
    g = np.empty_like(p)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        g[:, i] = (f(p + e) - f(p - e)) / (2 * h)
    return g


def project_to_surface(f: Field, p: np.ndarray, iterations: int = 4):
    """Newton steps onto ``f = 0``; returns the points, unit normals (outward) and ``|f|`` there."""
    for _ in range(iterations):
        g = _gradient(f, p)
        p = p - (f(p) / np.maximum((g * g).sum(axis=1), 1e-12))[:, None] * g
    g = _gradient(f, p)
    n = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
    return p, n, np.abs(f(p))


def surface_mesh(f: Field, grid: int):
    """Marching-cubes mesh of ``f = 0`` on a ``grid``-cell lattice of ``[-1, 1]^3`` (construction frame)."""
    from skimage.measure import marching_cubes

    x = np.linspace(-1.0, 1.0, grid + 1)
    pts = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    vals = f(pts).reshape(grid + 1, grid + 1, grid + 1)
    if not (vals.min() < 0 < vals.max()):
        raise ValueError("the shape has no surface on the grid")
    h = 2.0 / grid
    v, faces, _, _ = marching_cubes(vals, 0.0, spacing=(h, h, h))
    return v - 1.0, faces[:, ::-1].astype(np.int64)


def shape_samples(seed: int, spec: ProceduralSpec = ProceduralSpec(), family: str | None = None) -> dict:
    """Training samples of procedural shape ``seed`` in the corpus's unit box (the keys of the
    corpus cache, plus ``family``); see the module docstring."""
    from .metrics import sample_surface

    fam, f = make_shape(seed, spec, family)
    v, faces = surface_mesh(f, spec.grid)
    lo, hi = v.min(axis=0), v.max(axis=0)
    center = 0.5 * (lo + hi)
    scale = float((hi - lo).max())
    rng = np.random.default_rng([0x5A3B, seed])
    cell = 2.0 / spec.grid
    # Surface: area-uniform samples of the mesh, projected onto the exact surface; the few that move
    # further than a cell or do not converge are drawn again.
    pts = np.empty((0, 3))
    nrm = np.empty((0, 3))
    for _ in range(4):
        need = spec.n_surface - len(pts)
        if need <= 0:
            break
        p0, _ = sample_surface(v, faces, int(need * 1.1) + 16, rng)
        p, n, r = project_to_surface(f, p0)
        # A zero gradient (a crease or a saddle of the field) gives no normal: such points are dropped.
        ok = ((r < 1e-6) & (np.linalg.norm(p - p0, axis=1) < cell) & np.isfinite(n).all(axis=1)
              & (np.linalg.norm(n, axis=1) > 0.5))
        pts, nrm = np.concatenate([pts, p[ok]]), np.concatenate([nrm, n[ok]])
    if len(pts) < spec.n_surface:
        raise ValueError(f"shape {seed}: only {len(pts)} surface points converged")
    pts, nrm = pts[: spec.n_surface], nrm[: spec.n_surface]

    def world(u):
        return u * scale + center

    vol = rng.uniform(-PAD, PAD, size=(spec.n_volume, 3))
    src = (pts[rng.integers(len(pts), size=spec.n_near)] - center) / scale
    sigma = np.where(np.arange(spec.n_near) % 2 == 0, 0.005, 0.02)[:, None]
    near = src + rng.normal(size=src.shape) * sigma
    return {
        "version": np.int64(CACHE_VERSION),
        "surf_pts": ((pts - center) / scale).astype(np.float32),
        "surf_nrm": nrm.astype(np.float32),
        "vol_pts": vol.astype(np.float32),
        "vol_occ": f(world(vol)) < 0,
        "near_pts": near.astype(np.float32),
        "near_occ": f(world(near)) < 0,
        "family": fam,
    }
