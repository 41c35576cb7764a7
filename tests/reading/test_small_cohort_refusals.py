"""Small cohorts are refused early, saying what works: ``learned_head_fit --all-folds`` checks every fold's validation
share before training any fold, and its refusal names the smallest ``--val-fraction`` that works on every fold, or
says that none does and what does instead (the ``--folds`` count that works, one head on the train split); a single fit's refusal
does the same. A head whose validation interval contains 0.5 is saved with a warning and a flag in ``config.json``.

The cohorts are ``dataset.json`` files as ``histojax dataset --folds 3`` plans them (no bundle: nothing is read)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from baselines.reading import learned_head_fit as fit
from baselines.reading.fitting import CHANCE_FLAG, MIN_SLIDES_PER_CLASS, chance_warning
from baselines.validation import check_all_folds, check_validation_share, split_train
from data_tools.datasets.build import make_plan
from data_tools.datasets.split import fold_lists


def folded(root: Path, tumour: int, normal: int, folds: int = 3) -> Path:
    """``root/dataset.json`` of ``tumour`` + ``normal`` slides in ``folds`` folds over every slide, patient ``PX``
    owning the first tumour and the first normal slide; returns ``root``."""
    rows = [(f"t{i:02d}", 1) for i in range(tumour)] + [(f"n{i:02d}", 0) for i in range(normal)]
    entries = [
        SimpleNamespace(
            name=n, label=lab, split=None, path=root / n, annotation=None, annotation_kind=None, label_source="t"
        )
        for n, lab in rows
    ]
    patients = {n: n for n, _ in rows} | {"t00": "PX", "n00": "PX"}
    plan = make_plan(entries, root, {}, 0.25, 0, folds=folds, patients=patients)
    names = sorted(plan["slides"])
    spec = {
        "kind": "histojax dataset",
        "train": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "train"],
        "test": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "test"],
        "labels": {n: plan["slides"][n]["label"] for n in names},
        "slides": [],
        "folds": fold_lists(plan["folds"], names),
        "patients": plan["patients"],
    }
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.json").write_text(json.dumps(spec))
    return root


def _never(*a, **k):
    raise AssertionError("a slide was read or a fold trained before every fold was checked")


def test_all_folds_refuses_before_training_any_fold_when_none_can_work(tmp_path, capsys, monkeypatch):
    """29 slides (10 tumour), 3 folds: folds 1-2 keep 6 tumour training slides, fewer than 3 validation + 5 fitting."""
    ds = folded(tmp_path / "ds", 10, 19)
    monkeypatch.setattr(fit, "load_split", _never)
    monkeypatch.setattr(fit, "train", _never)
    out = tmp_path / "heads"
    assert fit._main()(["--dataset", str(ds), "--out", str(out), "--all-folds", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(ds / "dataset.json") in err and "--all-folds" in err and "Nothing was trained" in err
    assert "no --val-fraction works on every fold" in err and "6 tumour" in err
    assert "larger --val-fraction" not in err  # no fraction is offered where none works
    assert "build the dataset with --folds 5" in err  # more folds: each train side larger (4/5 of the slides)
    assert not (out / "fold0").exists()


def test_all_folds_names_the_smallest_fraction_that_works_on_every_fold(tmp_path, monkeypatch):
    ds = folded(tmp_path / "ds", 14, 14)
    with pytest.raises(ValueError) as err:
        check_all_folds(ds, 0.2, 0, fitting=MIN_SLIDES_PER_CLASS)
    line = str(err.value)
    assert "\n" not in line and "--val-fraction 0.32 works on every fold" in line and "fold 0" in line
    check_all_folds(ds, 0.32, 0, fitting=MIN_SLIDES_PER_CLASS)  # the fraction it names: accepted
    spec = json.loads((ds / "dataset.json").read_text())
    from histojax.datasets import with_fold

    for i in range(3):  # and it does give every fold 3 validation and 5 fitting slides of each class
        side = with_fold(spec, i)
        kept, held = split_train(side, 0.32, 0)
        for entries, least in ((held, 3), (kept, MIN_SLIDES_PER_CLASS)):
            got = [spec["labels"][Path(e).name] for e in entries]
            assert min(sum(got), len(got) - sum(got)) >= least


def test_all_folds_names_a_fold_count_that_works_when_no_fraction_does(tmp_path):
    ds = folded(tmp_path / "ds", 12, 12, folds=2)  # 2 folds: 6 tumour and 6 normal training slides a fold
    with pytest.raises(ValueError) as err:
        check_all_folds(ds, 0.2, 0, fitting=MIN_SLIDES_PER_CLASS)
    line = str(err.value)
    assert "no --val-fraction works on every fold" in line and "build the dataset with --folds 3" in line, line
    check_all_folds(folded(tmp_path / "ds3", 12, 12, folds=3), 0.36, 0, fitting=MIN_SLIDES_PER_CLASS)  # as named


def test_a_single_fits_refusal_says_when_no_fraction_works(tmp_path):
    ds = folded(tmp_path / "ds", 10, 19)
    from histojax.datasets import with_fold

    side = with_fold(json.loads((ds / "dataset.json").read_text()), 1)
    kept, held = split_train(side, 0.2, 0)
    with pytest.raises(ValueError) as err:
        check_validation_share(side, held, "ds/dataset.json", 0.2, 1, seed=0, fitting=MIN_SLIDES_PER_CLASS)
    line = str(err.value)
    assert "no --val-fraction does" in line and "more --folds K" in line and "larger --val-fraction" not in line


def test_a_validation_interval_containing_chance_is_warned_about():
    line = chance_warning(0.611, 0.278, 0.861, "the validation share of fold 1")
    assert "0.611 [0.278, 0.861]" in line and "contains 0.5" in line and CHANCE_FLAG in line and "\n" not in line
    assert chance_warning(0.95, 0.81, 0.99, "x") is None
    assert chance_warning(float("nan"), float("nan"), float("nan"), "x") is None


@pytest.mark.slow  # about 13 s: builds a 20-slide feature cohort and runs the fit's bookkeeping (jit); the warning's
# words are checked by default in test_a_validation_interval_containing_chance_is_warned_about
def test_a_head_whose_validation_interval_contains_chance_is_saved_with_a_warning_and_a_flag(
    tmp_path, capsys, monkeypatch
):
    """The learned fit on 8 + 8 training slides (3 + 3 validate): the fit itself is stubbed (an untrained head) and
    the interval is the issue's 0.611 [0.278, 0.861]; the head is saved, the warning printed, the flag recorded."""
    from learned_fixture import make_cohort, untrained_fit

    c = make_cohort(tmp_path / "ds", tumour=8, normal=8, test_tumour=2, test_normal=2, dim=16, signal=4.0)

    def untrained(*args, **kwargs):  # the untrained head, with this test's curve
        head, _ = untrained_fit(*args, **kwargs)
        return head, [{"step": 1, "loss": 0.7, "full": 0.6, "read 0.1": 0.5, "validation_loss": 0.7, "smoothed": 0.6}]

    monkeypatch.setattr(fit, "train", untrained)
    monkeypatch.setattr(fit, "check_head", lambda *a, **k: None)
    monkeypatch.setattr(fit, "val_interval", lambda val, auc: (0.278, 0.861))
    out = tmp_path / "h"
    args = ["--dataset", str(c["root"]), "--out", str(out), "--val-fraction", "0.4", "--hidden", "32", "--quiet"]
    assert fit._main()(args) == 0
    err = capsys.readouterr().err
    assert "[0.278, 0.861]" in err and "contains 0.5" in err
    assert json.loads((out / "config.json").read_text())["chosen_on"][CHANCE_FLAG] is True
