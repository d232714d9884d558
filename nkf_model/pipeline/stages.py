"""The stages of a reconstruction, in order: the one list that progress reports, the command line
and the Blender add-on share. Standard library only.

Each stage has the name :func:`nkf_model.reconstruct` reports in ``progress(fraction, stage)`` and
in ``stats["timings"]``, a label for a user interface, and its share of the wall time in a typical
run (used to map each stage's own progress onto one monotonic fraction).
"""

from __future__ import annotations

from typing import NamedTuple


class Stage(NamedTuple):
    name: str
    label: str
    weight: float


STAGES: tuple[Stage, ...] = (
    Stage("subsample", "Subsampling", 0.01),
    Stage("normalise", "Normalising", 0.01),
    Stage("reduce", "Reducing", 0.02),
    Stage("normals", "Estimating normals", 0.08),
    Stage("augment", "Augmenting", 0.01),
    Stage("features", "Features", 0.05),
    Stage("solve", "Solving", 0.33),
    Stage("evaluate", "Evaluating", 0.50),
    Stage("mesh", "Meshing", 0.10),
    Stage("clean", "Trimming", 0.02),
    Stage("colors", "Colours", 0.02),
)
STAGE_WEIGHTS = {s.name: s.weight for s in STAGES}
# Labels for every stage a front end shows, with the moments before the first and after the last.
STAGE_LABELS = {"start": "Starting", **{s.name: s.label for s in STAGES}, "done": "Done"}
