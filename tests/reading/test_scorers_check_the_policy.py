"""Every scorer checks the policy's slides, not only the head's: ``readers --reader NAME RUN``, ``budget-curve --ppo
NAME RUN`` and ``diagnosis --navigator NAME RUN`` refuse, before any slide is read and in one line naming the option
and ``RUN/slides_seen.json``, slides the policy trained on (``--allow-fitting-slides``: scored with a warning, and
the files written say on which, ``"policy NAME"`` beside ``"head"``); the validation slides its dataset held back
are scored (how ``train_readers`` chooses among its runs). The rollouts are stubbed; the default tests stop where
the slides would be read (a stub head that records no fit), the full runs through a head are ``slow`` (the budget curve's, its rows stubbed, is not).

The cohort (:func:`learned_fixture.make_cohort`, 16-d features): 18 training slides, 6 test slides. The policy
"trained" on the **test** split (``slides_seen.json`` as the trainers write it), so that the head, fitted on the
train split, may score the test split and only the policy is refused there."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from learned_fixture import make_cohort, untrained_fit

from baselines.harness.logs import save_checkpoint
from baselines.reading import budget_curve, diagnosis, provenance, readers

RUN = {
    "algo": "ppo",
    "env_id": "HistoJAX-Easy-v0",
    "action_mode": "glimpse",
    "obs_mode": "features",
    "with_position": False,
    "hidden": 16,
}
FAST = ["--steps", "100", "--eval-every", "20", "--hidden", "32", "--batch", "8", "--views", "64", "--quiet"]


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    return make_cohort(
        tmp_path_factory.mktemp("policy-scorers") / "ds",
        tumour=9,
        normal=9,
        test_tumour=3,
        test_normal=3,
        dim=16,
        signal=4.0,
    )


def _run(folder: Path, dataset, split: str = "test") -> Path:
    """A run folder "trained" on ``dataset``'s ``split``: its checkpoint and the record the trainers write."""
    config = {**RUN, "env_kwargs": {"dataset": str(dataset), "split": split}}
    save_checkpoint(folder, {"params": {"w": np.zeros((1, 2), np.float32)}}, config)
    provenance.write_run_record(folder, config)
    return folder


class _Unread(Exception):
    """Raised where the scorer would start reading slides: the guards before it let the slides through."""


def _never(*a, **k):
    raise _Unread


@pytest.fixture
def no_reading(monkeypatch):
    """A head that records no fit (it has seen no slide) and no slide read: the policy's guard alone is checked."""
    from histojax.reading import heads

    class Head:
        info = "{}"

    monkeypatch.setattr(heads, "load", lambda path: Head())
    monkeypatch.setattr(readers, "load_split", _never)
    monkeypatch.setattr(diagnosis, "score_split", _never)
    monkeypatch.setattr(budget_curve, "load_split", _never)
    monkeypatch.setattr(readers, "policy_masks", _never)
    monkeypatch.setattr(diagnosis, "navigator_masks", _never)


def _one_error(capsys) -> str:
    err = [x for x in capsys.readouterr().err.strip().splitlines() if x.startswith("error")]
    assert len(err) == 1, err
    return err[0]


def _commands(dataset, run, out, split="test"):
    """``(name, main, argv)`` of each scorer taking a trained policy, scoring ``split`` of ``dataset``."""
    common = ["--dataset", str(dataset), "--out", str(out)]
    return [
        ("--reader", readers.main, [*common, "--head", "H", "--split", split, "--reader", "mine", str(run)]),
        ("--navigator", diagnosis.main, [*common, "--head", "H", "--split", split, "--navigator", "mine", str(run)]),
        ("--ppo", budget_curve.main, [*common, "--ppo", "mine", str(run), "--budgets", "0.5", "--seeds", "1"]),
    ]


