"""The shared mesh corpus (``../shared/data/meshes``): listing, loading and sampling inputs.

The corpus is outside the repository. Its location comes from the ``NKF_MESHES`` environment
variable, else ``../shared/data/meshes`` next to the repository checkout.
"""

from __future__ import annotations

import csv
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.files import read_mesh
from .metrics import sample_surface


def corpus_dir() -> Path:
    """Folder of the mesh corpus (it holds ``MANIFEST.csv``)."""
    env = os.environ.get("NKF_MESHES")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[2]
    return repo.parent / "shared" / "data" / "meshes"


@dataclass
class CorpusMesh:
    """One row of ``MANIFEST.csv``."""

    file: str
    split: str
    watertight: bool
    category: str
    license: str
    source_repo: str
    source_path: str

    @property
    def name(self) -> str:
        return self.file.rsplit(".", 1)[0]

    @property
    def source(self) -> str:
        """The asset pack or repository the mesh comes from (see :func:`source_of`)."""
        return source_of(self.source_repo, self.source_path)


# --------------------------------------------------------------------------------------------
# Splitting by source
#
# The corpus's own ``split`` column mixes every source into ``train`` and ``val``, so a validation
# on ``val`` measures interpolation between meshes of packs the kernel trained on. The learned
# kernel is meant to generalise to objects unlike its training data, so whole sources, chosen to
# differ in kind, are held out: they are used for checkpoint selection and the gate only, never for
# training (both of their ``split`` rows).

#: The asset-pack collection whose packs count as separate sources (by their folder).
PACK_REPO = "beep2bleep/FreeAssetsByKenneyNLandQuaternius"

#: Held-out sources by kind. Each is the whole of its pack or repository.
HELDOUT_SOURCES: dict[str, tuple[str, ...]] = {
    # Quaternius' animals and people: organic bodies with limbs, necks, ears and tails.
    "organic": ("quaternius/Characters and Animals",),
    # trimesh's test models: machined CAD parts (plates with holes, brackets, gears, pins, rods).
    "mechanical": ("mikedh/trimesh",),
    # Kenney's furniture pack: chairs, tables, shelves, lamps, beds (thin plates and legs).
    "furniture": ("kenney/Furniture Pack",),
    # Kenney's castle kit and city builder: walls, towers, gates, houses.
    "architecture": ("kenney/Castle Kit", "KenneyNL/Starter-Kit-City-Builder"),
}


def source_of(source_repo: str, source_path: str) -> str:
    """The source of a corpus mesh: its repository, or for the Kenney/Quaternius collection its
    asset pack (``"kenney/Furniture Pack"``, ``"quaternius/Characters and Animals"``)."""
    if source_repo != PACK_REPO:
        return source_repo
    parts = source_path.split("/")
    if len(parts) < 2:
        raise ValueError(f"{source_repo}: {source_path!r} names no asset pack")
    artist = "kenney" if parts[0].startswith("Kenny") else "quaternius" if "Quaternius" in parts[0] else None
    if artist is None:
        raise ValueError(f"{source_repo}: unknown collection folder {parts[0]!r}")
    pack = parts[1].split(" (")[0]  # "Castle Kit (1.0)" -> "Castle Kit"
    return f"{artist}/{pack}"


def heldout_kind(entry: CorpusMesh) -> str | None:
    """The kind (``HELDOUT_SOURCES`` key) whose held-out sources include ``entry``, else None."""
    for kind, sources in HELDOUT_SOURCES.items():
        if entry.source in sources:
            return kind
    return None


def source_split(entries: list[CorpusMesh] | None = None) -> tuple[list[CorpusMesh], dict[str, list[CorpusMesh]]]:
    """The training meshes and the held-out meshes by kind.

    Training: the corpus ``train`` split minus every held-out source (the ``val`` rows of the other
    sources stay out too, for the in-distribution benchmark of docs/benchmarks.md). Held out: every
    row (``train`` and ``val``) of the held-out sources. Both sorted by name, so the split does not
    depend on the manifest's order.
    """
    entries = manifest() if entries is None else entries
    train = sorted((e for e in entries if e.split == "train" and heldout_kind(e) is None), key=lambda e: e.name)
    held: dict[str, list[CorpusMesh]] = {k: [] for k in HELDOUT_SOURCES}
    for e in entries:
        kind = heldout_kind(e)
        if kind is not None:
            held[kind].append(e)
    for k in held:
        held[k].sort(key=lambda e: e.name)
    return train, held


def validation_subset(held: dict[str, list[CorpusMesh]], per_kind: int) -> dict[str, list[CorpusMesh]]:
    """A fixed subset of at most ``per_kind`` held-out meshes per kind, for validation during training
    (chosen by a hash of the name, so it does not depend on the order or on the other meshes)."""
    return {
        k: sorted(sorted(v, key=lambda e: stable_seed("val-subset", e.name))[:per_kind], key=lambda e: e.name)
        for k, v in held.items()
    }


def manifest(root: Path | None = None) -> list[CorpusMesh]:
    """All rows of the corpus manifest."""
    root = root or corpus_dir()
    with open(root / "MANIFEST.csv", newline="") as fh:
        return [
            CorpusMesh(
                file=r["file"],
                split=r["split"],
                watertight=r["watertight"] == "True",
                category=r["category"],
                license=r["source_license"],
                source_repo=r["source_repo"],
                source_path=r["source_path"],
            )
            for r in csv.DictReader(fh)
        ]


def load(entry: CorpusMesh, root: Path | None = None):
    """Vertices (V, 3) float64 and faces (F, 3) int64 of a corpus mesh (unit box)."""
    return read_mesh((root or corpus_dir()) / entry.file)


def stable_seed(*parts) -> int:
    """A seed that depends only on ``parts`` (not on Python's hash randomisation)."""
    h = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(h[:4], "little")


def sample_input(vertices, faces, n_points: int, noise: float, seed: int):
    """Oriented input points as a scanner would give them: ``n_points`` uniform surface samples,
    positions perturbed by Gaussian noise of standard deviation ``noise`` (unit-box units), normals
    of the true surface."""
    rng = np.random.default_rng(seed)
    pts, nrm = sample_surface(vertices, faces, n_points, rng)
    if noise > 0:
        pts = pts + rng.normal(scale=noise, size=pts.shape)
    return pts, nrm
