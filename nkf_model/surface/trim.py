"""Clean-up of meshes from open scans: cut away surface far from the input points, drop small pieces.

A kernel fit is a closed surface. Where a scan has no data (the back of a wall, the underside of an
object on a table, the sky) the surface still closes, far from every input point. :func:`trim_far`
removes the triangles with a vertex farther than ``factor`` times the input's point spacing (the
median nearest-neighbour distance) from the nearest input point, and :func:`remove_small_pieces`
removes connected pieces whose area is below a fraction of the whole mesh's area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree


@dataclass
class TrimInfo:
    """What the clean-up removed.

    Attributes
    ----------
    threshold : float
        Distance beyond which vertices were cut, in the mesh's units (0 when trimming was off).
    trimmed_faces : int
        Triangles removed for being far from the points.
    pieces_before, pieces_removed : int
        Connected pieces before the size filter, and how many it removed.
    small_piece_faces : int
        Triangles removed with those pieces.
    floaters_removed : int
        Pieces removed for an area under ``min_area`` (floaters), with their triangles in
        ``small_piece_faces``.
    """

    threshold: float = 0.0
    trimmed_faces: int = 0
    pieces_before: int = 0
    pieces_removed: int = 0
    small_piece_faces: int = 0
    floaters_removed: int = 0


def far_vertices(vertices: np.ndarray, points: np.ndarray, threshold: float, tree=None) -> np.ndarray:
    """Mask (V,) of vertices farther than ``threshold`` from every point of ``points`` (N, 3)."""
    tree = tree if tree is not None else cKDTree(points)
    d, _ = tree.query(vertices, k=1, distance_upper_bound=threshold, workers=-1)
    return ~np.isfinite(d)


def trim_far(vertices, faces, points, threshold: float, tree=None) -> np.ndarray:
    """Mask (F,) of the faces to keep: those whose three vertices all lie within ``threshold``
    of an input point."""
    far = far_vertices(vertices, points, threshold, tree)
    return ~far[faces].any(axis=1)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area (F,) of each triangle."""
    t = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def piece_labels(n_vertices: int, faces: np.ndarray):
    """Connected pieces of a triangle mesh (through shared vertices): (count, labels (F,))."""
    if len(faces) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    from scipy.sparse.csgraph import connected_components  # only when trimming: not on every import

    r = np.concatenate([faces[:, 0], faces[:, 1]])
    c = np.concatenate([faces[:, 1], faces[:, 2]])
    g = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n_vertices, n_vertices))
    _, vlabel = connected_components(g, directed=False)
    used, flabel = np.unique(vlabel[faces[:, 0]], return_inverse=True)
    return len(used), flabel.reshape(-1)


def remove_small_pieces(vertices, faces, min_fraction: float):
    """Mask (F,) of faces to keep: pieces with at least ``min_fraction`` of the total area.

    Returns the mask, the number of pieces and the number removed.
    """
    count, label = piece_labels(len(vertices), faces)
    if count == 0 or min_fraction <= 0:
        return np.ones(len(faces), dtype=bool), count, 0
    area = np.bincount(label, weights=face_areas(vertices, faces), minlength=count)
    keep_piece = area >= min_fraction * area.sum()
    return keep_piece[label], count, int((~keep_piece).sum())


def compact(vertices: np.ndarray, faces: np.ndarray, keep_faces: np.ndarray):
    """Drop the faces not in ``keep_faces`` and the vertices no face uses.

    Returns the kept faces re-indexed (F', 3) and the indices (V',) of the kept vertices.
    """
    faces = faces[keep_faces]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return remap[faces], np.flatnonzero(used)


def clean_scan_mesh(vertices, faces, points, spacing: float, trim=None, min_piece: float = 0.0, floor: float = 0.0,
                    min_area: float = 0.0, max_share: float = 1.0):
    """Trim and filter a mesh; returns ``(faces (F', 3), kept vertex indices (V',), TrimInfo)``.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    points : (N, 3) float
        Input points, in the frame of ``vertices``.
    spacing : float
        Point spacing (median nearest-neighbour distance), in the same units.
    trim : float or None
        Cut triangles farther than ``trim * spacing`` (never less than ``floor``) from the points;
        ``None`` keeps everything.
    min_piece : float
        Remove connected pieces with less than this fraction of the total area (0 keeps all).
    floor : float
        Smallest trimming distance (the caller passes one grid cell: the surface cannot follow the
        points closer than that).
    min_area : float
        Also remove pieces with less than this area, in the mesh's units squared (0 keeps all).
    max_share : float
        ... but only those that also have less than this fraction of the total area (1: no limit).
    """
    info = TrimInfo()
    keep = np.ones(len(faces), dtype=bool)
    if trim is not None and len(faces):
        info.threshold = max(float(trim) * float(spacing), float(floor))
        keep = trim_far(vertices, faces, points, info.threshold)
        info.trimmed_faces = int((~keep).sum())
    if min_piece > 0 and keep.any():
        sub_faces = faces[keep]
        mask, info.pieces_before, info.pieces_removed = remove_small_pieces(vertices, sub_faces, min_piece)
        info.small_piece_faces = int((~mask).sum())
        idx = np.flatnonzero(keep)
        keep[idx[~mask]] = False
    elif len(faces):
        info.pieces_before = piece_labels(len(vertices), faces[keep])[0]
    if min_area > 0 and keep.any():
        idx = np.flatnonzero(keep)
        count, label = piece_labels(len(vertices), faces[idx])
        area = np.bincount(label, weights=face_areas(vertices, faces[idx]), minlength=count)
        small = (area < min_area) & (area < max_share * area.sum())
        if small.all():  # never remove every piece: keep the largest
            small[np.argmax(area)] = False
        info.floaters_removed = int(small.sum())
        drop = small[label]
        info.small_piece_faces += int(drop.sum())
        keep[idx[drop]] = False
    new_faces, kept = compact(vertices, faces, keep)
    return new_faces, kept, info
