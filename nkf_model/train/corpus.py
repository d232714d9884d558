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
