"""Simulated multi-view range scans of a mesh: test data that looks like a real scanner's.

:func:`range_scan` places ``views`` virtual scanners around an object as a turntable would (a ring
at one or two elevations above the object, none below it), renders a range image from each
(:func:`benchmarks._raster_kernels.rasterise_faces`: one point per pixel, where the pixel's ray first
meets the surface, so occlusion and the point density of a real range image follow), and then
adds what real scans carry:

- **range noise along the line of sight** that grows at grazing angles (standard deviation
  ``noise / max(cos t, 0.2)`` for the angle ``t`` between the ray and the surface normal); surface
  seen more obliquely than ``GRAZING_LIMIT`` gives no points (a hole, as in a real scanner);
- **silhouette outliers**: pixels at a depth edge are "mixed pixels" with probability
  ``edge_outliers``, pushed back along the ray by 0.5 % to 5 % of the object's size, plus a
  fraction ``spray`` of points scattered in the scanner's field near the object;
- **holes** where no scanner looked (the underside, deep folds);
- **misregistration**: each scan but the first is moved by a small random rigid motion (a
  rotation about the object's centre and a translation, each moving points by up to
  ``misregistration`` times the bounding-box diagonal), so the overlapping scans form thin layers a
  little off each other.

No normals are returned with the points (a scanner gives none); ``true_normals`` are the normals of
the surface hit, for oracle comparisons only. Units are those of the mesh (the corpus's unit box).
Everything is NumPy and numba, seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _raster_kernels as rk

GRAZING_LIMIT = 80.0  # degrees between the ray and the surface normal beyond which nothing is returned
EDGE_JUMP = 0.02  # a neighbouring pixel this much deeper (of the diagonal), or empty, marks a depth edge


@dataclass
class RangeScan:
    """Points of a simulated multi-view range scan.

    Attributes
    ----------
    points : (N, 3) float64
        Registered (imperfectly) points, in the mesh's frame.
    scan : (N,) int64
        Which range image each point came from.
    viewpoints : (K, 3) float64
        Scanner positions (in the frame of scan 0; the others are off by their misregistration).
    true_normals : (N, 3) float64
        Outward normal of the triangle each point's ray hit (before noise); oracle only.
    outlier : (N,) bool
        Mixed pixels and spray (not on the surface).
    diagonal : float
        Bounding-box diagonal of the mesh (the unit of the noise and misregistration settings).
    """

    points: np.ndarray
    scan: np.ndarray
    viewpoints: np.ndarray
    true_normals: np.ndarray
    outlier: np.ndarray
    diagonal: float


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rows: the camera's a, b and viewing (w) axes in world coordinates."""
    w = target - eye
    w = w / np.linalg.norm(w)
    up = np.array([0.0, 0.0, 1.0]) if abs(w[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    a = np.cross(up, w)
    a /= np.linalg.norm(a)
    b = np.cross(w, a)
    return np.stack([a, b, w])


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def turntable_views(views: int, center: np.ndarray, radius: float, distance: float = 2.5,
                    elevations=(15.0, 40.0), rng: np.random.Generator | None = None) -> np.ndarray:
    """Scanner positions on a ring around ``center``: ``views`` azimuths (evenly spaced, jittered),
    alternating between the ``elevations`` (degrees above the horizon), ``distance`` radii away."""
    rng = rng or np.random.default_rng(0)
    az = 2 * np.pi * (np.arange(views) + 0.3 * rng.uniform(-1, 1, views)) / views
    el = np.radians(np.asarray(elevations, float)[np.arange(views) % len(elevations)])
    d = np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)], axis=1)
    return center + distance * radius * d


