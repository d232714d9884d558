"""``nkf train``: fit the feature network of the learned kernel on the mesh corpus.

One step draws ``batch`` training meshes and one augmented example of each
(:func:`nkf_model.train.examples.make_example`), fits the kernel to the example's constraints with the
features the network gives (:func:`nkf_model.train.differentiable_fit.fit_and_evaluate`, float64, gradients
through the solve) and minimises::

    BCE(sigmoid(-s f(q)), occupancy(q))  over near-surface and volume queries q
    + surface_weight * mean |f(p)|      over points p on the true surface

Runs are seeded: the examples of step ``k`` come from ``numpy.random.default_rng([seed, k])``, so a
run resumed from a checkpoint sees the same data as an uninterrupted one. Checkpoints (every
``checkpoint_every`` steps, and at the end) are safetensors files (no pickle) read back with
:func:`read_checkpoint`. The run writes into ``--out``:

* ``train.log``: a plain log (settings, losses, validation), appended across resumes;
* ``metrics.csv``: one row per step (loss) and per validation;
* ``curves.png``: training loss and validation IoU against steps (needs matplotlib, the ``train``
  extra);
* ``nkf.safetensors``: the weights with the best validation IoU, with the config in the metadata;
* ``checkpoint.safetensors``: the latest state for ``--resume`` (:func:`write_checkpoint`).

Validation uses meshes held out of the ``train`` split (``holdout`` of them, never trained on), so
the corpus's ``val`` split stays untouched for the benchmark. Each validation example is fitted
with the learned kernel and with the data-free kernel (features zero); the log shows both IoUs.
"""

from __future__ import annotations

import csv
import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from ..fit.augment import augment, default_eps
from ..kernel.feature_net import FeatureConfig
from .examples import AugmentSpec, CacheSpec, Example
from .procedural import ProceduralSpec

DEFAULT_CONFIG = Path("configs/nkf.toml")


@dataclass
class FitSpec:
    """Loss and solve settings."""

    lam: float = 1e-10
    sharpness: float = 2.0
    surface_weight: float = 1.0


@dataclass
class DataSpec:
    """Which meshes train and which validate.

    ``split = "train"``: the corpus ``train`` split, ``holdout`` of its meshes (by a hash of the
    name) kept for validation. ``split = "sources"``: :func:`corpus.source_split`: whole sources held
    out by kind (organic, mechanical, furniture, architecture); validation uses ``val_per_kind`` of
    each kind's meshes and reports each kind. ``p_procedural``: the share of examples made from
    procedural shapes (:mod:`nkf_model.train.procedural`) instead of corpus meshes.
    """

    split: str = "train"
    holdout: int = 24
    cache: str = ".train-cache"
    limit: int = 0  # use only this many training meshes (0: all); for tests and smoke runs
    val_per_kind: int = 6
    p_procedural: float = 0.0


@dataclass
class TrainSpec:
    seed: int = 0
    steps: int = 6000
    budget_minutes: float = 0.0  # also stop (and anneal the learning rate) by wall time; 0: no limit
    batch: int = 2
    lr: float = 1e-3
    warmup: int = 200
    final_lr_fraction: float = 0.05
    grad_clip: float = 1.0
    const_lr_scale: float = 20.0  # learning-rate multiplier of the constant feature's log(c^2)
    val_every: int = 500
    checkpoint_every: int = 250
    checkpoint_minutes: float = 0.0  # also checkpoint after this much wall time since the last one; 0: never
    threads: int = 2
    workers: int = 0  # 0: examples are made in the training process; 1: in one worker process ahead of it
    device: str = "auto"


@dataclass
class TrainConfig:
    model: FeatureConfig = field(default_factory=FeatureConfig)
    fit: FitSpec = field(default_factory=FitSpec)
    data: DataSpec = field(default_factory=DataSpec)
    augment: AugmentSpec = field(default_factory=AugmentSpec)
    cache: CacheSpec = field(default_factory=CacheSpec)
    train: TrainSpec = field(default_factory=TrainSpec)
    procedural: ProceduralSpec = field(default_factory=ProceduralSpec)
    validation: list = field(
        default_factory=lambda: [
            {"points": 1000, "noise": 0.0, "half": False},
            {"points": 1000, "noise": 0.005, "half": False},
            {"points": 300, "noise": 0.0, "half": False},
            {"points": 3000, "noise": 0.0, "half": True},
        ]
    )

    def to_dict(self) -> dict:
        return {
            "model": self.model.to_dict(),
            "fit": asdict(self.fit),
            "data": asdict(self.data),
            "augment": asdict(self.augment),
            "cache": asdict(self.cache),
            "train": asdict(self.train),
            "procedural": asdict(self.procedural),
            "validation": list(self.validation),
        }


