"""Heads that know what they were fitted on, on a small cohort: a fit whose validation share is too small is refused
before any training; a fitted head records the dataset, split, fold and its fitting and validation slides; every
scorer refuses a head on a slide it was fitted or validated on (``--allow-fitting-slides``: warned); published and
older heads (no record) are taken as fitted on the train split; ``learned_head_fit --all-folds`` fits one head per
fold and each fold's head is the one that scores that fold.

The cohort (:func:`learned_fixture.make_cohort`, TRIDENT-layout 16-d features): 18 training slides (9 tumour, 9
normal), 6 test slides (3 + 3), a patient with two slides (:data:`PATIENT`) and three folds over all 24 (4 + 4 each,
dealt by the folds' own patient grouping)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from learned_fixture import make_cohort, untrained_fit

from baselines.reading import learned_head_fit as fit
from baselines.reading import provenance
from baselines.validation import MIN_VALIDATION_PER_CLASS, check_validation_share, split_train

PATIENT = {"s00_tumour": "P1", "s01_tumour": "P1"}
"""The cohort's one patient with two slides (both tumour, both training slides)."""
FAST = ["--steps", "100", "--eval-every", "20", "--hidden", "32", "--batch", "8", "--views", "64", "--quiet"]


def _main(argv):
    return fit._main()(argv)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The small cohort with three folds over every slide (``dataset.json``'s ``folds``, pool ``all``)."""
    c = make_cohort(
        tmp_path_factory.mktemp("provenance") / "ds",
        tumour=9,
        normal=9,
        test_tumour=3,
        test_normal=3,
        dim=16,
        signal=4.0,
    )
    from data_tools.datasets.split import fold_lists, folds_record, kfold_split, patient_groups

    spec = json.loads((c["root"] / "dataset.json").read_text())
    names = [Path(e).name for e in spec["train"] + spec["test"]]
    groups, how = patient_groups(names, PATIENT)  # the folds' own grouping: the patient's two slides in one fold
    fold = kfold_split(names, spec["labels"], 3, 0, groups)
    spec["folds"] = fold_lists(folds_record(fold, 3, 0, "all", how), names)
    (c["root"] / "dataset.json").write_text(json.dumps(spec))
    return c


@pytest.fixture(scope="module")
def head(small, tmp_path_factory):
    """A learned head "fitted" (untrained: :func:`learned_fixture.untrained_fit`, the guards on its figures off) by
    the command on the train split with a validation share of 0.4 (4 + 4 slides): what the command records, without
    its training."""
    out = tmp_path_factory.mktemp("provenance-head") / "h"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit, "train", untrained_fit)
        mp.setattr(fit, "check_head", lambda *a, **k: None)
        assert _main(["--dataset", str(small["root"]), "--out", str(out), "--val-fraction", "0.4", *FAST]) == 0
    return out


def test_a_validation_share_too_small_is_refused_before_any_slide_is_read(small, tmp_path, capsys, monkeypatch):
    def never(*a, **k):
        raise AssertionError("read or trained before the validation share was checked")

    monkeypatch.setattr(fit, "load_split", never)
    monkeypatch.setattr(fit, "train", never)
    root = small["root"]
    assert _main(["--dataset", str(root), "--out", str(tmp_path / "h"), "--quiet"]) == 2  # 0.2 of 9 + 9: 2 + 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "2 tumour and 2 normal validation slides" in err and str(root) in err
    assert "use --val-fraction 0.28 (the smallest that does)" in err  # what works, not merely "larger"
    assert not (tmp_path / "h").exists()
    assert _main(["--dataset", str(root), "--out", str(tmp_path / "h"), "--fold", "0", "--quiet"]) == 2
    assert "fold 0's train side" in capsys.readouterr().err


def test_the_logit_and_mil_fits_refuse_the_same_share(small):
    from baselines.reading import head_fit

    with pytest.raises(ValueError, match="gives 2 tumour and 2 normal validation slides"):
        head_fit.fit(small["root"], None, val_fraction=0.2)
    spec = json.loads((small["root"] / "dataset.json").read_text())
    kept, held = split_train(spec, 0.4, 0)
    check_validation_share(spec, held, "x", 0.4)  # 4 + 4: accepted
    assert MIN_VALIDATION_PER_CLASS == 3


