"""Reconstruction quality, by the Convolutional Occupancy Networks protocol.

All meshes are taken in the unit box of the reference shape. Surface metrics compare 100,000 points
sampled uniformly on each surface; IoU compares the inside/outside state of 100,000 uniform points
in the box padded by 0.05 on each side:

* Chamfer-L1: mean of the two mean nearest-neighbour distances (prediction to reference and back).
* Normal consistency: mean of the two mean ``|n_pred . n_ref|`` over nearest neighbours.
* F-score at ``tau`` = 0.01: harmonic mean of precision and recall of points within ``tau``.
* IoU of the occupancies; inside is decided by the generalised winding number (> 0.5), which
  also works for reference meshes that are not watertight.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

PADDING = 0.05
FSCORE_TAU = 0.01


def sample_surface(vertices, faces, n: int, rng: np.random.Generator, return_faces: bool = False):
    """Sample ``n`` points uniformly by area on a triangle mesh (faces of zero area are never drawn).

    Returns
    -------
    points : (n, 3) float64
    normals : (n, 3) float64
        Unit normals of the sampled faces (outward for consistently wound meshes).
    face : (n,) int64
        Only with ``return_faces``: the row of ``faces`` each point lies on.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    keep = area > 0
    tri, cross, area = tri[keep], cross[keep], area[keep]
    which = rng.choice(len(tri), size=n, p=area / area.sum())
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    t = tri[which]
    pts = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
    nrm = cross[which] / (2.0 * area[which])[:, None]
    if return_faces:
        return pts, nrm, np.flatnonzero(keep)[which]
    return pts, nrm


@nb.njit(parallel=True, nogil=True, cache=True)
def _winding(v, f, q):  # pragma: no cover - compiled
    out = np.zeros(q.shape[0])
    for i in nb.prange(q.shape[0]):
        s = 0.0
        px, py, pz = q[i, 0], q[i, 1], q[i, 2]
        for t in range(f.shape[0]):
            ax = v[f[t, 0], 0] - px
            ay = v[f[t, 0], 1] - py
            az = v[f[t, 0], 2] - pz
            bx = v[f[t, 1], 0] - px
            by = v[f[t, 1], 1] - py
            bz = v[f[t, 1], 2] - pz
            cx = v[f[t, 2], 0] - px
            cy = v[f[t, 2], 1] - py
            cz = v[f[t, 2], 2] - pz
            la = math.sqrt(ax * ax + ay * ay + az * az)
            lb = math.sqrt(bx * bx + by * by + bz * bz)
            lc = math.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
            den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc
            den += (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb
            s += 2.0 * math.atan2(det, den)
        out[i] = s / (4.0 * math.pi)
    return out


def _winding_torch(v, f, q, device) -> np.ndarray:
    """:func:`_winding` in float64 PyTorch on ``device`` (the same formula), in chunks of queries."""
    import torch

    vt = torch.as_tensor(v, dtype=torch.float64, device=device)
    ft = torch.as_tensor(f, dtype=torch.int64, device=device)
    tri = vt[ft]  # (F, 3 corners, 3)
    out = torch.empty(len(q), dtype=torch.float64, device=device)
    qt = torch.as_tensor(q, dtype=torch.float64, device=device)
    step = max(1, (1 << 24) // max(1, len(f)))  # about 16M query-face pairs per chunk
    for s in range(0, len(q), step):
        d = tri[None] - qt[s : s + step, None, None, :]  # (Q, F, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[s : s + step] = (2.0 * torch.atan2(det, den)).sum(-1) / (4.0 * math.pi)
    return out.cpu().numpy()


def winding_number(vertices, faces, queries, device=None) -> np.ndarray:
    """Generalised winding number (Jacobson et al. 2013) of a triangle mesh at ``queries`` (N, 3).

    About 1 inside a closed, outward-facing mesh and 0 outside; O(N F) time. ``device`` (a
    PyTorch device such as ``"cuda"``) computes it there in float64 with the same formula; None
    uses the compiled CPU loop.
    """
    if device is not None:
        return _winding_torch(vertices, faces, queries, device)
    return _winding(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(queries, dtype=np.float64),
    )


def occupancy(vertices, faces, queries) -> np.ndarray:
    """Inside test (N,) bool by winding number > 0.5."""
    return winding_number(vertices, faces, queries) > 0.5


AMBIGUOUS_BAND = 0.25  # a winding number further than this from every whole number >= 0 is ambiguous


def ambiguous_share(w: np.ndarray, band: float = AMBIGUOUS_BAND) -> float:
    """Share of winding numbers ``w`` (N,) that say neither inside nor outside.

    A consistently oriented mesh has winding numbers near 0 outside and near 1 inside (near 2
    where two closed parts overlap). Holes leave values in between, and faces that point inward
    leave negative values; there the occupancy ``w > 0.5`` of :func:`occupancy` is a guess about
    the shape. Counted: ``w < -band`` and ``|w - round(w)| > band``.
    """
    w = np.asarray(w, dtype=np.float64)
    if len(w) == 0:
        return 0.0
    return float(np.mean((w < -band) | (np.abs(w - np.round(w)) > band)))


def volume_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` uniform points in the unit box padded by :data:`PADDING` on each side."""
    h = 0.5 + PADDING
    return rng.uniform(-h, h, size=(n, 3))


def iou(occ_a: np.ndarray, occ_b: np.ndarray) -> float:
    """Intersection over union of two boolean occupancy arrays."""
    union = np.logical_or(occ_a, occ_b).sum()
    return float(np.logical_and(occ_a, occ_b).sum() / union) if union else 1.0


def surface_metrics(pred_pts, pred_nrm, ref_pts, ref_nrm, tau: float = FSCORE_TAU) -> dict:
    """Chamfer-L1, normal consistency and F-score between two oriented point samples."""
    d_pr, i_pr = cKDTree(ref_pts).query(pred_pts, workers=-1)
    d_rp, i_rp = cKDTree(pred_pts).query(ref_pts, workers=-1)
    nc_pr = np.abs(np.sum(pred_nrm * ref_nrm[i_pr], axis=1)).mean()
    nc_rp = np.abs(np.sum(ref_nrm * pred_nrm[i_rp], axis=1)).mean()
    precision = float((d_pr < tau).mean())
    recall = float((d_rp < tau).mean())
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "chamfer_l1": 0.5 * float(d_pr.mean() + d_rp.mean()),
        "normal_consistency": 0.5 * float(nc_pr + nc_rp),
        "fscore": f,
    }


def chamfer_l1(pred_pts, ref_pts) -> float:
    """Chamfer-L1 distance between two point sets (N, 3) and (M, 3)."""
    d1, _ = cKDTree(ref_pts).query(pred_pts, workers=-1)
    d2, _ = cKDTree(pred_pts).query(ref_pts, workers=-1)
    return 0.5 * float(d1.mean() + d2.mean())