CHECKPOINT = "checkpoint.safetensors"
_SCALARS = ("step", "best", "elapsed", "cpu", "config")


def write_checkpoint(path, state: dict) -> None:
    """Write a training state as safetensors (no pickle): ``state["model"]`` (a state dict) as
    ``model.<name>``, the optimizer's per-parameter tensors as ``optimizer.<index>.<name>``, and its
    param groups, its non-tensor per-parameter entries and the numbers ``step``, ``best``,
    ``elapsed``, ``cpu``, ``config`` as JSON in the metadata."""
    import torch
    from safetensors.torch import save_file

    tensors = {f"model.{k}": v.detach().contiguous() for k, v in state["model"].items()}
    opt = state["optimizer"]
    extra = {}
    for idx, entries in opt["state"].items():
        for name, v in entries.items():
            if isinstance(v, torch.Tensor):
                tensors[f"optimizer.{idx}.{name}"] = v.detach().contiguous()
            else:
                extra.setdefault(str(idx), {})[name] = v
    meta = {k: json.dumps(state[k]) for k in _SCALARS if k in state}
    meta["param_groups"] = json.dumps(opt["param_groups"])
    meta["optimizer_extra"] = json.dumps(extra)
    save_file(tensors, str(path), metadata=meta)


def read_checkpoint(path, device="cpu") -> dict:
    """The state :func:`write_checkpoint` wrote: ``model`` and ``optimizer`` state dicts as
    ``torch.nn.Module.load_state_dict`` and ``torch.optim.Optimizer.load_state_dict`` take them, and
    the numbers."""
    from safetensors import safe_open

    model, opt_state = {}, {}
    with safe_open(str(path), framework="pt", device=str(device)) as fh:
        meta = fh.metadata() or {}
        for key in fh.keys():
            kind, _, rest = key.partition(".")
            if kind == "model":
                model[rest] = fh.get_tensor(key)
            else:
                idx, _, name = rest.partition(".")
                opt_state.setdefault(int(idx), {})[name] = fh.get_tensor(key)
    for idx, entries in json.loads(meta.get("optimizer_extra", "{}")).items():
        opt_state.setdefault(int(idx), {}).update(entries)
    state = {k: json.loads(meta[k]) for k in _SCALARS if k in meta}
    state["model"] = model
    groups = [{k: tuple(v) if isinstance(v, list) and k != "params" else v for k, v in g.items()}
              for g in json.loads(meta.get("param_groups", "[]"))]  # JSON made the tuples (betas) lists
    state["optimizer"] = {"state": dict(sorted(opt_state.items())), "param_groups": groups}
    return state


def config_matches(stored: dict, current: dict) -> bool:
    """Whether a checkpoint's config (``stored``) is the same run as ``current``.

    Equal, except that a setting added to the code after the checkpoint was written (absent from
    ``stored``) is accepted when ``current`` has its default value, so a run spanning sessions
    survives new options that do not change it.
    """
    defaults = TrainConfig().to_dict()

    def same(a, b, d) -> bool:
        if isinstance(a, dict) and isinstance(b, dict):
            if set(a) - set(b):
                return False
            return all(
                same(a[k], b[k], d.get(k) if isinstance(d, dict) else None) if k in a
                else isinstance(d, dict) and k in d and json.dumps(b[k]) == json.dumps(d[k])
                for k in b
            )
        return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)

    return same(stored, current, defaults)