def test_each_scorer_refuses_a_policy_on_its_training_slides_before_reading(cohort, tmp_path, no_reading, capsys):
    run = _run(tmp_path / "run", cohort["root"])
    for option, main, argv in _commands(cohort["root"], run, tmp_path / "o"):
        assert main(argv) == 2, option
        line = _one_error(capsys)
        assert line.startswith(f"error: {option} mine: {run / 'slides_seen.json'}: the policy was trained on 6"), line
        assert "--allow-fitting-slides" in line and not (tmp_path / "o").exists()


def test_a_policy_on_other_slides_reaches_the_reading(cohort, tmp_path, no_reading):
    """The same runs on the train split (slides the policy never saw): past every guard, to the reading."""
    run = _run(tmp_path / "run", cohort["root"])
    for option, main, argv in _commands(cohort["root"], run, tmp_path / "o", split="train"):
        if option == "--ppo":  # the curve scores the test split: a policy trained on the train split instead
            argv = [a if a != str(run) else str(_run(tmp_path / "train-run", cohort["root"], "train")) for a in argv]
        with pytest.raises(_Unread):
            main(argv)


def test_the_validation_slides_held_back_are_scored(cohort, tmp_path, no_reading):
    """A run on ``train_readers``' derived dataset (its training split minus a validation share): its validation set
    (the held-back slides as ``test``) is scored without the flag."""
    from baselines.reading.train_readers import split_dataset

    data = split_dataset(cohort["root"], tmp_path / "derived", 0.4, 0)
    run = _run(tmp_path / "run", data, "train")
    record = json.loads((run / "slides_seen.json").read_text())
    assert record["held_back"] and not set(record["held_back"]) & set(record["fitted"])
    for _, main, argv in _commands(data / "validation-set", run, tmp_path / "o")[:2]:
        with pytest.raises(_Unread):
            main(argv)


def test_the_flag_warns_and_marks_the_policy_beside_the_head(cohort, tmp_path, capsys):
    run = _run(tmp_path / "run", cohort["root"])
    spec = json.loads((cohort["root"] / "dataset.json").read_text())
    names = provenance.check_policy(run, cohort["root"], spec["test"], allow=True, option="--reader mine")
    assert names == sorted(cohort["names"]["test"])
    assert str(run / "slides_seen.json") in capsys.readouterr().err
    mark = provenance.with_seen({"self_scored": True, "scored_on_seen_slides": {"head": ["a"]}}, "policy mine", names)
    assert mark["self_scored"] is True and mark["scored_on_seen_slides"] == {"head": ["a"], "policy mine": names}
    assert provenance.mark_words(mark) == "head: a; policy mine: " + " ".join(names)
    assert provenance.with_seen({}, "policy mine", []) == {}  # nothing seen: nothing marked
    # RUN/params.msgpack names the same run; a folder recording nothing has seen nothing
    assert provenance.check_policy(run / "params.msgpack", cohort["root"], spec["test"], allow=True) == names
    assert provenance.check_policy(tmp_path / "elsewhere", cohort["root"], spec["test"]) == []


# ----------------------------------------------------------------------------- through a head (slow)
@pytest.fixture(scope="module")
def head(cohort, tmp_path_factory):
    """A learned head "fitted" on the train split (untrained), recording it: it may score the test split."""
    from baselines.reading import learned_head_fit as fit

    out = tmp_path_factory.mktemp("policy-scorers-head") / "h"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit, "train", untrained_fit)
        mp.setattr(fit, "check_head", lambda *a, **k: None)
        assert fit._main()(["--dataset", str(cohort["root"]), "--out", str(out), "--val-fraction", "0.4", *FAST]) == 0
    return out


def _read_all(run, dataset, slides, split="test", budgets=(), seeds=1, **kw):
    """A stub trained reader's masks: every tissue view, at each budget (no rollout)."""
    return {float(b): [[np.asarray(s["tissue"], bool) for s in slides]] for b in budgets}


