"""Stage 6: triangulate the zero level set of a :class:`~nkf_model.surface.evaluate.SparseField`.

scikit-image's Lewiner marching cubes runs block by block (``BLOCK`` cells per side) on the band
cells only (its ``mask`` argument), so memory stays bounded whatever the resolution. Vertices that
neighbouring blocks both produce lie on the same grid edge; they are welded by the edge's integer
key, not by comparing float coordinates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from skimage.measure import marching_cubes

from ..points.normalise import GRID_HALF
from .evaluate import SparseField, node_keys

BLOCK = 32


@dataclass
class Mesh:
    """A triangle mesh in the input's coordinate frame.

    Attributes
    ----------
    vertices : (V, 3) float32
        Positions, in the input's coordinates and units.
    faces : (F, 3) int32
        Vertex indices, counter-clockwise seen from outside (normals point out).
    normals : (V, 3) float32
        Unit vertex normals (area-weighted face normals), pointing outward.
    center : (3,) float64
        Centre of the input's bounding box.
    scale : float
        Longest side of the input's bounding box.
    local_vertices : (V, 3) float32
        ``vertices - center`` computed in float64 before rounding. Float32 ``vertices`` lose
        precision far from the origin (coordinates around 1e6); ``center`` plus these keep it,
        for example as a Blender object's location and its mesh.
    stats : dict
        Counts and per-stage timings of the run that made it.
    colors : (V, 3) uint8 or None
        Per-vertex colour (8-bit sRGB, as in PLY files) carried from coloured input points; in
        Blender, a ``BYTE_COLOR`` point attribute (set ``color_srgb`` to ``colors / 255`` plus
        alpha 1).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    local_vertices: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    colors: np.ndarray | None = None

    def __post_init__(self):
        if self.local_vertices is None:
            self.local_vertices = (np.asarray(self.vertices, np.float64) - self.center).astype(np.float32)


def triangulate(
    field_: SparseField,
    cancel_poll: Callable[[], None] | None = None,
    step: Callable[[float], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes at level 0 over the band cells of ``field_``.

    Returns
    -------
    vertices : (V, 3) float64
        Unit-box positions, welded across blocks.
    faces : (F, 3) int64
        Outward-facing triangles (the field is negative inside).
    """
    r = field_.resolution
    band = field_.band
    if len(band) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    block_of = band // BLOCK
    nb = (r + BLOCK - 1) // BLOCK
    bkey = (block_of[:, 0] * nb + block_of[:, 1]) * nb + block_of[:, 2]
    order = np.argsort(bkey, kind="stable")
    bkey, band = bkey[order], band[order]
    starts = np.flatnonzero(np.r_[True, bkey[1:] != bkey[:-1]])
    ends = np.r_[starts[1:], len(bkey)]
    g = np.arange(BLOCK + 1)
    local_nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)

    all_keys, all_pos, all_faces = [], [], []
    n_vertices = 0
    n_interior = 0
    for bi, (s, e) in enumerate(zip(starts, ends)):
        if cancel_poll is not None:
            cancel_poll()
        cells = band[s:e]
        origin = (cells[0] // BLOCK) * BLOCK
        size = np.minimum(BLOCK, r - origin)  # cells along each axis in this block
        shape = tuple(int(x) + 1 for x in size)
        nodes = local_nodes.reshape(BLOCK + 1, BLOCK + 1, BLOCK + 1, 3)[: shape[0], : shape[1], : shape[2]]
        nodes = nodes.reshape(-1, 3)
        vol = field_.lookup(origin + nodes).reshape(shape)
        vol = np.where(np.isnan(vol), 1.0, vol).astype(np.float32)
        mask = np.zeros(shape, dtype=bool)
        # skimage processes the cell whose far corner (x+1, y+1, z+1) is set in the mask.
        lc = cells - origin + 1
        mask[lc[:, 0], lc[:, 1], lc[:, 2]] = True
        try:
            v, f, _, _ = marching_cubes(vol, level=0.0, gradient_direction="descent", mask=mask)
        except (RuntimeError, ValueError):
            continue  # no crossing inside the masked cells of this block
        if len(f) == 0:
            continue
        keys, n_interior = _edge_keys(v, origin, r, n_interior)
        all_keys.append(keys)
        all_pos.append(v.astype(np.float64) + origin)
        all_faces.append(f.astype(np.int64) + n_vertices)
        n_vertices += len(v)
        if step is not None:
            step((bi + 1) / len(starts))
    if not all_faces:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    keys = np.concatenate(all_keys)
    pos = np.concatenate(all_pos)
    faces = np.concatenate(all_faces)
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    pos = pos[first]
    faces = inverse.reshape(-1)[faces]
    degenerate = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    faces = faces[~degenerate]
    used = np.zeros(len(pos), dtype=bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    pos = pos[used]
    faces = remap[faces]
    unit = -GRID_HALF + pos * (2.0 * GRID_HALF / r)
    return unit, faces


def _edge_keys(v: np.ndarray, origin: np.ndarray, r: int, n_interior: int):
    """Integer identity of each marching-cubes vertex: its grid edge, node, or (for the extra
    vertices Lewiner's method puts inside ambiguous cells) a unique negative number."""
    fl = np.floor(v).astype(np.int64)
    frac = v != fl
    nfrac = frac.sum(axis=1)
    axis = np.where(nfrac == 1, np.argmax(frac, axis=1), 3)
    key = node_keys(fl + origin, r) * 4 + axis
    interior = nfrac > 1
    k = int(interior.sum())
    key[interior] = -1 - n_interior - np.arange(k)
    return key, n_interior + k


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) float64 of a triangle mesh."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices, dtype=np.float64)
    for c in range(3):
        for k in range(3):
            vn[:, k] += np.bincount(faces[:, c], weights=fn[:, k], minlength=len(vertices))
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, length, out=np.zeros_like(vn), where=length > 0)
