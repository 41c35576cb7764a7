"""A run naming a head folder that is gone is refused in one line naming it (before: the published head of the same
folder name, without a word); ``learned_head_fit --score NAME`` resolves a published head's name as ``histojax
evaluate --head`` does (the package's copy, never a same-named folder of the working folder); and the published
heads and agents carry the slides they saw (c16-full's, by CAMELYON16 name), so another dataset's slides are scored
and a C16 set's training slides refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from baselines.evaluate.checks import resolve_head
from baselines.published_agents import PUBLISHED, published_names
from baselines.reading import learned_head_fit, provenance
from data_tools.errors import HistojaxDataError

C16_KIND = "histojax true-scale CAMELYON16 benchmark (data_tools c16)"


def test_a_missing_head_folder_is_refused_not_replaced_by_a_published_one(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    where = run / "head_reward.json"
    gone = tmp_path / "elsewhere" / "c16-v2-head"  # a head of the machine it trained on, same folder name
    with pytest.raises(HistojaxDataError) as e:
        resolve_head(str(gone), run, where)
    line = str(e.value)
    assert len(line.splitlines()) == 1 and str(where) in line and str(gone / "config.json") in line, line
    with pytest.raises(HistojaxDataError, match="runs/c16-v2-head"):
        resolve_head("runs/c16-v2-head", run, where)  # a relative folder: not the published head either
    assert resolve_head("c16-v2-head", run, where) == PUBLISHED / "c16-v2-head"  # its own name: the package's


def test_learned_head_fit_score_resolves_a_published_name_from_the_package(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    decoy = tmp_path / "c16-v2-learned-head"  # a same-named folder of the working folder
    decoy.mkdir()
    (decoy / "config.json").write_text('{"kind": "learned-attention-mil", "note": "a decoy"}')
    import argparse

    parser = argparse.ArgumentParser()
    learned_head_fit.add_arguments(parser)
    args = parser.parse_args(["--dataset", "d", "--score", "c16-v2-learned-head"])
    assert Path(args.score) == PUBLISHED / "c16-v2-learned-head"
    args = parser.parse_args(["--dataset", "d", "--score", "./c16-v2-learned-head"])  # named as a path: that one
    assert Path(args.score).resolve() == decoy.resolve()


def _dataset(root: Path, kind: str, train: list[str], test: list[str]) -> Path:
    root.mkdir()
    spec = {"kind": kind, "train": [f"bundles/{n}" for n in train], "test": [f"bundles/{n}" for n in test]}
    (root / "dataset.json").write_text(json.dumps(spec))
    for i, n in enumerate(train + test):  # each bundle built from its own slide file
        (root / "bundles" / n).mkdir(parents=True)
        (root / "bundles" / n / "metadata.json").write_text(json.dumps({"source": {"sha256": f"{i:064x}"}}))
    return root


@pytest.mark.parametrize("name", published_names())
def test_every_published_folder_records_the_slides_it_saw(name):
    folder = PUBLISHED / name
    config = json.loads((folder / "config.json").read_text())
    record = config.get(provenance.RECORD) if "algo" not in config else provenance.run_record(folder)[0]
    assert isinstance(record, dict), name
    assert record["dataset"]["folder"] == "c16-full" and C16_KIND == record["dataset"]["kind"]
    seen = set(record["fitted"]) | set(record["validation"])
    assert len(seen) == 180 and all(record["identities"][n] == f"camelyon16:{n}" for n in seen)


def test_published_records_refuse_c16_training_slides_and_score_another_datasets(tmp_path):
    """The issue's case: a published head scoring 29 slides of another dataset it never saw, some of them named like
    c16-full's training slides, was refused ('fitted on 23 of the 29'); now scored. A C16 set's train slides are
    refused, its test slides scored."""
    from histojax.reading import heads

    other = _dataset(tmp_path / "other", "histojax dataset of real slides (data_tools dataset)", ["Tumor_001"], ["s1"])
    c16 = _dataset(tmp_path / "c16", C16_KIND, ["Tumor_001", "Normal_001"], ["Test_001"])
    head = heads.load(PUBLISHED / "c16-v2-head")
    entries = ["bundles/Tumor_001", "bundles/s1"]
    assert provenance.check_scored(head, PUBLISHED / "c16-v2-head", other, entries) is None
    with pytest.raises(provenance.FittingSlidesError, match="fitted on 2 of the 2"):
        provenance.check_scored(head, PUBLISHED / "c16-v2-head", c16, ["bundles/Tumor_001", "bundles/Normal_001"])
    agent, where = provenance.run_record(PUBLISHED / "c16-v2-set-reader")
    assert where == PUBLISHED / "c16-v2-set-reader" / "slides_seen.json"
    assert provenance.check_record(agent, where, other, entries, who="policy") is None
    assert provenance.check_record(agent, where, c16, ["bundles/Test_001"], who="policy") is None
    with pytest.raises(provenance.FittingSlidesError, match="the policy was"):
        provenance.check_record(agent, where, c16, ["bundles/Tumor_001", "bundles/Normal_001"], who="policy")