@pytest.mark.slow  # reads the split and scores every scripted reader through the head (~20 s of compiling)
def test_readers_with_the_flag_mark_the_readers_slides(cohort, head, tmp_path, monkeypatch, capsys):
    run = _run(tmp_path / "run", cohort["root"])
    monkeypatch.setattr(readers, "policy_masks", _read_all)
    out = tmp_path / "r"
    argv = ["--dataset", str(cohort["root"]), "--head", str(head), "--reader", "mine", str(run), "--out", str(out)]
    argv += ["--budgets", "0.5", "--seeds", "1", "--allow-fitting-slides"]
    assert readers.main(argv) == 0
    assert str(run / "slides_seen.json") in capsys.readouterr().err
    record = json.loads((out / "readers.json").read_text())
    test = sorted(cohort["names"]["test"])
    assert record["self_scored"] is True and record["scored_on_seen_slides"] == {"policy mine": test}
    with open(out / "readers.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["scored_on_seen_slides"] == "policy mine: " + " ".join(test) for r in rows)


@pytest.mark.slow  # reads the split and scores every scripted reader through the head (~20 s of compiling)
def test_diagnosis_with_the_flag_marks_the_navigators_slides(cohort, head, tmp_path, monkeypatch):
    run = _run(tmp_path / "run", cohort["root"])
    monkeypatch.setattr(
        diagnosis, "navigator_masks", lambda run, ds, slides, *a, **k: _read_all(0, 0, slides, budgets=[1])
    )
    out = tmp_path / "d"
    argv = ["--dataset", str(cohort["root"]), "--head", str(head), "--navigator", "mine", str(run), "--out", str(out)]
    assert diagnosis.main([*argv, "--seeds", "1", "--allow-fitting-slides"]) == 0
    record = json.loads((out / "readers.json").read_text())
    assert record["scored_on_seen_slides"] == {"policy mine": sorted(cohort["names"]["test"])}


def test_budget_curve_with_the_flag_marks_the_rows_scored_on_the_policys_slides(cohort, tmp_path, monkeypatch):
    run = _run(tmp_path / "run", cohort["root"])
    seen = []

    def stub(train, test, budgets, policies=(), **kw):
        seen.extend(policies)
        one = {"fraction_read": 0.5, "auc": 0.5, "accuracy": 0.5, "slides": 1, "auc_std": 0.0, "accuracy_std": 0.0}
        return [{"method": "stub", "budget": b, "seeds": 1, **one} for b in budgets]

    monkeypatch.setattr(budget_curve, "budget_rows", stub)
    out = tmp_path / "bc"
    argv = ["--dataset", str(cohort["root"]), "--ppo", "mine", str(run), "--budgets", "0.5", "--out", str(out)]
    argv += ["--env", "HistoJAX-Easy-v0", "--glimpse-level", "1", "--seeds", "1", "--steps", "20"]
    assert budget_curve.main([*argv, "--allow-fitting-slides"]) == 0
    assert seen == [("mine", str(run))]
    with open(out / "budget_curve.csv") as f:
        rows = list(csv.DictReader(f))
    test = sorted(cohort["names"]["test"])
    assert rows and all(r["scored_on_seen_slides"] == "policy mine: " + " ".join(test) for r in rows), rows


def test_the_navigator_ceiling_refuses_a_head_on_its_own_slides(cohort, tmp_path, monkeypatch, capsys):
    """``experiments.navigator_ceiling`` (a head's readers at a navigator's ceiling) checks its head as every scorer
    does: refused on slides it was fitted on; with the flag, scored (up to the reading, stubbed)."""
    from experiments import navigator_ceiling
    from histojax.reading import heads

    class Head:
        info = json.dumps({"slides_seen": {"fitted": cohort["names"]["test"], "validation": []}})

    monkeypatch.setattr(heads, "load", lambda path: Head())
    monkeypatch.setattr(navigator_ceiling, "score_split", _never)
    argv = ["--dataset", str(cohort["root"]), "--head", str(tmp_path / "h"), "--out", str(tmp_path / "o")]
    assert navigator_ceiling.main(argv) == 2
    line = _one_error(capsys)
    assert "the head was fitted on 6 of the 6 slides" in line and "--allow-fitting-slides" in line, line
    with pytest.raises(_Unread):
        navigator_ceiling.main([*argv, "--allow-fitting-slides"])
