"""A learned check of the orientation's signs: which points still face the wrong way.

After :func:`nkf_model.normals.estimate.orient_normals` has oriented a closed object (``"outward"``), some
points keep a wrong sign where no single rule decides: hidden faces, thin parts, sharp edges. Each
rule's evidence is still there, per point: the views' votes, the other face of a thin part, the
winding number in front of and behind the point, the neighbours' agreement. A small network
(two hidden layers of 64) trained on the corpus's ``train`` split weighs them together and gives
each point the probability that its sign is wrong; points above :data:`FLIP_PROBABILITY` flip.

The weights ship as ``weights/sign_check.safetensors`` (float32 tensors; the feature names, their
normalisation and the training summary in the metadata), read with numpy only: no PyTorch is
needed to use them. ``python -m nkf_model.train.sign_check_training`` makes them again; the model card
``weights/SIGN_CHECK_CARD.md`` says on what and how well.

Every feature is measured in point spacings or as a ratio, and signed by the point's current
normal, so that flipping a point flips (or keeps) its features in a way the network can read.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import WeightsError
from ..io.safetensors_file import read_safetensors
from .edges import WINDING_EXCLUDE, edge_relation

FORMAT = "nkf-sign-check"
FORMAT_VERSION = "1"
WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "sign_check.safetensors"
# A point flips when the network gives its sign at least this probability of being wrong (chosen
# on held-out train meshes, docs/scans.md).
FLIP_PROBABILITY = 0.7
# At most this many points get the check (every point of a smaller cloud); larger clouds skip it
# (the winding-number fields it reads cost O(N) queries each).
MAX_POINTS = 20_000
# Offsets (in point spacings) in front of and behind each point where the winding number is read.
OFFSETS = (1.5, 3.0, 6.0, 12.0)

FEATURES = (
    "seeded", "vote_rel", "log_weight", "layer_front", "layer_back", "layer_vote_rel", "layer_seed_rel",
    "wgrad",
    *[f"w_{side}{d}" for d in OFFSETS for side in ("front", "back")],
    "consensus", "residual", "radial",
)


@dataclass
class OrientationState:
    """What the orientation knows about each point once it has chosen the signs.

    Attributes
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64
        Unit normals of arbitrary sign (the PCA directions); the oriented normals are
        ``normals * sign[:, None]``.
    sign : (N,) float64
        The chosen signs, +1 or -1.
    votes, weight : (N,) float64
        The views' summed votes and their weights (:func:`nkf_model.normals.estimate.visibility_votes`).
    view_seed : (N,) float64
        +1/-1 where the views decided the sign, 0 elsewhere.
    layer_seed : (N,) float64
        ``view_seed`` extended by the trusted layer votes.
    layer_vote : (N,) float64
        :func:`nkf_model.normals.estimate.layer_votes`, in the frame of ``normals``.
    above, below : (N,) int64
        :func:`nkf_model.normals.estimate.layer_sides`, in the frame of ``normals``.
    graph : scipy.sparse matrix (N, N)
        The orientation's neighbour graph.
    residual : (N,) float64
        Plane-fit residual of each point, in the units of ``points``.
    spacing : float
        Median nearest-neighbour distance, in the units of ``points``.
    winding : :class:`~nkf_model.points.winding.WindingGradient` or None
        The winding-number step's field over every point, when it built one (reused here).
    noise : (N,) float64 or None
        The noise level the orientation's edges used (offsets along the normals within it are noise).
    """

    points: np.ndarray
    normals: np.ndarray
    sign: np.ndarray
    votes: np.ndarray
    weight: np.ndarray
    view_seed: np.ndarray
    layer_seed: np.ndarray
    layer_vote: np.ndarray
    above: np.ndarray
    below: np.ndarray
    graph: object
    residual: np.ndarray
    spacing: float
    winding: object = None
    noise: object = None


def point_features(state: OrientationState, cancel_poll=None) -> np.ndarray:
    """Features (N, len(FEATURES)) float32 of every point, in the order of :data:`FEATURES`."""
    from ..points.winding import FarField, WindingGradient

    p, nrm, s, sp = state.points, state.normals, state.sign, state.spacing
    n = len(p)
    on = nrm * s[:, None]
    f = {}
    f["seeded"] = (state.view_seed != 0).astype(float)
    f["vote_rel"] = np.divide(state.votes * s, state.weight, out=np.zeros(n), where=state.weight > 0)
    f["log_weight"] = np.log1p(state.weight)
    front = np.where(s > 0, state.above, state.below)
    back = np.where(s > 0, state.below, state.above)
    f["layer_front"], f["layer_back"] = np.log1p(front), np.log1p(back)
    f["layer_vote_rel"] = state.layer_vote * s
    f["layer_seed_rel"] = state.layer_seed * s
    winding = state.winding if state.winding is not None else WindingGradient(p, nrm, WINDING_EXCLUDE * sp,
                                                                              cancel_poll=cancel_poll)
    grad = winding(s, cancel_poll=cancel_poll)
    f["wgrad"] = -np.sum(grad * on, axis=1) * sp
    field = FarField(p, on, cancel_poll=cancel_poll)
    for d in OFFSETS:
        f[f"w_front{d}"] = field(p + d * sp * on, cancel_poll)
        f[f"w_back{d}"] = field(p - d * sp * on, cancel_poll)
    g = state.graph.tocoo()
    rel = edge_relation(p, nrm, g.row, g.col, state.residual)
    agree = np.bincount(g.row, weights=rel * s[g.row] * s[g.col], minlength=n)
    f["consensus"] = agree / np.maximum(np.bincount(g.row, minlength=n), 1)
    f["residual"] = state.residual / sp
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    r = p - centre
    f["radial"] = np.sum(r * on, axis=1) / np.maximum(np.linalg.norm(r, axis=1), 1e-12)
    x = np.stack([f[k] for k in FEATURES], axis=1)
    return np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


class SignCheck:
    """The trained network: ``SignCheck.load()(features) -> (N,) probability that a sign is wrong``."""

    def __init__(self, layers, mean: np.ndarray, scale: np.ndarray, training: Optional[dict] = None):
        self.layers = [(np.asarray(w, np.float32), np.asarray(b, np.float32)) for w, b in layers]
        self.mean = np.asarray(mean, np.float32)
        self.scale = np.asarray(scale, np.float32)
        self.training = training or {}

    @classmethod
    def load(cls, path=None) -> SignCheck:
        """Read a weights file (default: the one shipped in the package); raises WeightsError."""
        path = Path(path) if path is not None else WEIGHTS
        if not path.is_file():
            raise WeightsError(f"sign-check weights {path} are missing; reinstall the package")
        t, meta = read_safetensors(path)
        if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
            raise WeightsError(f"{path} is not a sign-check weights file of version {FORMAT_VERSION}")
        names = tuple(json.loads(meta.get("features", "[]")))
        if names != FEATURES:
            raise WeightsError(f"{path} was trained on other features than this version computes")
        layers = []
        i = 0
        while f"w{i}" in t:
            layers.append((t[f"w{i}"], t[f"b{i}"]))
            i += 1
        if not layers or "mean" not in t or "scale" not in t:
            raise WeightsError(f"{path} lacks the network's tensors")
        return cls(layers, t["mean"], t["scale"], json.loads(meta.get("training", "{}")))

    def save(self, path) -> Path:
        """Write the network to ``path`` as safetensors (via a temporary file)."""
        from safetensors.numpy import save_file

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        t = {"mean": self.mean, "scale": self.scale}
        for i, (w, b) in enumerate(self.layers):
            t[f"w{i}"], t[f"b{i}"] = np.ascontiguousarray(w), np.ascontiguousarray(b)
        meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "features": json.dumps(list(FEATURES)),
                "training": json.dumps(self.training, sort_keys=True)}
        tmp = path.with_name(path.name + ".tmp")
        save_file(t, str(tmp), metadata=meta)
        tmp.replace(path)
        return path

    def __call__(self, features: np.ndarray) -> np.ndarray:
        h = (np.asarray(features, np.float32) - self.mean) / self.scale
        for k, (w, b) in enumerate(self.layers):
            h = h @ w.T + b
            if k < len(self.layers) - 1:
                h = np.maximum(h, 0.0)
        return 1.0 / (1.0 + np.exp(-h[:, 0].astype(np.float64)))


_LOADED: dict = {}


def default_check() -> Optional[SignCheck]:
    """The shipped network (loaded once), or None when the package has no such file or
    ``safetensors`` is not installed (optional in Blender: the orientation then runs without it)."""
    if "net" not in _LOADED:
        try:
            import safetensors  # noqa: F401
        except ImportError:
            _LOADED["net"] = None
        else:
            _LOADED["net"] = SignCheck.load() if WEIGHTS.is_file() else None
    return _LOADED["net"]


def flip_wrong(state: OrientationState, net: Optional[SignCheck] = None, cancel_poll=None):
    """Signs (N,) with the points the network finds wrong (probability >= FLIP_PROBABILITY)
    flipped, and the number flipped, or None where the check did not run (no network, more than
    MAX_POINTS points, fewer than 20): then the signs come back unchanged."""
    net = net if net is not None else default_check()
    if net is None or len(state.points) > MAX_POINTS or len(state.points) < 20:
        return state.sign, None
    prob = net(point_features(state, cancel_poll))
    flip = prob >= FLIP_PROBABILITY
    return np.where(flip, -state.sign, state.sign), int(flip.sum())