def range_image(vertices, faces, face_normals, eye, center, radius, pixels, rng, *, noise, edge_outliers,
                diagonal):
    """One range image from ``eye``: points, their true normals, and which are mixed-pixel outliers."""
    rot = _look_at(eye, center)
    dist = float(np.linalg.norm(center - eye))
    tan_half = 1.05 * radius / np.sqrt(max(dist**2 - radius**2, 1e-12))
    cam = (vertices - eye) @ rot.T
    cam[:, :2] /= tan_half
    depth, face = rk.rasterise_faces(np.ascontiguousarray(cam[faces]), pixels, 1e-6)
    hit = face >= 0
    i, j = np.nonzero(hit)
    f = face[i, j]
    # The pixel's ray in world coordinates, then its exact intersection with the triangle's plane.
    u = ((i + 0.5) / (0.5 * pixels) - 1.0) * tan_half
    v = ((j + 0.5) / (0.5 * pixels) - 1.0) * tan_half
    d = np.stack([u, v, np.ones_like(u)], axis=1) @ rot
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = face_normals[f]
    denom = np.einsum("ij,ij->i", n, d)
    t = np.einsum("ij,ij->i", n, vertices[faces[f, 0]] - eye) / np.where(np.abs(denom) < 1e-12, 1e-12, denom)
    cos_t = np.abs(denom)
    keep = cos_t > np.cos(np.radians(GRAZING_LIMIT))
    # Depth edges: a 4-neighbour that is empty or much deeper.
    pad = np.pad(depth, 1, constant_values=np.inf)
    jump = EDGE_JUMP * diagonal
    edge_img = np.zeros_like(hit)
    for di, dj in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[di:di + pixels, dj:dj + pixels]
        edge_img |= nb > depth + jump
    edge = edge_img[i, j]
    sigma = noise * diagonal / np.maximum(cos_t, 0.2)
    t = t + rng.normal(size=len(t)) * sigma
    mixed = edge & (rng.random(len(t)) < edge_outliers)
    t = t + np.where(mixed, rng.uniform(0.005, 0.05, len(t)) * diagonal, 0.0)
    pts = eye + t[:, None] * d
    keep &= np.isfinite(pts).all(axis=1)
    return pts[keep], n[keep], mixed[keep]


def range_scan(vertices, faces, *, views: int = 10, pixels: int = 200, noise: float = 0.0003,
               edge_outliers: float = 0.3, spray: float = 0.001, misregistration: float = 0.001,
               elevations=(15.0, 40.0), seed: int = 0) -> RangeScan:
    """Simulate a registered multi-view range scan of a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
        Counter-clockwise seen from outside.
    views : int
        Range images (scanner positions on a turntable ring).
    pixels : int
        Pixels per side of each range image; the object fills most of the image.
    noise : float
        Range noise (standard deviation along the ray, head-on) as a fraction of the bounding-box diagonal.
    edge_outliers : float
        Probability that a pixel at a depth edge is a mixed pixel (pushed back along its ray).
    spray : float
        Fraction of extra points scattered uniformly within the object's bounding box grown by 10 %.
    misregistration : float
        Largest displacement of a point by its scan's misregistration, as a fraction of the diagonal
        (each scan draws its own, uniformly up to this; scan 0 is exact).
    elevations : sequence of float
        Scanner elevations above the horizon, degrees; the views cycle through them.
    seed : int

    Returns
    -------
    RangeScan
    """
    rng = np.random.default_rng(seed)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    lo, hi = vertices.min(0), vertices.max(0)
    center = 0.5 * (lo + hi)
    diagonal = float(np.linalg.norm(hi - lo))
    radius = 0.5 * diagonal
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    eyes = turntable_views(views, center, radius, elevations=elevations, rng=rng)
    out_p, out_n, out_s, out_o = [], [], [], []
    for k, eye in enumerate(eyes):
        p, n, mixed = range_image(vertices, faces, fn, eye, center, radius, pixels, rng, noise=noise,
                                  edge_outliers=edge_outliers, diagonal=diagonal)
        if k > 0 and misregistration > 0:
            step = rng.uniform(0, misregistration) * diagonal
            # Split the displacement between a rotation about the centre and a translation.
            share = rng.uniform(0.3, 0.7)
            rot = _rotation(rng.normal(size=3), share * step / radius)
            shift = rng.normal(size=3)
            shift *= (1 - share) * step / np.linalg.norm(shift)
            p = (p - center) @ rot.T + center + shift
            n = n @ rot.T
        out_p.append(p)
        out_n.append(n)
        out_s.append(np.full(len(p), k, np.int64))
        out_o.append(mixed)
    pts = np.concatenate(out_p)
    n_spray = int(round(spray * len(pts)))
    if n_spray:
        box_lo, box_hi = lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)
        out_p.append(rng.uniform(box_lo, box_hi, size=(n_spray, 3)))
        out_n.append(np.zeros((n_spray, 3)))
        out_s.append(rng.integers(0, views, n_spray))
        out_o.append(np.ones(n_spray, bool))
    return RangeScan(
        points=np.concatenate(out_p),
        scan=np.concatenate(out_s),
        viewpoints=eyes,
        true_normals=np.concatenate(out_n),
        outlier=np.concatenate(out_o),
        diagonal=diagonal,
    )