def _section(cls, d: dict, name: str):
    names = {f.name for f in fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ValueError(f"[{name}] has unknown keys: {', '.join(sorted(unknown))}")
    return cls(**d)


def load_config(path) -> TrainConfig:
    """Read a TOML training config; unknown sections or keys are errors."""
    with open(path, "rb") as fh:
        raw = tomllib.load(fh)
    known = {"model", "fit", "data", "augment", "cache", "train", "procedural", "validation"}
    unknown = set(raw) - known
    if unknown:
        raise ValueError(f"{path}: unknown sections {', '.join(sorted(unknown))}")
    cfg = TrainConfig(
        model=FeatureConfig.from_dict(raw.get("model", {})),
        fit=_section(FitSpec, raw.get("fit", {}), "fit"),
        data=_section(DataSpec, raw.get("data", {}), "data"),
        augment=_section(AugmentSpec, raw.get("augment", {}), "augment"),
        cache=_section(CacheSpec, raw.get("cache", {}), "cache"),
        train=_section(TrainSpec, raw.get("train", {}), "train"),
        procedural=_section(ProceduralSpec, raw.get("procedural", {}), "procedural"),
    )
    if isinstance(cfg.procedural.weights, list):
        cfg.procedural = ProceduralSpec(**{**asdict(cfg.procedural), "weights": tuple(cfg.procedural.weights)})
    if cfg.data.split not in ("train", "sources"):
        raise ValueError(f"[data] split must be 'train' or 'sources', not {cfg.data.split!r}")
    if cfg.train.workers not in (0, 1):
        raise ValueError("[train] workers must be 0 or 1")
    if "validation" in raw:
        cfg.validation = list(raw["validation"])
    return cfg


# --------------------------------------------------------------------------------------------
# The differentiable forward pass of one example


def example_field(net, ex: Example, lam: float, queries: np.ndarray, *, use_features: bool = True, device="cpu",
                  use_weights: bool = True):
    """Field values (Q,) float64 tensor at ``queries`` (Q, 3) after fitting the example's input.

    With ``use_features=False`` the features are zero and the weights one: the Neural Splines fit.
    With ``use_weights=False`` the learned features are used but every per-point weight is one.
    """
    import torch

    from .differentiable_fit import fit_and_evaluate

    n = len(ex.points)
    xa, y = augment(ex.points, ex.normals, default_eps(n))
    xa_t = torch.as_tensor(xa, dtype=torch.float64, device=device)
    q_t = torch.as_tensor(queries, dtype=torch.float64, device=device)
    y_t = torch.as_tensor(y, dtype=torch.float64, device=device)
    one_a = torch.ones(len(xa), 1, dtype=torch.float64, device=device)
    one_q = torch.ones(len(queries), 1, dtype=torch.float64, device=device)
    if use_features:
        grid = net.grid_features(xa_t.float(), y_t.float())
        phi_a, w = net.point_features(grid, xa_t.float())
        phi_q, _ = net.point_features(grid, q_t.float())
        a = torch.cat([xa_t, phi_a.double(), one_a], dim=1)
        q = torch.cat([q_t, phi_q.double(), one_q], dim=1)
        if w is not None and use_weights:
            w = w.double()
            a = a * w[:, None]
            y_t = y_t * w
    else:
        a = torch.cat([xa_t, one_a], dim=1)
        q = torch.cat([q_t, one_q], dim=1)
    return fit_and_evaluate(a, y_t, lam, q)


def example_loss(net, ex: Example, fit: FitSpec, device="cpu"):
    """Loss of one example (scalar tensor) and its parts (floats)."""
    import torch
    import torch.nn.functional as F

    q = np.concatenate([ex.queries, ex.surface])
    f = example_field(net, ex, fit.lam, q, device=device)
    nq = len(ex.queries)
    occ = torch.as_tensor(ex.occupancy, dtype=torch.float64, device=device)
    bce = F.binary_cross_entropy_with_logits(-fit.sharpness * f[:nq], occ)
    surf = f[nq:].abs().mean() if len(ex.surface) else torch.zeros((), dtype=torch.float64, device=device)
    loss = bce + fit.surface_weight * surf
    return loss, {"bce": float(bce.detach()), "surface": float(surf.detach())}


def field_iou(f: np.ndarray, queries: np.ndarray, occupancy: np.ndarray) -> float:
    """IoU of ``f < 0`` (inside the evaluation grid box only) against the true occupancy."""
    from ..points.normalise import GRID_HALF

    pred = (f < 0) & np.all(np.abs(queries) <= GRID_HALF, axis=1)
    true = occupancy > 0.5
    union = np.logical_or(pred, true).sum()
    return float(np.logical_and(pred, true).sum() / union) if union else 1.0


# --------------------------------------------------------------------------------------------
# Training


class Trainer:
    """Everything of one training run; see the module docstring."""

    def __init__(self, cfg: TrainConfig, out: Path, *, progress: bool = True, log_to_stderr: bool = True):
        import torch

        from ..kernel.feature_net import FeatureNet
        from . import corpus

        self.cfg = cfg
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.progress = progress
        self.log_to_stderr = log_to_stderr
        torch.set_num_threads(max(1, cfg.train.threads))
        try:
            import numba

            numba.set_num_threads(max(1, min(cfg.train.threads, numba.config.NUMBA_NUM_THREADS)))
        except ImportError:  # pragma: no cover - numba is a dependency
            pass
        dev = cfg.train.device
        if dev == "auto":
            dev = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = dev
        torch.manual_seed(cfg.train.seed)
        self.net = FeatureNet(cfg.model).to(dev)
        const = [p for n, p in self.net.named_parameters() if n == "log_c2"]
        rest = [p for n, p in self.net.named_parameters() if n != "log_c2"]
        groups = [{"params": rest, "scale": 1.0}]
        if const:
            groups.append({"params": const, "scale": cfg.train.const_lr_scale})
        self.opt = torch.optim.Adam(groups, lr=cfg.train.lr)
        self.step = 0
        self.best = -1.0
        self.elapsed = 0.0  # seconds of training over all sessions of this run
        self.cpu = 0.0  # CPU seconds of training (this process and the data worker) over all sessions
        self.worker = None

        # holdout_kinds[i]: the held-out kind of holdout_entries[i] (None with split = "train")
        if cfg.data.split == "sources":
            self.train_entries, held = corpus.source_split()
            sub = corpus.validation_subset(held, cfg.data.val_per_kind)
            self.holdout_entries = [e for k in sub for e in sub[k]]
            self.holdout_kinds = [k for k in sub for _ in sub[k]]
        else:
            entries = [e for e in corpus.manifest() if e.split == cfg.data.split]
            entries.sort(key=lambda e: corpus.stable_seed("holdout", e.name))
            self.holdout_entries = entries[: cfg.data.holdout]
            self.holdout_kinds = [None] * len(self.holdout_entries)
            self.train_entries = sorted(entries[cfg.data.holdout :], key=lambda e: e.name)
        if cfg.data.limit:
            self.train_entries = self.train_entries[: cfg.data.limit]
            keep = max(1, min(len(self.holdout_entries), cfg.data.holdout if cfg.data.split == "train" else 4,
                              cfg.data.limit))
            self.holdout_entries = self.holdout_entries[:keep]
            self.holdout_kinds = self.holdout_kinds[:keep]

    # -- logging -------------------------------------------------------------------------
    def log(self, msg: str) -> None:
        line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}"
        with open(self.out / "train.log", "a") as fh:
            fh.write(line + "\n")
        if self.log_to_stderr and not self.progress:
            print(line, file=sys.stderr, flush=True)

    def _csv(self, row: dict) -> None:
        path = self.out / "metrics.csv"
        cols = ["kind", "step", "elapsed_s", "cpu_s", "loss", "bce", "surface", "lr", "skipped", "config", "iou_nkf",
                "iou_splines"]
        new = not path.exists()
        with open(path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols)
            if new:
                w.writeheader()
            w.writerow({c: row.get(c, "") for c in cols})

    # -- data ----------------------------------------------------------------------------
    def load_data(self) -> None:
        """Held-out samples and validation inputs; the training data source (see :mod:`data_worker`).

        On the CPU, training meshes' samples are made when first drawn (by the data worker with
        ``workers = 1``); on a GPU they are all made up front, where winding numbers are fast.
        """
        from . import corpus
        from .data_worker import DataSource, source_kwargs
        from .examples import build_cache, validation_example

        cache = Path(self.cfg.data.cache)
        self.log(f"cache: {cache} ({len(self.train_entries)} training meshes, {len(self.holdout_entries)} held out"
                 + (f", procedural shapes {self.cfg.data.p_procedural:.0%} of examples" if self.cfg.data.p_procedural
                    else "") + ")")
        wn_device = self.device if self.device != "cpu" else None
        if wn_device is not None:
            build_cache(self.train_entries, cache, self.cfg.cache, progress=self.progress, device=wn_device)
        self.holdout_samples = build_cache(self.holdout_entries, cache, self.cfg.cache, progress=self.progress,
                                           device=wn_device)
        self.source = None if self.cfg.train.workers else DataSource(**source_kwargs(self.train_entries, self.cfg))

        self.val_examples = []
        for e, kind, s in zip(self.holdout_entries, self.holdout_kinds, self.holdout_samples):
            for vc in self.cfg.validation:
                seed = corpus.stable_seed("holdout-val", e.name, vc["points"], vc["noise"], vc["half"])
                ex = validation_example(s, int(vc["points"]), float(vc["noise"]), bool(vc["half"]), seed)
                name = self._vc_name(vc)
                self.val_examples.append((f"{kind}/{name}" if kind else name, ex))

    def next_batch(self) -> list:
        """The examples of the current step (from the worker, or made here)."""
        if self.worker is not None:
            return self.worker.get(self.step)
        return self.source.batch_at(self.step)

    def worker_cpu(self) -> float:
        return self.worker.cpu_seconds if self.worker is not None else 0.0

    @staticmethod
    def _vc_name(vc) -> str:
        return f"{vc['points']}{'-half' if vc['half'] else ''}-noise{vc['noise']:g}"

    # -- checkpoints ---------------------------------------------------------------------
    def checkpoint_path(self) -> Path:
        return self.out / CHECKPOINT

    def save_checkpoint(self) -> None:
        tmp = self.checkpoint_path().with_suffix(".tmp")
        write_checkpoint(tmp, {
            "model": self.net.state_dict(),
            "optimizer": self.opt.state_dict(),
            "step": self.step,
            "best": self.best,
            "elapsed": self.elapsed,
            "cpu": self.cpu,
            "config": json.dumps(self.cfg.to_dict(), sort_keys=True),
        })
        tmp.replace(self.checkpoint_path())

    def load_checkpoint(self) -> bool:
        path = self.checkpoint_path()
        if not path.exists():
            return False
        state = read_checkpoint(path, device=self.device)
        if not config_matches(json.loads(state["config"]), self.cfg.to_dict()):
            raise ValueError(
                f"{path} was written with a different config; start a new --out folder or restore the config"
            )
        self.net.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        self.best = float(state["best"])
        self.elapsed = float(state["elapsed"])
        self.cpu = float(state.get("cpu", 0.0))
        self._drop_metrics_after(self.step)
        return True

    def _drop_metrics_after(self, step: int) -> None:
        """Remove ``metrics.csv`` rows of steps after ``step``: a session that ended between two
        checkpoints logged steps that the resumed run does again."""
        path = self.out / "metrics.csv"
        if not path.exists():
            return
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        if not rows:
            return
        col = rows[0].index("step") if "step" in rows[0] else None
        if col is None:
            return
        kept = [rows[0]] + [r for r in rows[1:] if not (r[col].isdigit() and int(r[col]) > step)]
        if len(kept) < len(rows):
            with open(path, "w", newline="") as fh:
                csv.writer(fh).writerows(kept)
            self.log(f"resume: dropped {len(rows) - len(kept)} metrics rows after step {step}")

    # -- schedule ------------------------------------------------------------------------
    def progress_fraction(self) -> float:
        """How far the run is: the larger of steps done and wall time used, as fractions."""
        t = self.cfg.train
        p = self.step / max(1, t.steps)
        if t.budget_minutes > 0:
            p = max(p, self.elapsed / (60.0 * t.budget_minutes))
        return p

    def lr_at(self, step: int) -> float:
        t = self.cfg.train
        if step < t.warmup:
            return t.lr * (step + 1) / t.warmup
        p = self.progress_fraction()
        lo = t.final_lr_fraction
        return t.lr * (lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * min(1.0, p))))

    # -- one step ------------------------------------------------------------------------
    def train_step(self, examples: list | None = None) -> dict:
        """One optimisation step on ``examples`` (default: this step's batch)."""
        import torch

        from .differentiable_fit import IllConditionedError

        examples = self.next_batch() if examples is None else examples
        lr = self.lr_at(self.step)
        for gparam in self.opt.param_groups:
            gparam["lr"] = lr * gparam.get("scale", 1.0)
        self.net.train()
        self.opt.zero_grad(set_to_none=True)
        b = self.cfg.train.batch
        parts = {"loss": 0.0, "bce": 0.0, "surface": 0.0}
        used = 0
        skipped = 0
        for ex in examples:
            try:
                loss, p = example_loss(self.net, ex, self.cfg.fit, device=self.device)
                if not torch.isfinite(loss):
                    raise FloatingPointError("non-finite loss")
                (loss / b).backward()
            except (IllConditionedError, FloatingPointError) as exc:
                skipped += 1
                self.log(f"step {self.step}: skipped an example ({type(exc).__name__}: {exc})")
                continue
            used += 1
            parts["loss"] += float(loss.detach())
            parts["bce"] += p["bce"]
            parts["surface"] += p["surface"]
        ok = used > 0
        if ok:
            grads = [p.grad for p in self.net.parameters() if p.grad is not None]
            finite = all(bool(torch.isfinite(g).all()) for g in grads)
            if finite:
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg.train.grad_clip)
                self.opt.step()
            else:
                skipped += used
                self.log(f"step {self.step}: non-finite gradient, update skipped")
        out = {k: v / max(1, used) for k, v in parts.items()}
        out.update(lr=lr, skipped=skipped)
        return out

    # -- validation ----------------------------------------------------------------------
    def validate(self, baseline: bool = False) -> dict:
        """Mean IoU per validation setting (learned kernel, or the data-free one)."""
        import torch

        self.net.eval()
        per: dict = {}
        with torch.no_grad():
            for name, ex in self.val_examples:
                f = example_field(self.net, ex, self.cfg.fit.lam, ex.queries, use_features=not baseline,
                                  device=self.device)
                per.setdefault(name, []).append(field_iou(f.cpu().numpy(), ex.queries, ex.occupancy))
        return {k: float(np.mean(v)) for k, v in per.items()}

    # -- the loop ------------------------------------------------------------------------
    def commit(self) -> bool:
        """Commit the run folder (only its paths) to the git repository that holds it.

        For runs that must survive the end of a session: ``git add`` then ``git commit -- OUT``, which
        commits nothing else that is staged. Waits up to a minute while another git command holds the
        index lock; a failure is logged, never raised (the next checkpoint tries again).
        """
        import subprocess

        out = self.out.resolve()
        try:
            top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=out, capture_output=True, text=True,
                                 check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError) as exc:
            self.log(f"commit: {out} is not in a git repository ({exc})")
            return False
        rel = os.path.relpath(out, top)
        best = f"best held-out mean IoU {self.best:.4f}" if self.best >= 0 else "not validated yet"
        msg = f"Training run {rel}: step {self.step}, {self.cpu / 3600:.2f} CPU hours, {best} (checkpoint, log, curves)"
        for _ in range(12):
            if (Path(top) / ".git" / "index.lock").exists():
                time.sleep(5)
                continue
            a = subprocess.run(["git", "add", "--", rel], cwd=top, capture_output=True, text=True)
            c = subprocess.run(["git", "commit", "-q", "-m", msg, "--", rel], cwd=top, capture_output=True, text=True)
            if a.returncode == 0 and c.returncode == 0:
                self.log(f"commit: step {self.step} committed ({rel})")
                return True
            err = (a.stderr + c.stderr + c.stdout).strip()
            if "index.lock" not in err:
                self.log(f"commit failed: {err[:300]}")
                return False
            time.sleep(5)
        self.log("commit: the git index stayed locked; trying again at the next checkpoint")
        return False

    def run(self, resume: bool = False, max_steps: int | None = None, stop_after_s: float | None = None,
            commit_every_s: float | None = None) -> dict:
        """Train until the config's steps or budget, ``max_steps`` more steps, or ``stop_after_s``
        seconds of this session (then validate and checkpoint, so that ``resume=True`` continues).

        ``commit_every_s``: also commit the run folder (:meth:`commit`) after the first checkpoint
        that comes this many seconds of wall time after the last commit, and at the end."""
        from tqdm import tqdm

        from ..kernel.weights import save_weights
        from .data_worker import BatchWorker, source_kwargs

        t = self.cfg.train
        resumed = resume and self.load_checkpoint()
        self.log(
            (f"resumed at step {self.step}" if resumed else "new run")
            + f"; device {self.device}, {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} cores, torch threads {t.threads}"
        )
        if not resumed:
            self.log("config " + json.dumps(self.cfg.to_dict(), sort_keys=True))
        self.load_data()
        if t.workers:
            self.worker = BatchWorker(source_kwargs(self.train_entries, self.cfg), start=self.step)
        base_path = self.out / "baseline.json"
        if base_path.exists():
            baseline = json.loads(base_path.read_text())
        else:
            baseline = self.validate(baseline=True)
            base_path.write_text(json.dumps(baseline, indent=1))
            for k, v in baseline.items():
                self._csv({"kind": "val", "step": 0, "config": k, "iou_splines": v})
        self.log("neural splines on the held-out meshes: " + ", ".join(f"{k} {v:.4f}" for k, v in baseline.items()))
        self.log(f"run so far: step {self.step}, {self.elapsed / 60:.1f} min wall, {self.cpu / 3600:.3f} CPU hours")
        end = t.steps if max_steps is None else min(t.steps, self.step + max_steps)
        t_wall = time.perf_counter()
        deadline = None if stop_after_s is None else t_wall + stop_after_s
        bar = tqdm(total=t.steps, initial=self.step, disable=not self.progress, desc="train", unit="step",
                   dynamic_ncols=True)
        window: list = []
        last_val = None
        c_main = time.process_time()
        c_work = self.worker_cpu()
        last_ckpt = last_commit = time.perf_counter()

        def account():
            nonlocal c_main, c_work
            cm, cw = time.process_time(), self.worker_cpu()
            self.cpu += (cm - c_main) + (cw - c_work)
            c_main, c_work = cm, cw

        try:
            while self.step < end and self.progress_fraction() < 1.0 and not (
                    deadline is not None and time.perf_counter() >= deadline):
                r = self.train_step()
                now = time.perf_counter()
                self.elapsed += now - t_wall  # wall time, validation and checkpoints included
                t_wall = now
                account()
                self.step += 1
                out_of_time = deadline is not None and now >= deadline
                last = self.step >= end or self.progress_fraction() >= 1.0 or out_of_time
                window.append(r["loss"])
                window = window[-50:]
                self._csv({"kind": "train", "step": self.step, "elapsed_s": f"{self.elapsed:.1f}",
                           "cpu_s": f"{self.cpu:.1f}", "loss": f"{r['loss']:.5f}", "bce": f"{r['bce']:.5f}",
                           "surface": f"{r['surface']:.5f}",
                           "lr": f"{r['lr']:.3g}", "skipped": r["skipped"]})
                bar.update(1)
                bar.set_postfix(loss=f"{np.mean(window):.4f}", val=last_val or "-")
                if self.step % 50 == 0:
                    self.log(f"step {self.step}: loss {np.mean(window):.4f} (mean of last {len(window)}), "
                             f"lr {r['lr']:.3g}, constant feature {self.net.constant_feature():.3f}, "
                             f"{self.elapsed / 60:.1f} min, {self.cpu / 3600:.3f} CPU h")
                if self.step % t.val_every == 0 or last:
                    tv = time.perf_counter()
                    val = self.validate()
                    mean = float(np.mean(list(val.values())))
                    for k, v in val.items():
                        self._csv({"kind": "val", "step": self.step, "elapsed_s": f"{self.elapsed:.1f}",
                                   "cpu_s": f"{self.cpu:.1f}", "config": k, "iou_nkf": f"{v:.5f}",
                                   "iou_splines": f"{baseline[k]:.5f}"})
                    self.log(f"step {self.step}: validation IoU " + ", ".join(
                        f"{k} {v:.4f} (splines {baseline[k]:.4f})" for k, v in val.items())
                        + f"; mean {mean:.4f} vs {np.mean(list(baseline.values())):.4f} "
                        f"[{time.perf_counter() - tv:.0f} s]")
                    kinds = sorted({k.split("/")[0] for k in val if "/" in k})
                    if kinds:
                        self.log(f"step {self.step}: held-out mean IoU by kind: " + ", ".join(
                            f"{kd} {np.mean([v for k, v in val.items() if k.startswith(kd + '/')]):.4f} (splines "
                            f"{np.mean([v for k, v in baseline.items() if k.startswith(kd + '/')]):.4f})"
                            for kd in kinds))
                    last_val = f"{mean:.4f}"
                    if mean > self.best:
                        self.best = mean
                        save_weights(self.out / "nkf.safetensors", self.net, lam=self.cfg.fit.lam,
                                     training=self.summary(val, baseline))
                        self.log(f"step {self.step}: best so far, wrote {self.out / 'nkf.safetensors'}")
                timed = t.checkpoint_minutes > 0 and time.perf_counter() - last_ckpt >= 60.0 * t.checkpoint_minutes
                if self.step % t.checkpoint_every == 0 or last or timed:
                    now = time.perf_counter()
                    self.elapsed += now - t_wall
                    t_wall = now
                    account()
                    self.save_checkpoint()
                    last_ckpt = time.perf_counter()
                    if commit_every_s is not None and (last or last_ckpt - last_commit >= commit_every_s):
                        self._plot()
                        self.commit()
                        last_commit = time.perf_counter()
                now = time.perf_counter()
                self.elapsed += now - t_wall
                t_wall = now
                account()
        finally:
            bar.close()
            if self.worker is not None:
                self.worker.close()
                self.worker = None
        self._plot()
        self.log(f"stopped at step {self.step} after {self.elapsed / 60:.1f} min of training "
                 f"({self.cpu / 3600:.3f} CPU hours); best mean IoU {self.best:.4f}")
        return {"step": self.step, "best": self.best, "elapsed_s": self.elapsed, "cpu_s": self.cpu}

    def _plot(self) -> None:
        try:
            plot_curves(self.out)
        except ImportError:
            self.log("matplotlib is not installed (the 'train' extra); no curves.png")

    def summary(self, val: dict, baseline: dict) -> dict:
        import torch

        return {
            "step": self.step,
            "elapsed_s": round(self.elapsed, 1),
            "cpu_s": round(self.cpu, 1),
            "device": self.device,
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}",
            "holdout_iou": {k: round(v, 5) for k, v in val.items()},
            "holdout_iou_splines": {k: round(v, 5) for k, v in baseline.items()},
            "config": self.cfg.to_dict(),
        }


