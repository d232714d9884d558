"""Train the learned sign check (:mod:`nkf_model.normals.sign_check`) on the corpus's ``train`` split.

``python -m nkf_model.train.sign_check_training`` samples each ``train`` mesh at 10,000 points (as the
normals benchmark does), orients the PCA normals without the check (views, graph, layer votes,
winding number), and records every point's features and whether its sign disagrees with the mesh's
normal. A small network (two hidden layers of 64, ReLU) learns that probability with a binary
cross-entropy; the weights go to ``nkf_model/weights/sign_check.safetensors`` (or ``--out``).

Labels come from the mesh's face normals, turned around for meshes wound inside out
(:func:`outward_samples`); meshes whose labels disagree with the orientation on most points are
left out (:data:`MAX_WRONG`). The first ``--holdout`` meshes by the SHA-256 of their names (60)
are left out too, so that the check can be judged on train meshes the network has not seen; the
``val`` split is never read. Features are cached per mesh in ``--cache``; about 2.5 s a mesh on 2
CPU cores, then about a minute of training.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import numpy as np

from ..normals.estimate import DEFAULT_K, _estimate
from ..normals.sign_check import FEATURES, WEIGHTS, SignCheck, point_features
from . import corpus

HOLDOUT = 60
HIDDEN = 64
# A mesh whose (outward) normals disagree with the orientation on more than this share of its
# points is left out: an open sheet has no outside, and such labels are more likely wrong than the
# orientation (docs/scans.md).
MAX_WRONG = 0.5


def holdout_split(entries, holdout: int = HOLDOUT):
    """``(fit, held_out)``: the entries sorted by the SHA-256 of their names, the first
    ``holdout`` held out."""
    order = sorted(entries, key=lambda e: hashlib.sha256(e.name.encode()).hexdigest())
    return order[holdout:], order[:holdout]


def outward_samples(vertices, faces, n_points: int, noise: float, seed: int):
    """:func:`nkf_model.train.corpus.sample_input`'s points (n, 3) and normals (n, 3), all turned around
    when the mesh's signed volume (about its vertices' centroid) is negative.

    A few corpus meshes are wound inside out (a shark, a head); their face normals point in, and as
    labels they would teach the network that outward normals are wrong."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    pts, nrm = corpus.sample_input(v, f, n_points, noise, seed)
    tri = v[f] - v.mean(axis=0)
    volume = float(np.einsum("fi,fi->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    return pts, (-nrm if volume < 0 else nrm)


def mesh_features(entry, n_points: int = 10_000, noise: float = 0.0):
    """Features (n, F) float32 and labels (n,) float32 (1 where the oriented sign is wrong, against
    :func:`outward_samples`' normals) of one corpus mesh, sampled as
    :mod:`benchmarks.bench_normals` samples it."""
    v, f = corpus.load(entry)
    pts, true_nrm = outward_samples(v, f, n_points, noise, corpus.stable_seed("input", entry.name, n_points, noise))
    sign, state, _ = _estimate(pts, DEFAULT_K, "outward", None)
    nrm = state.normals
    y = (np.sum(nrm * sign[:, None] * true_nrm, axis=1) < 0).astype(np.float32)
    return point_features(state), y


def train(x: np.ndarray, y: np.ndarray, epochs: int = 6, seed: int = 0, log=print) -> tuple[SignCheck, float]:
    """Fit the network to features ``x`` (M, F) and labels ``y`` (M,); returns it and the last
    epoch's mean loss."""
    import torch

    torch.manual_seed(seed)
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-6
    xt = torch.tensor((x - mean) / scale, dtype=torch.float32)
    yt = torch.tensor(y, dtype=torch.float32)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], HIDDEN), torch.nn.ReLU(), torch.nn.Linear(HIDDEN, HIDDEN),
                              torch.nn.ReLU(), torch.nn.Linear(HIDDEN, 1))
    opt = torch.optim.Adam(net.parameters(), 2e-3, weight_decay=1e-5)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    n = len(yt)
    mean_loss = float("nan")
    for epoch in range(epochs):
        perm = torch.randperm(n)
        total = 0.0
        for s in range(0, n, 4096):
            b = perm[s : s + 4096]
            loss = loss_fn(net(xt[b]).squeeze(1), yt[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(b)
        mean_loss = total / n
        log(f"epoch {epoch + 1}/{epochs}: loss {mean_loss:.4f}")
    layers = [(m.weight.detach().numpy(), m.bias.detach().numpy()) for m in net if isinstance(m, torch.nn.Linear)]
    return SignCheck(layers, mean, scale), mean_loss


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m nkf_model.train.sign_check_training",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--holdout", type=int, default=HOLDOUT)
    ap.add_argument("--limit", type=int, default=None, help="train on the first N meshes only")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0, help="seed of the network's start and of the batches")
    ap.add_argument("--cache", type=Path, default=Path(".sign-check-cache"))
    ap.add_argument("--out", type=Path, default=WEIGHTS)
    args = ap.parse_args(argv)
    log = lambda *a: print(*a, file=sys.stderr, flush=True)  # noqa: E731
    fit, held = holdout_split([e for e in corpus.manifest() if e.split == "train"], args.holdout)
    if args.limit:
        fit = fit[: args.limit]
    args.cache.mkdir(parents=True, exist_ok=True)
    xs, ys, skipped = [], [], []
    for i, e in enumerate(fit):
        f = args.cache / f"{e.name}-{args.points}.npz"
        if f.is_file():
            d = np.load(f)
            x, y = d["x"], d["y"]
        else:
            t0 = time.perf_counter()
            x, y = mesh_features(e, args.points)
            np.savez_compressed(f, x=x, y=y)
            log(f"[{i + 1}/{len(fit)}] {e.name}: {y.mean():.1%} wrong signs ({time.perf_counter() - t0:.1f} s)")
        if y.mean() > MAX_WRONG:
            skipped.append(e.name)
            continue
        xs.append(x)
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    log(f"{len(xs)} meshes, {len(y):,} points, {y.mean():.2%} with a wrong sign; left out (labels disagree "
        f"with the orientation on most points): {', '.join(skipped) or 'none'}")
    net, loss = train(x, y, args.epochs, seed=args.seed, log=log)
    net.training = {
        "split": "train", "meshes": len(xs), "left_out": skipped, "held_out": len(held), "points_per_mesh": args.points,
        "points": int(len(y)), "wrong_share": round(float(y.mean()), 5), "epochs": args.epochs, "seed": args.seed,
        "final_loss": round(loss, 5), "features": list(FEATURES), "hidden": HIDDEN,
    }
    net.save(args.out)
    log(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
