"""Write the data-driven parts of ``nkf_model/weights/MODEL_CARD.md`` from a weights file.

    python scripts/make_model_card.py --weights nkf_model/weights/nkf_default.safetensors \
        --run runs/nkf --notes docs/nkf.md --bench docs/nkf-benchmark.md \
        --ablation docs/nkf-ablation.md --config configs/nkf.toml --out nkf_model/weights/MODEL_CARD.md

The card gets: the file and its checksum, the network's config, how and how long it was trained
(from the weights' metadata and the run's log), the held-out validation table, the hand-written
notes (design choices and their reasons), the benchmark tables, and the training data's sources and
licenses from the corpus's MANIFEST.csv, crediting every CC-BY item by name.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nkf_model.kernel.weights import read_weights  # noqa: E402
from nkf_model.train import corpus  # noqa: E402


def _read(path):
    return Path(path).read_text().strip() if path and Path(path).exists() else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", required=True)
    ap.add_argument("--run", default=None, help="the run folder (train.log) that made the weights")
    ap.add_argument("--notes", default=None)
    ap.add_argument("--bench", default=None)
    ap.add_argument("--ablation", default=None)
    ap.add_argument("--out", required=True)
    ap.add_argument("--config", default="configs/nkf.toml", help="the config file the run was started with")
    args = ap.parse_args(argv)

    path = Path(args.weights)
    tensors, meta, config = read_weights(path)
    training = json.loads(meta["training"])
    cfg = training.get("config", {})
    params = sum(t.numel() for t in tensors.values())
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    L = [
        "# Model card: `nkf_default.safetensors`",
        "",
        "The default weights of the learned kernel (`method=\"nkf\"`): the feature network phi of Neural",
        "Kernel Fields (Williams et al., CVPR 2022), trained on the `train` split of the project's mesh corpus.",
        "",
        "| | |",
        "|---|---|",
        f"| file | `nkf_model/weights/{path.name}` ({path.stat().st_size / 2**20:.2f} MiB, safetensors, no pickle) |",
        f"| sha256 | `{sha}` |",
        f"| parameters | {params:,} (float32) |",
        f"| format | `{meta['format']}` version {meta['format_version']}; the config below is in the file's metadata |",
        f"| lambda | {float(meta['lam']):g} per constraint (the default `lam` of `reconstruct`) |",
        f"| trained | {training.get('step', '?')} steps, {training.get('elapsed_s', 0) / 3600:.2f} h wall time, "
        f"{training.get('machine', '?')}, device {training.get('device', '?')} |",
        "",
        "## Network (from the file's metadata)",
        "",
        "| setting | value |",
        "|---|---|",
    ]
    L += [f"| `{k}` | {v} |" for k, v in config.to_dict().items()]
    L += ["", "## Training config", "", f"From `{args.config}` as the run read it:", "", "```json",
          json.dumps({k: v for k, v in cfg.items() if k != "model"}, indent=1, sort_keys=True), "```", ""]
    hold = training.get("holdout_iou", {})
    base = training.get("holdout_iou_splines", {})
    if hold:
        L += ["## Validation on held-out training-split meshes", "",
              f"Mean IoU of the sign of the fitted field at 8,192 uniform points of each mesh's box, on the "
              f"{cfg.get('data', {}).get('holdout', '?')} meshes of the train split that training never used "
              f"(the selection of the best step used only these):", "",
              "| input | nkf | splines |", "|---|---:|---:|"]
        L += [f"| {k} | {hold[k]:.4f} | {base.get(k, float('nan')):.4f} |" for k in hold]
        L += [""]
    notes = _read(args.notes)
    if notes:
        L += [notes, ""]
    ab = _read(args.ablation)
    if ab:
        L += [ab, ""]
    bench = _read(args.bench)
    if bench:
        L += [bench, ""]
    if args.run and (Path(args.run) / "train.log").exists():
        log = (Path(args.run) / "train.log").read_text().splitlines()
        keep = [ln for ln in log if "validation IoU" in ln or "best so far" in ln or "stopped" in ln
                or "resumed" in ln or "new run" in ln]
        L += ["## Training log (validation lines)", "", "```", *keep, "```", ""]

    rows = [e for e in corpus.manifest() if e.split == cfg.get("data", {}).get("split", "train")]
    by_src = collections.Counter((e.source_repo, e.license) for e in rows)
    L += ["## Training data: sources and licenses", "",
          f"{len(rows)} meshes of the `train` split of the shared corpus (`../shared/data/meshes`, "
          "MANIFEST.csv); the `val` split was used only for the benchmark. Counts per source and license:", "",
          "| source repository | license (from MANIFEST.csv) | meshes |", "|---|---|---:|"]
    L += [f"| {src} | {lic} | {c} |" for (src, lic), c in sorted(by_src.items(), key=lambda kv: (-kv[1], kv[0]))]
    ccby = [e for e in rows if "CC-BY" in e.license]
    L += ["", "### CC-BY items (attribution)", "",
          "These training meshes are licensed CC-BY; the weights were trained on them:", "",
          "| file | source repository | path in the source | license |", "|---|---|---|---|"]
    L += [f"| `{e.file}` | {e.source_repo} | `{e.source_path}` | {e.license} |" for e in ccby]
    L += ["", "Robot meshes from bullet3 may also carry their vendors' terms (see MANIFEST.csv).", ""]
    Path(args.out).write_text("\n".join(L) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