def plot_curves(out: Path) -> Path:
    """Draw ``curves.png`` (training loss and validation IoU) from ``metrics.csv`` in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(Path(out) / "metrics.csv")))
    tr = [(int(r["step"]), float(r["loss"])) for r in rows if r["kind"] == "train" and r["loss"]]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    if tr:
        s, l_ = np.array(tr).T
        k = min(100, max(1, len(l_) // 20))
        smooth = np.convolve(l_, np.ones(k) / k, mode="valid")
        ax1.plot(s, l_, color="0.8", lw=0.5, label="per step")
        ax1.plot(s[k - 1 :], smooth, color="C0", label=f"mean of {k}")
        ax1.set_yscale("log")
    ax1.set_xlabel("step")
    ax1.set_ylabel("training loss")
    ax1.legend()
    val = [r for r in rows if r["kind"] == "val"]
    if any("/" in r["config"] for r in val):
        # held-out sources: one curve per kind (the mean over its validation settings), and the mean
        for r in val:
            r["config"] = r["config"].split("/")[0]
        val += [dict(r, config="mean of kinds") for r in val]
    names = sorted({r["config"] for r in val})
    for i, name in enumerate(names):
        by_step: dict = {}
        base: list = []
        for r in val:
            if r["config"] == name and r["iou_nkf"]:
                by_step.setdefault(int(r["step"]), []).append(float(r["iou_nkf"]))
            if r["config"] == name and r["iou_splines"] and int(r["step"]) == 0:
                base.append(float(r["iou_splines"]))
        if not base:
            base = [float(r["iou_splines"]) for r in val if r["config"] == name and r["iou_splines"]]
        if by_step:
            s = sorted(by_step)
            ax2.plot(s, [np.mean(by_step[k]) for k in s], "o-", color=f"C{i}", label=f"nkf {name}")
        if base:
            ax2.axhline(np.mean(base), color=f"C{i}", ls="--", lw=0.8)
    ax2.set_xlabel("step")
    ax2.set_ylabel("held-out IoU (dashed: splines)")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    path = Path(out) / "curves.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(args) -> int:
    """Entry point of ``nkf train`` (arguments parsed by :mod:`nkf_model.cli`)."""
    from ..errors import NKFInputError

    try:
        cfg = load_config(args.config)
    except FileNotFoundError:
        raise NKFInputError(f"training config {args.config} does not exist") from None
    except (OSError, ValueError, TypeError) as exc:  # tomllib.TOMLDecodeError is a ValueError
        raise NKFInputError(f"training config {args.config}: {exc}") from None
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    if (out / CHECKPOINT).exists() and not args.resume:
        raise NKFInputError(f"{out} already holds a run; pass --resume to continue it, or choose another --out")
    if args.resume and not (out / CHECKPOINT).exists():
        raise NKFInputError(f"--resume: {out} holds no {CHECKPOINT} to resume from")
    tr = Trainer(cfg, out, progress=not args.quiet)
    try:
        stop = None if getattr(args, "stop_after", None) is None else 60.0 * args.stop_after
        every = getattr(args, "commit_every", None)
        res = tr.run(resume=args.resume, max_steps=args.max_steps, stop_after_s=stop,
                     commit_every_s=None if every is None else 60.0 * every)
    except ValueError as exc:  # a checkpoint written with another config
        raise NKFInputError(str(exc)) from None
    print(f"{out / 'nkf.safetensors'}: best held-out mean IoU {res['best']:.4f} after {res['step']} steps "
          f"({res['elapsed_s'] / 60:.1f} min)")
    return 0
