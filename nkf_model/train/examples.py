"""Training data for the learned kernel: cached samples per mesh and augmented examples.

Per corpus mesh the cache (one ``.npz`` per mesh, built once, in a git-ignored folder) holds:

* ``surf_pts``, ``surf_nrm`` (S, 3) float32: points sampled uniformly by area and their normals;
* ``vol_pts`` (V, 3) float32, ``vol_occ`` (V,) bool: uniform points in the padded unit box
  ``[-0.55, 0.55]^3`` and whether they are inside (generalised winding number > 0.5, so open meshes
  work too);
* ``near_pts`` (V, 3) float32, ``near_occ`` (V,) bool: surface points moved by Gaussian offsets
  (half with standard deviation 0.005, half 0.02), with occupancy.

:func:`make_example` turns those samples into one training example: an input cloud of a random size,
optionally cut to one side of a plane through the centre, with position noise, transformed by a
random rotation (or one of the 48 axis permutations and flips) and anisotropic scaling, then
normalised to the unit box exactly as :func:`nkf_model.reconstruct` normalises its input; plus
labelled query points and surface points in the same frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..points.normalise import GRID_HALF, Normalisation
from . import corpus, metrics

CACHE_VERSION = 1
PAD = 0.5 + metrics.PADDING  # half side of the box the cached volume points fill


@dataclass(frozen=True)
class CacheSpec:
    """Sample counts per mesh."""

    n_surface: int = 20000
    n_volume: int = 8192
    n_near: int = 8192


def _cache_path(cache_dir: Path, entry: corpus.CorpusMesh) -> Path:
    return Path(cache_dir) / f"{entry.name}.npz"


def build_samples(entry: corpus.CorpusMesh, spec: CacheSpec, device=None) -> dict:
    """Compute the cached samples of one corpus mesh (see the module docstring)."""
    v, f = corpus.load(entry)
    return samples_from_mesh(v, f, spec, corpus.stable_seed("train-cache", entry.name), device=device)


def samples_from_mesh(v, f, spec: CacheSpec, seed: int, device=None) -> dict:
    """Samples of a triangle mesh (vertices (V, 3), faces (F, 3)) in the corpus's unit box.

    ``device``: where the winding numbers are computed (None: the CPU loop; ``"cuda"``: PyTorch).
    """
    rng = np.random.default_rng(seed)
    sp, sn = metrics.sample_surface(v, f, spec.n_surface, rng)
    vol = rng.uniform(-PAD, PAD, size=(spec.n_volume, 3))
    src, _ = metrics.sample_surface(v, f, spec.n_near, rng)
    sigma = np.where(np.arange(spec.n_near) % 2 == 0, 0.005, 0.02)[:, None]
    near = src + rng.normal(size=src.shape) * sigma
    wn = metrics.winding_number(v, f, np.concatenate([vol, near]), device=device)
    occ = wn > 0.5
    return {
        "version": np.int64(CACHE_VERSION),
        "surf_pts": sp.astype(np.float32),
        "surf_nrm": sn.astype(np.float32),
        "vol_pts": vol.astype(np.float32),
        "vol_occ": occ[: spec.n_volume],
        "near_pts": near.astype(np.float32),
        "near_occ": occ[spec.n_volume :],
    }


def load_samples(path: Path) -> dict | None:
    """Cached samples from ``path``, or None if it is missing, unreadable or of another version."""
    try:
        with np.load(path) as d:
            if int(d["version"]) != CACHE_VERSION:
                return None
            return {k: d[k] for k in d.files if k != "version"}
    except (OSError, KeyError, ValueError):
        return None


def build_cache(entries, cache_dir: Path, spec: CacheSpec = CacheSpec(), progress: bool = True,
                device=None) -> list[dict]:
    """Samples of every entry, computed once into ``cache_dir`` (a progress bar on stderr).

    ``device``: where missing samples' winding numbers are computed (see :func:`samples_from_mesh`).
    """
    from tqdm import tqdm

    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    out = []
    for e in tqdm(entries, desc="train cache", disable=not progress, unit="mesh"):
        path = _cache_path(cache_dir, e)
        d = load_samples(path)
        if d is None:
            d = build_samples(e, spec, device=device)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, **d)
            tmp.replace(path)
            d.pop("version")
        out.append(d)
    return out


@dataclass(frozen=True)
class AugmentSpec:
    """How training examples are drawn (see :func:`make_example`)."""

    n_min: int = 300
    n_max: int = 3000
    n_mode: int = 1000  # input sizes are log-normal around this, clipped to [n_min, n_max]
    n_log_sigma: float = 0.5
    noise_max: float = 0.005
    p_noise_free: float = 0.35
    p_half: float = 0.2
    p_rotate: float = 0.5  # otherwise one of the 48 axis permutations and flips
    scale_min: float = 0.75
    scale_max: float = 1.25
    # Partial surfaces (not with half): drop the input points within 1..partial_holes balls centred
    # on surface points, of radius partial_radius_min..max (mesh units), as a scan misses patches.
    p_partial: float = 0.0
    partial_holes: int = 3
    partial_radius_min: float = 0.08
    partial_radius_max: float = 0.3
    n_volume: int = 1024
    n_near: int = 1024
    n_surface: int = 512


@dataclass
class Example:
    """One training (or validation) example, all in the input's unit box, float64.

    Attributes
    ----------
    points, normals : (N, 3)
        Oriented input points (unit normals).
    queries : (Q, 3)
        Query points with known occupancy.
    occupancy : (Q,)
        1.0 inside, 0.0 outside.
    surface : (S, 3)
        Points on the true surface (the field should be zero there).
    noise : float
        Standard deviation of the position noise (units of the mesh's box).
    half : bool
        The input was cut to one side of a plane.
    """

    points: np.ndarray
    normals: np.ndarray
    queries: np.ndarray
    occupancy: np.ndarray
    surface: np.ndarray
    noise: float
    half: bool


def _random_rotation(rng) -> np.ndarray:
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


def _signed_permutation(rng) -> np.ndarray:
    m = np.zeros((3, 3))
    m[np.arange(3), rng.permutation(3)] = rng.choice([-1.0, 1.0], size=3)
    return m


def half_space_mask(points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Points (N, 3) on the positive side of the plane through the box centre (origin) normal to
    ``direction``."""
    return points @ direction > 0.0


def partial_mask(points: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Points (N, 3) outside every ball (centres (K, 3), radii (K,))."""
    d = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=2)
    return np.all(d > radii[None, :], axis=1)


def sample_input(samples: dict, n: int, noise: float, rng, half_direction=None, holes=None):
    """Input points and normals from the cached surface samples (mesh frame, float64).

    ``holes``: optional (centres (K, 3), radii (K,)); surface samples inside those balls are never drawn.
    """
    sp = samples["surf_pts"].astype(np.float64)
    sn = samples["surf_nrm"].astype(np.float64)
    # Samples without a usable normal (zero or non-finite, as a degenerate spot of a shape gives) are
    # never drawn: one would turn into NaN features and end the run.
    length = np.linalg.norm(sn, axis=1)
    idx = np.flatnonzero(np.isfinite(length) & (length > 0.5))
    if half_direction is not None:
        idx = idx[half_space_mask(sp[idx], half_direction)]
    if holes is not None:
        kept = idx[partial_mask(sp[idx], *holes)]
        if len(kept) >= min(n, len(idx)) // 2:  # never leave less than half of what was asked for
            idx = kept
    pick = rng.choice(idx, size=min(n, len(idx)), replace=False)
    pts, nrm = sp[pick], sn[pick]
    if noise > 0:
        pts = pts + rng.normal(scale=noise, size=pts.shape)
    return pts, nrm


def make_example(samples: dict, rng: np.random.Generator, spec: AugmentSpec = AugmentSpec()) -> Example:
    """One randomly augmented training example from a mesh's cached samples."""
    n = int(np.clip(round(np.exp(rng.normal(np.log(spec.n_mode), spec.n_log_sigma))), spec.n_min, spec.n_max))
    noise = 0.0 if rng.random() < spec.p_noise_free else float(rng.uniform(0.0, spec.noise_max))
    half = rng.random() < spec.p_half
    direction = None
    if half:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
    holes = None
    if spec.p_partial > 0 and not half and rng.random() < spec.p_partial:
        sp = samples["surf_pts"]
        k = int(rng.integers(1, spec.partial_holes + 1))
        holes = (sp[rng.integers(len(sp), size=k)].astype(np.float64),
                 rng.uniform(spec.partial_radius_min, spec.partial_radius_max, size=k))
    pts, nrm = sample_input(samples, n, noise, rng, direction, holes)

    rot = _random_rotation(rng) if rng.random() < spec.p_rotate else np.eye(3)
    A = np.diag(rng.uniform(spec.scale_min, spec.scale_max, size=3)) @ _signed_permutation(rng) @ rot
    A_inv = np.linalg.inv(A)
    p = pts @ A.T
    nn_ = nrm @ A_inv  # normals transform by A^{-T}
    nn_ /= np.linalg.norm(nn_, axis=1, keepdims=True)
    norm = Normalisation.fit(p)
    p = norm.to_unit(p)

    def to_unit(x):
        return norm.to_unit(np.asarray(x, np.float64) @ A.T)

    def in_box(u):
        return np.all(np.abs(u) <= GRID_HALF, axis=1)

    # Near-surface queries.
    near = to_unit(samples["near_pts"])
    ok = np.flatnonzero(in_box(near))
    pick = rng.choice(ok, size=min(spec.n_near, len(ok)), replace=False)
    q_near, o_near = near[pick], samples["near_occ"][pick]
    # Uniform queries over the grid box: outside the mesh's padded box they are outside the shape;
    # inside it they are replaced by cached volume points (whose occupancy is known).
    u = rng.uniform(-GRID_HALF, GRID_HALF, size=(spec.n_volume, 3))
    back = norm.to_world(u) @ A_inv.T
    outside = ~np.all(np.abs(back) <= PAD, axis=1)
    vol = to_unit(samples["vol_pts"])
    ok = np.flatnonzero(in_box(vol))
    k = min(int((~outside).sum()), len(ok))
    pick = rng.choice(ok, size=k, replace=False)
    q_vol = np.concatenate([u[outside], vol[pick]])
    o_vol = np.concatenate([np.zeros(int(outside.sum()), bool), samples["vol_occ"][pick]])
    # Surface targets from the whole surface (also the part cut away from a half input).
    surf = to_unit(samples["surf_pts"][rng.choice(len(samples["surf_pts"]), spec.n_surface, replace=False)])
    surf = surf[in_box(surf)]
    return Example(
        points=p,
        normals=nn_,
        queries=np.concatenate([q_near, q_vol]),
        occupancy=np.concatenate([o_near, o_vol]).astype(np.float64),
        surface=surf,
        noise=noise,
        half=half,
    )


def validation_example(samples: dict, n: int, noise: float, half: bool, seed: int) -> Example:
    """A fixed, untransformed example for validation: queries are all cached volume points."""
    rng = np.random.default_rng(seed)
    direction = None
    if half:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
    pts, nrm = sample_input(samples, n, noise, rng, direction)
    norm = Normalisation.fit(pts)
    vol = norm.to_unit(samples["vol_pts"])
    return Example(
        points=norm.to_unit(pts),
        normals=nrm,
        queries=vol,
        occupancy=samples["vol_occ"].astype(np.float64),
        surface=norm.to_unit(samples["surf_pts"][:512]),
        noise=noise,
        half=half,
    )