def test_the_head_records_the_dataset_split_and_its_slides(small, head):
    cfg = json.loads((head / "config.json").read_text())
    rec = cfg[provenance.RECORD]
    spec = json.loads((small["root"] / "dataset.json").read_text())
    kept, held = split_train(spec, 0.4, 0)
    assert rec["fitted"] == sorted(Path(e).name for e in kept)
    assert rec["validation"] == sorted(Path(e).name for e in held)
    assert rec["split"] == "train" and rec["fold"] is None
    assert rec["dataset"]["folder"] == str(small["root"].resolve()) and "seal" in rec["dataset"]
    assert not set(rec["fitted"]) & set(small["names"]["test"])


def test_score_refuses_the_heads_own_slides_and_warns_with_the_flag(small, head, capsys):
    root = str(small["root"])
    assert _main(["--dataset", root, "--score", str(head), "--split", "train", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(head / "config.json") in err and "--allow-fitting-slides" in err, err
    assert "fitted on 10" in err and "validated on 8" in err
    assert (
        _main(["--dataset", root, "--score", str(head), "--split", "train", "--allow-fitting-slides", "--quiet"]) == 0
    )
    out, err = capsys.readouterr()
    figure = json.loads(out.strip().splitlines()[-1])
    assert figure["slides"] == 18 and "warning:" in err and "not held out" in err
    # the figure written says it was scored on the head's own slides (before: no mark in what was written)
    assert figure["self_scored"] is True and figure["scored_on_seen_slides"] == sorted(small["names"]["train"])
    assert _main(["--dataset", root, "--score", str(head), "--split", "test", "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "not held out" not in err  # (the small-split warning may be there)
    assert "self_scored" not in json.loads(out.strip().splitlines()[-1])
    # a fold's held-out side holding training slides of the head: refused too
    assert _main(["--dataset", root, "--score", str(head), "--fold", "1", "--quiet"]) == 2
    assert "not held out" in capsys.readouterr().err


def test_readers_refuse_the_heads_own_slides(small, head, tmp_path, capsys):
    from baselines.reading import readers

    argv = [
        "--dataset",
        str(small["root"]),
        "--head",
        str(head),
        "--split",
        "train",
        "--out",
        str(tmp_path / "r"),
        "--budgets",
        "0.5",
        "--seeds",
        "1",
    ]
    assert readers.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--allow-fitting-slides" in err and not (tmp_path / "r").exists(), err
    # with the flag: scored, and what is written says on which of the head's own slides
    assert readers.main([*argv, "--allow-fitting-slides"]) == 0
    record = json.loads((tmp_path / "r" / "readers.json").read_text())
    assert record["self_scored"] is True and record["scored_on_seen_slides"]["head"] == sorted(small["names"]["train"])
    with open(tmp_path / "r" / "readers.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["scored_on_seen_slides"].startswith("head: ") for r in rows)


def test_every_scorer_takes_the_flag():
    import argparse

    from baselines.evaluate.cli import add_arguments as evaluate_args
    from baselines.reading import budget_curve, diagnosis, readers

    for add in (
        evaluate_args,
        budget_curve.add_arguments,
        diagnosis.add_arguments,
        readers.add_arguments,
        fit.add_arguments,
    ):
        p = argparse.ArgumentParser()
        add(p)
        assert "--allow-fitting-slides" in p.format_help(), add.__module__


class _Head:
    def __init__(self, info):
        self.info = json.dumps(info)


def test_a_head_without_a_record_is_taken_as_fitted_on_the_train_split(small, capsys):
    """Older heads record a fit (``fitted_on``) but no slides: the train split of the dataset they name, when that
    is the scored one (or they name none), counts as fitted; one naming another dataset that is not here is scored
    with a warning that its slides cannot be checked (before: taken as fitted on the train split of whatever
    dataset it scored); a head built in code has seen nothing."""
    root = small["root"]
    legacy = _Head({"fitted_on": {"dataset": str(root), "split": "train"}})
    fitted, validated, source = provenance.overlap(legacy, root, small["names"]["train"][:3] + small["names"]["test"])
    assert source == "assumed" and fitted == sorted(small["names"]["train"][:3]) and validated == []
    provenance.check_scored(legacy, "h", root, small["names"]["test"])  # the test split: scored as before
    with pytest.raises(provenance.FittingSlidesError, match="records no slides"):
        provenance.check_scored(legacy, "h", root, small["names"]["train"][:1])
    assert provenance.overlap(_Head({}), root, small["names"]["train"])[:2] == ([], [])
    elsewhere = _Head({"fitted_on": {"dataset": "c16-full", "split": "train"}})  # another dataset, not here
    assert provenance.overlap(elsewhere, root, small["names"]["train"]) == ([], [], "unknown")
    capsys.readouterr()
    assert provenance.check_scored(elsewhere, "h", root, small["names"]["train"]) is None
    assert "records no slides and was fitted on c16-full, which is not here" in capsys.readouterr().err
    older_fold_head = _Head({"fitted_on": {"split": "train", "fold": 0}})  # fitted on folds 1 and 2, test slides too
    lists = json.loads((root / "dataset.json").read_text())["folds"]["lists"]
    seen = provenance.overlap(older_fold_head, root, small["names"]["test"])[0]
    assert seen == sorted(Path(e).name for e in lists[1] + lists[2] if Path(e).name in small["names"]["test"])
    assert seen  # some test slides lie in folds 1 and 2


def test_the_published_c16_heads_score_the_c16_test_split_but_not_its_train_split(tmp_path):
    from baselines.published_agents import PUBLISHED
    from histojax.reading import heads

    """The published heads record c16-full's train slides by their CAMELYON16 names: any C16 set's train slides
    are refused, its test slides scored."""
    spec = {
        "kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
        "train": ["bundles/Tumor_001", "bundles/Normal_001"],
        "test": ["bundles/Test_001"],
        "labels": {},
    }
    (tmp_path / "dataset.json").write_text(json.dumps(spec))
    for name in ("c16-v2-learned-head", "c16-v2-head", "c16-v2-head-mil"):
        h = heads.load(PUBLISHED / name)
        provenance.check_scored(h, "h", tmp_path, spec["test"])
        with pytest.raises(provenance.FittingSlidesError, match="fitted on 2 of the 2"):
            provenance.check_scored(h, "h", tmp_path, spec["train"])


def test_each_fold_resolves_its_own_head(tmp_path):
    assert provenance.head_for_fold("runs/h-fold{fold}", 2) == "runs/h-fold2"
    for i in range(2):
        (tmp_path / "all" / f"fold{i}").mkdir(parents=True)
        (tmp_path / "all" / f"fold{i}" / "config.json").write_text("{}")
    assert provenance.head_for_fold(tmp_path / "all", 1) == str(tmp_path / "all" / "fold1")
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "config.json").write_text("{}")
    assert provenance.head_for_fold(tmp_path / "one", 1) == str(tmp_path / "one")


def test_smoothed_choice_passes_over_a_lucky_check():
    """A validation curve that jumps to 1.0 once on a few slides (0.17, 1.0, 0.5, 0.83, 0.83, 0.83): the checkpoint
    kept is on the plateau, not the lucky check; equal plateaus go to the lower validation loss."""
    curve = [
        {"step": 10 * (i + 1), "full": v, "read 0.1": 0.5, "validation_loss": loss}
        for i, (v, loss) in enumerate([(0.17, 0.7), (1.0, 0.69), (0.5, 0.6), (0.83, 0.5), (0.83, 0.4), (0.83, 0.45)])
    ]
    fit.smooth_curve(curve)
    best = max(curve, key=fit.choice_key)
    assert best["step"] == 50, [(r["step"], r["smoothed"]) for r in curve]
    assert np.isclose(curve[1]["smoothed"], (0.17 + 1.0 + 0.5) / 3)


def test_all_folds_fits_one_head_per_fold_and_each_scores_only_its_fold(small, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(fit, "train", untrained_fit)  # the per-fold bookkeeping, not the learning
    monkeypatch.setattr(fit, "check_head", lambda *a, **k: None)
    root, out = str(small["root"]), tmp_path / "heads"
    assert _main(["--dataset", root, "--out", str(out), "--all-folds", "--val-fraction", "0.4", *FAST]) == 0
    for i in range(3):
        rec = json.loads((out / f"fold{i}" / "config.json").read_text())[provenance.RECORD]
        assert rec["fold"] == i
        held_out = {Path(e).name for e in json.loads((small["root"] / "dataset.json").read_text())["folds"]["lists"][i]}
        assert held_out.isdisjoint(rec["fitted"] + rec["validation"])
    head_0 = provenance.head_for_fold(out, 0)
    assert _main(["--dataset", root, "--score", str(out), "--fold", "0", "--quiet"]) == 0  # the folder: fold 0's head
    assert _main(["--dataset", root, "--score", head_0, "--fold", "1", "--quiet"]) == 2  # fold 0's head saw fold 1
    assert "fitted on fold 0" in capsys.readouterr().err


def test_evaluate_refuses_a_head_on_its_own_slides(small, head, tmp_path, capsys):
    from histojax.cli import main as histojax_main

    argv = [
        "evaluate",
        "--env",
        "HistoJAX-Reading-v0",
        "--action-mode",
        "glimpse:1",
        "--dataset",
        str(small["root"]),
        "--episodes",
        "1",
        "--head",
        str(head),
        "--out",
        str(tmp_path / "ev"),
    ]
    assert histojax_main([*argv, "--split", "train"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and str(head / "config.json") in err[0] and "--allow-fitting-slides" in err[0], err
    assert not (tmp_path / "ev").exists()


def test_budget_curve_refuses_one_head_over_folds_it_was_fitted_on(small, head, tmp_path, capsys):
    """``budget-curve --all-folds --head H`` with H fitted on the train split (most of every fold's held-out slides):
    refused at fold 0, before any slide is read."""
    from baselines.reading import budget_curve

    assert (
        budget_curve.main(
            ["--dataset", str(small["root"]), "--head", str(head), "--all-folds", "--out", str(tmp_path / "bc")]
        )
        == 2
    )
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "--allow-fitting-slides" in err[0] and str(head / "config.json") in err[0], err


def test_budget_curve_with_the_flag_marks_the_rows_scored_on_the_heads_slides(small, head, tmp_path, monkeypatch):
    """``budget-curve --fold 1 --head H --allow-fitting-slides``: each row of budget_curve.csv names the slides of
    fold 1 the head saw (the rows stubbed: the curve's own training is the slow tests')."""
    from baselines.reading import budget_curve

    def stub(train, test, budgets, **kw):
        return [
            {
                "method": "stub",
                "budget": b,
                "fraction_read": b,
                "auc": 0.5,
                "accuracy": 0.5,
                "slides": 1,
                "auc_std": 0.0,
                "accuracy_std": 0.0,
                "seeds": 1,
            }
            for b in budgets
        ]

    monkeypatch.setattr(budget_curve, "budget_rows", stub)
    out = tmp_path / "bc"
    argv = ["--dataset", str(small["root"]), "--head", str(head), "--fold", "1", "--budgets", "0.5", "--out", str(out)]
    argv += ["--env", "HistoJAX-Easy-v0", "--glimpse-level", "1", "--seeds", "1", "--steps", "20"]
    assert budget_curve.main([*argv, "--allow-fitting-slides"]) == 0
    with open(out / "budget_curve.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["scored_on_seen_slides"].startswith("head: ") for r in rows), rows


def test_diagnosis_refuses_the_heads_own_slides(small, head, tmp_path, capsys):
    from baselines.reading import diagnosis

    assert (
        diagnosis.main(
            [
                "--dataset",
                str(small["root"]),
                "--head",
                str(head),
                "--split",
                "train",
                "--navigator",
                "nav",
                str(tmp_path / "no-run"),
                "--out",
                str(tmp_path / "d"),
            ]
        )
        == 2
    )
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "--allow-fitting-slides" in err[0], err


def test_evaluate_all_folds_refuses_one_head_fitted_on_the_folds_slides(small, head, tmp_path, capsys):
    from histojax.cli import main as histojax_main

    argv = [
        "evaluate",
        "--env",
        "HistoJAX-Reading-v0",
        "--action-mode",
        "glimpse:1",
        "--dataset",
        str(small["root"]),
        "--episodes",
        "1",
        "--head",
        str(head),
        "--all-folds",
        "--out",
        str(tmp_path / "ev"),
    ]
    assert histojax_main(argv) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "--allow-fitting-slides" in err[0] and "not held out" in err[0], err


def test_the_patients_two_slides_share_a_fold_and_a_fold_head_refuses_both(small, tmp_path, capsys, monkeypatch):
    lists = json.loads((small["root"] / "dataset.json").read_text())["folds"]["lists"]
    assert [len(lst) for lst in lists] == [8, 8, 8]
    home = [i for i, lst in enumerate(lists) if "bundles/s00_tumour" in lst]
    assert len(home) == 1 and "bundles/s01_tumour" in lists[home[0]]
    other = (home[0] + 1) % 3  # a head fitted on fold `other`'s train side saw both of the patient's slides
    monkeypatch.setattr(fit, "train", untrained_fit)
    monkeypatch.setattr(fit, "check_head", lambda *a, **k: None)
    root, out = str(small["root"]), tmp_path / "h"
    assert _main(["--dataset", root, "--out", str(out), "--fold", str(other), "--val-fraction", "0.4", *FAST]) == 0
    rec = json.loads((out / "config.json").read_text())[provenance.RECORD]
    assert {"s00_tumour", "s01_tumour"} <= set(rec["fitted"] + rec["validation"]) and rec["fold"] == other
    assert _main(["--dataset", root, "--score", str(out), "--fold", str(home[0]), "--quiet"]) == 2
    assert "not held out" in capsys.readouterr().err
