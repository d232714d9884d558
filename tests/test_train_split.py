"""The corpus split by source (nkf_model.train.corpus.source_split): whole sources held out by kind."""

from __future__ import annotations

import random

import pytest

from nkf_model.train import corpus


def _row(name, repo, path, split="train"):
    return corpus.CorpusMesh(file=f"{name}.ply", split=split, watertight=True, category="x", license="x",
                             source_repo=repo, source_path=path)


def test_source_of_names_asset_packs_and_repositories():
    assert corpus.source_of("mikedh/trimesh", "models/rod.3DXML") == "mikedh/trimesh"
    assert corpus.source_of(corpus.PACK_REPO, "Kenny NL Assets/Furniture Pack (1.0)/Models/chair.fbx") == \
        "kenney/Furniture Pack"
    assert corpus.source_of(corpus.PACK_REPO, "FreeModels by Quaternius[Patreon]/Characters and Animals/x/Cow.fbx") \
        == "quaternius/Characters and Animals"
    with pytest.raises(ValueError):
        corpus.source_of(corpus.PACK_REPO, "Somebody Else/Pack/x.fbx")


def test_held_out_sources_never_train_and_keep_both_split_rows():
    rows = [
        _row("a", "mikedh/trimesh", "models/a.stl"),
        _row("b", "mikedh/trimesh", "models/b.stl", split="val"),
        _row("c", "bulletphysics/bullet3", "data/c.obj"),
        _row("d", "bulletphysics/bullet3", "data/d.obj", split="val"),
        _row("e", corpus.PACK_REPO, "Kenny NL Assets/Castle Kit (1.0)/e.fbx"),
        _row("f", corpus.PACK_REPO, "Kenny NL Assets/Space Kit (1.0)/f.fbx"),
    ]
    train, held = corpus.source_split(rows)
    assert [e.name for e in train] == ["c", "f"]  # the other val row (d) stays out of training too
    assert [e.name for e in held["mechanical"]] == ["a", "b"]
    assert [e.name for e in held["architecture"]] == ["e"]
    assert held["organic"] == [] and held["furniture"] == []


def test_split_does_not_depend_on_the_order():
    rows = [_row(f"m{i}", repo, path) for i, (repo, path) in enumerate(
        [("mikedh/trimesh", "models/x")] * 5 + [("pyvista/vtk-data", "Data/y")] * 5
        + [(corpus.PACK_REPO, "Kenny NL Assets/Furniture Pack (1.0)/z")] * 9)]
    a_train, a_held = corpus.source_split(rows)
    random.Random(3).shuffle(rows)
    b_train, b_held = corpus.source_split(rows)
    assert [e.name for e in a_train] == [e.name for e in b_train]
    assert {k: [e.name for e in v] for k, v in a_held.items()} == {k: [e.name for e in v] for k, v in b_held.items()}
    sub = corpus.validation_subset(a_held, 4)
    assert len(sub["furniture"]) == 4 and len(sub["mechanical"]) == 4
    assert sub == corpus.validation_subset(b_held, 4)
    # The subset of a kind depends only on that kind's names: adding meshes elsewhere changes nothing.
    more = dict(a_held, organic=[_row("zz", "x/y", "p")])
    assert corpus.validation_subset(more, 4)["furniture"] == sub["furniture"]


def test_the_corpus_split_holds_out_four_kinds_of_whole_sources():
    if not (corpus.corpus_dir() / "MANIFEST.csv").is_file():
        pytest.skip("the mesh corpus (../shared/data/meshes) is not beside this checkout")
    rows = corpus.manifest()
    train, held = corpus.source_split(rows)
    assert set(held) == {"organic", "mechanical", "furniture", "architecture"}
    held_sources = {e.source for v in held.values() for e in v}
    train_sources = {e.source for e in train}
    assert held_sources and not held_sources & train_sources  # whole sources, disjoint
    for kind, sources in corpus.HELDOUT_SOURCES.items():
        assert {e.source for e in held[kind]} == set(sources)  # every named source exists in the corpus
        assert len(held[kind]) >= 8, kind
        # every row of a held-out source is held out, whatever its split column says
        assert len(held[kind]) == sum(1 for e in rows if e.source in sources)
    names = [e.name for e in train] + [e.name for v in held.values() for e in v]
    assert len(names) == len(set(names))
    assert len(train) >= 300
    assert all(e.split == "train" for e in train)
    sub = corpus.validation_subset(held, 6)
    assert all(len(v) == 6 for v in sub.values())
