"""Held-out check of a weights file: learned kernel vs Neural Splines, with and without the per-point
weights, on meshes of the train split that training never saw (the same held-out meshes as
``nkf train``'s validation, chosen by the config's ``data.holdout``).

    python scripts/nkf_ablation.py --config configs/nkf.toml --weights nkf_model/weights/nkf_default.safetensors

Prints a Markdown table of mean IoU (sign of the fitted field at the cached volume points, as in
training's validation) and statistics of the learned weights; ``--json`` also writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nkf_model.fit.augment import augment, default_eps  # noqa: E402
from nkf_model.kernel.weights import load_weights  # noqa: E402
from nkf_model.train import corpus  # noqa: E402
from nkf_model.train.examples import build_cache, validation_example  # noqa: E402
from nkf_model.train.kernel_training import example_field, field_iou, load_config  # noqa: E402

SETTINGS = [(300, 0.0, False), (300, 0.005, False), (1000, 0.0, False), (1000, 0.005, False),
            (3000, 0.0, False), (3000, 0.0, True)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/nkf.toml")
    ap.add_argument("--weights", default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config(args.config)
    model = load_weights(args.weights)
    net = model.net
    entries = [e for e in corpus.manifest() if e.split == cfg.data.split]
    entries.sort(key=lambda e: corpus.stable_seed("holdout", e.name))
    hold = entries[: cfg.data.holdout]
    samples = build_cache(hold, Path(cfg.data.cache), cfg.cache, progress=False)
    rows = []
    for n, noise, half in SETTINGS:
        iou = {"splines": [], "nkf": [], "nkf, weights = 1": []}
        wstats = []
        for e, s in zip(hold, samples):
            seed = corpus.stable_seed("ablation", e.name, n, noise, half)
            ex = validation_example(s, n, noise, half, seed)
            with torch.no_grad():
                for name, kw in (("splines", {"use_features": False}), ("nkf", {}),
                                 ("nkf, weights = 1", {"use_weights": False})):
                    if name == "nkf, weights = 1" and not model.config.point_weights:
                        continue
                    f = example_field(net, ex, model.meta["lam_value"], ex.queries, **kw).numpy()
                    iou[name].append(field_iou(f, ex.queries, ex.occupancy))
                if model.config.point_weights:
                    xa, y = augment(ex.points, ex.normals, default_eps(len(ex.points)))
                    wstats.append(model.prepare(xa, y).weights)
        row = {"points": n, "noise": noise, "half": half, "meshes": len(hold)}
        row.update({k: float(np.mean(v)) for k, v in iou.items() if v})
        if wstats:
            w = np.concatenate(wstats)
            row.update(w_mean=float(w.mean()), w_p05=float(np.quantile(w, 0.05)), w_min=float(w.min()),
                       w_below_half=float((w < 0.5).mean()))
        rows.append(row)
        print(row, file=sys.stderr, flush=True)
    cols = [c for c in ("splines", "nkf", "nkf, weights = 1") if c in rows[0]]
    print("| input | " + " | ".join(f"IoU {c}" for c in cols) + " | mean w | 5 % quantile of w |")
    print("|---|" + "---:|" * (len(cols) + 2))
    for r in rows:
        label = f"{r['points']}{' half' if r['half'] else ''}, noise {r['noise']:g}"
        ws = f"{r['w_mean']:.3f} | {r['w_p05']:.3f}" if "w_mean" in r else "- | -"
        print(f"| {label} | " + " | ".join(f"{r[c]:.4f}" for c in cols) + f" | {ws} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
