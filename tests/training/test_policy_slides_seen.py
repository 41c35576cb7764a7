"""Policies know their slides, like heads: a trained run records the slides it trained and validated on
(``slides_seen.json``: the dataset's seal, split, fold, names and each slide's identity), and ``histojax evaluate``
refuses to score a policy on them (``--allow-fitting-slides``: scored with a warning, and the written figures say
so); slides are known by identity, so a renamed slide is still the slide it trained on, and a slide of another
dataset that only shares a name is not. The rollouts are stubbed (what is checked happens before any)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from fold_helpers import build_folded

from baselines.evaluate import cli
from baselines.harness.logs import save_checkpoint
from baselines.reading import provenance
from data_tools.datasets.build import write_dataset_index

RUN = {
    "algo": "ppo",
    "env_id": "HistoJAX-Easy-v0",
    "action_mode": "discrete",
    "obs_mode": "pixels",
    "with_position": False,
    "hidden": 16,
}


@pytest.fixture(scope="module")
def folded(tmp_path_factory):
    """The 7-slide dataset of the fold tests (``--folds 2``), each slide cut from another part of the sample slide
    (so each has its own source SHA-256)."""
    return build_folded(tmp_path_factory.mktemp("policy-slides"))


def _run(folder: Path, dataset: Path, fold: int | None = 0, record: bool = True) -> Path:
    config = {
        **RUN,
        "env_kwargs": {"dataset": str(dataset), "split": "train", **({"fold": fold} if fold is not None else {})},
    }
    save_checkpoint(folder, {"params": {"w": np.zeros((1, 2), np.float32)}}, config)
    if record:
        provenance.write_run_record(folder, config)  # as the trainers' finish_run writes it
    return folder


@pytest.fixture
def stubbed(monkeypatch):
    """``evaluate`` replaced by one row per call (no rollout); returns the configs it was called with."""
    calls = []

    def scored(config, params, out=None, **kw):
        calls.append(config.env_kwargs)
        return {
            "learned (greedy)": {
                "episodes": 1,
                "success_rate": 1.0,
                "mean_return": 0.0,
                "mean_length": 1.0,
                "mean_steps_to_success": 1.0,
                "mean_fraction_read": 0.1,
                "mean_fields_of_view": 1.0,
            }
        }

    monkeypatch.setattr(cli, "evaluate", scored)
    return calls


def _one_line(capsys) -> str:
    err = [x for x in capsys.readouterr().err.strip().splitlines() if x.startswith("error:")]
    assert len(err) == 1, err
    return err[0]


def test_a_run_records_the_slides_it_trained_on(folded, tmp_path):
    run = _run(tmp_path / "run", folded)
    record = json.loads((run / provenance.RUN_RECORD).read_text())
    spec = json.loads((folded / "dataset.json").read_text())
    assert record["dataset"]["seal"] == spec["dataset_sha256"] and record["fold"] == 0 and record["split"] == "train"
    lists = spec["folds"]["lists"]
    assert record["fitted"] == sorted(Path(e).name for e in lists[1])  # fold 0's train side: the other fold
    assert set(record["identities"]) == set(record["fitted"]) and all(
        v.startswith("sha256:") for v in record["identities"].values()
    )


def test_evaluate_refuses_a_policy_on_its_own_training_slides(folded, tmp_path, stubbed, capsys):
    """``histojax evaluate RUN`` (its own train split) and ``--fold 1`` (fold 1's held-out side: the slides fold 0's
    run trained on) are refused in one line naming the run's record; fold 0's held-out side is scored."""
    run = _run(tmp_path / "run", folded)
    for extra in ([], ["--dataset", str(folded), "--fold", "1"]):
        assert cli.main([str(run), *extra, "--out", str(tmp_path / "o")]) == 2
        line = _one_line(capsys)
        assert str(run / "slides_seen.json") in line and "the policy was trained on" in line, line
        assert "--allow-fitting-slides" in line and not (tmp_path / "o").exists()
    assert not stubbed
    assert cli.main([str(run), "--dataset", str(folded), "--fold", "0", "--out", str(tmp_path / "ok")]) == 0
    record = json.loads((tmp_path / "ok" / "eval.json").read_text())
    assert "self_scored" not in record and "scored_on_seen_slides" not in record


def test_the_flag_scores_them_and_the_written_figures_say_so(folded, tmp_path, stubbed, capsys):
    run = _run(tmp_path / "run", folded)
    out = tmp_path / "o"
    assert cli.main([str(run), "--allow-fitting-slides", "--out", str(out)]) == 0
    assert "warning:" in capsys.readouterr().err
    record = json.loads((out / "eval.json").read_text())
    trained = json.loads((run / "slides_seen.json").read_text())["fitted"]
    assert record["self_scored"] is True and record["scored_on_seen_slides"]["policy"] == trained
    with open(out / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["scored_on_seen_slides"] == "policy: " + " ".join(trained) for r in rows)


def test_an_older_run_without_the_record_is_checked_from_its_config(folded, tmp_path, stubbed, capsys):
    run = _run(tmp_path / "old", folded, record=False)  # trained before slides_seen.json: config.json names them
    assert cli.main([str(run), "--out", str(tmp_path / "o")]) == 2
    assert str(run / "config.json") in _one_line(capsys)


def _renamed_copy(dataset: Path, into: Path, old: str, new: str) -> Path:
    """``dataset`` copied to ``into`` with slide ``old`` renamed ``new`` (its bundle, entries, label, record) and
    sealed again: another seal, the same slide files."""
    shutil.copytree(dataset, into, symlinks=True)
    (into / "bundles" / old).rename(into / "bundles" / new)
    text = (into / "dataset.json").read_text().replace(f'bundles/{old}"', f'bundles/{new}"')
    spec = json.loads(text)
    spec["labels"] = {(new if k == old else k): v for k, v in spec["labels"].items()}
    for r in spec.get("slides", []):
        if r.get("name") == old:
            r["name"] = new
    spec.pop("dataset_sha256", None)
    write_dataset_index(into, spec)
    return into


def test_a_renamed_slide_in_another_dataset_is_still_the_slide_it_trained_on(folded, tmp_path, stubbed, capsys):
    run = _run(tmp_path / "run", folded, fold=None)  # the whole train split
    trained = json.loads((run / "slides_seen.json").read_text())["fitted"]
    copy = _renamed_copy(folded, tmp_path / "copy", trained[0], "renamed")
    assert (
        json.loads((copy / "dataset.json").read_text())["dataset_sha256"]
        != json.loads((folded / "dataset.json").read_text())["dataset_sha256"]
    )
    assert cli.main([str(run), "--dataset", str(copy), "--split", "all", "--out", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert f"renamed (recorded as {trained[0]})" in line, line


def test_a_slide_of_another_dataset_sharing_only_a_name_is_not_seen(folded, tmp_path):
    """Another seal and another slide file under a recorded name: not the slide it saw (before: matched by name)."""
    run = _run(tmp_path / "run", folded, fold=None)
    record = json.loads((run / "slides_seen.json").read_text())
    other = tmp_path / "other"
    shutil.copytree(folded, other, symlinks=True)
    spec = json.loads((other / "dataset.json").read_text())
    spec["note_copy"] = "another dataset"  # another seal
    spec.pop("dataset_sha256", None)
    write_dataset_index(other, spec)
    name = record["fitted"][0]
    meta = other / "bundles" / name / "metadata.json"
    body = json.loads(meta.read_text())
    body["source"]["sha256"] = "0" * 64  # another slide file under the same name
    meta.unlink()
    meta.write_text(json.dumps(body))
    entries = [f"bundles/{n}" for n in record["fitted"]]
    fitted, validated, _ = provenance.seen_among(record, other, entries)
    assert name not in fitted and set(fitted) == set(record["fitted"]) - {name}
    # the same dataset (its seal): names are trusted
    assert provenance.seen_among(record, folded, entries)[0] == record["fitted"]


def test_all_folds_refuses_a_fold_the_policy_trained_on_and_marks_it_with_the_flag(folded, tmp_path, stubbed, capsys):
    """One run (trained on fold 0's train side) for every fold: fold 1's held-out side is its training slides."""
    run = _run(tmp_path / "run", folded)
    argv = [str(run), "--dataset", str(folded), "--all-folds", "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    assert str(run / "slides_seen.json") in _one_line(capsys)
    assert cli.main([*argv, "--allow-fitting-slides"]) == 0
    record = json.loads((tmp_path / "o" / "eval.json").read_text())
    trained = json.loads((run / "slides_seen.json").read_text())["fitted"]
    assert record["self_scored"] is True and record["scored_on_seen_slides"] == {"1": {"policy": trained}}
    with open(tmp_path / "o" / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["fold"]: r["scored_on_seen_slides"] for r in rows if r["fold"] in ("0", "1")} == {
        "0": "",
        "1": "policy: " + " ".join(trained),
    }
    assert all(r["scored_on_seen_slides"].startswith("fold 1: policy: ") for r in rows if r["fold"] == "mean")


def test_the_validation_slides_held_back_are_scored_and_a_published_run_records_them(folded, tmp_path, stubbed):
    """A run on a ``baselines.validation`` split: scoring its held-back slides is the validation (not refused);
    published, the run was chosen on them: its record names them as ``validation``, refused like trained ones."""
    from baselines.publish import publish
    from baselines.validation import write_validation_dataset

    val = tmp_path / "val"
    write_validation_dataset(folded, 0.4, 0, val)
    run = _run(tmp_path / "run", val, fold=None)
    record = json.loads((run / "slides_seen.json").read_text())
    held = record["held_back"]
    assert held and record["validation"] == [] and set(held) <= set(record["identities"])
    assert cli.main([str(run), "--dataset", str(val), "--split", "test", "--out", str(tmp_path / "o")]) == 0
    dest = publish(run, "agent", root=tmp_path / "published")
    published = json.loads((dest / "slides_seen.json").read_text())
    assert published["validation"] == held and "held_back" not in published
    assert published["dataset"]["folder"] == "val"  # no path of this machine
    with pytest.raises(provenance.FittingSlidesError, match="validated on"):
        provenance.check_record(
            published, dest, val, json.loads((val / "dataset.json").read_text())["test"], who="policy"
        )
