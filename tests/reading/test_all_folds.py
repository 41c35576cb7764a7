"""``--all-folds``: the budget curve and ``histojax evaluate`` run their one-fold path (``--fold I``) on every fold of a
dataset built with ``--folds K`` and report each figure as its mean ± std over folds (per-fold rows kept, a summary
row added); a dataset without folds is refused in one line, with nothing written."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
from fold_helpers import build_folded

from baselines import folds
from baselines.reading import budget_curve
from data_tools.datasets.build import write_dataset_index
from histojax.datasets import dataset_slides

CURVE = [
    "--env",
    "HistoJAX-Easy-v0",
    "--glimpse-level",
    "1",
    "--budgets",
    "0.25",
    "0.5",
    "--seeds",
    "1",
    "--steps",
    "20",
]


@pytest.fixture(scope="module")
def folded(tmp_path_factory):
    """7 slides (4 tumour, 3 normal; t0 and t1 one patient), the colour-stats feature grid, ``--folds 2``; and the
    same dataset without folds (``plain``)."""
    root = tmp_path_factory.mktemp("all-folds")
    out = build_folded(root, encoder="colour-stats")
    plain = root / "plain"
    shutil.copytree(out, plain)
    ds = json.loads((plain / "dataset.json").read_text())
    del ds["folds"]
    write_dataset_index(plain, ds)  # sealed again: a dataset built without --folds
    return out, plain


def test_mean_std_over_the_defined_folds():
    assert folds.mean_std([0.5, 1.0]) == (0.75, 0.25)
    assert folds.mean_std([0.5, float("nan"), 1.0]) == (0.75, 0.25)  # a fold without an AUC does not count
    m, s = folds.mean_std([float("nan")])
    assert m != m and s != s
    assert folds.with_fold("runs/ppo-fold{fold}", 3) == "runs/ppo-fold3" and folds.with_fold("runs/a", 3) == "runs/a"


def test_budget_curve_all_folds_refuses_a_dataset_without_folds(folded, tmp_path, capsys):
    _, plain = folded
    assert budget_curve.main(["--dataset", str(plain), *CURVE, "--all-folds", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--all-folds" in err and "dataset.json has no folds" in err, err
    assert "--folds K" in err and not (tmp_path / "o").exists()
    for extra in (["--fold", "0"], ["--folds", "2"]):
        assert (
            budget_curve.main(
                ["--dataset", str(folded[0]), *CURVE, "--all-folds", *extra, "--out", str(tmp_path / "o")]
            )
            == 2
        )
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"not with {extra[0]} {extra[1]}" in err, err
        assert not (tmp_path / "o").exists()


def test_budget_curve_all_folds_is_the_one_fold_path_on_every_fold(folded, tmp_path, monkeypatch, capsys):
    """Each fold's rows come from the one-fold path on that fold's sides (the head's training rows stubbed: the
    real head is the slow test's), and the ``mean`` rows are their mean ± std over folds."""
    out, _ = folded
    seen = []

    def rows_of_the_fold(train, test, budgets, fold=None, **kw):
        seen.append((fold, len(train[1]), len(test[1]), kw["policies"]))
        auc = 0.6 + 0.2 * fold  # 0.6 on fold 0, 0.8 on fold 1
        return [
            {
                "method": "random reader + MIL",
                "budget": b,
                "fraction_read": b,
                "auc": auc,
                "accuracy": 0.5,
                "slides": len(test[1]),
                "auc_std": 0.0,
                "accuracy_std": 0.0,
                "seeds": 1,
                "fields_of_view": float("nan"),
            }
            for b in budgets
        ]

    monkeypatch.setattr(budget_curve, "budget_rows", rows_of_the_fold)
    assert (
        budget_curve.main(
            [
                "--dataset",
                str(out),
                *CURVE,
                "--all-folds",
                "--ppo",
                "agent",
                "runs/ppo-fold{fold}",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    sizes = [len(dataset_slides(out, "test", i)) for i in range(2)]
    assert [s[:3] for s in seen] == [(0, 7 - sizes[0], sizes[0]), (1, 7 - sizes[1], sizes[1])]
    assert [s[3] for s in seen] == [[("agent", "runs/ppo-fold0")], [("agent", "runs/ppo-fold1")]]  # a run per fold
    with open(tmp_path / "budget_curve.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["fold"] for r in rows] == ["0", "0", "1", "1", "mean", "mean"]
    mean = [r for r in rows if r["fold"] == "mean"]
    assert [float(r["auc"]) for r in mean] == [0.7, 0.7] and [float(r["auc_std"]) for r in mean] == [0.1, 0.1]
    assert [int(r["slides"]) for r in mean] == [7, 7] and (tmp_path / "budget_curve.png").is_file()
    assert "mean ± std over folds" in capsys.readouterr().out


def test_budget_curve_without_all_folds_writes_no_fold_column(folded, tmp_path, monkeypatch):
    monkeypatch.setattr(
        budget_curve,
        "budget_rows",
        lambda train, test, budgets, **kw: [
            {
                "method": "MIL, read everything",
                "budget": 1.0,
                "fraction_read": 1.0,
                "auc": 1.0,
                "accuracy": 1.0,
                "slides": len(test[1]),
                "auc_std": 0.0,
                "accuracy_std": 0.0,
                "seeds": 1,
                "fields_of_view": float("nan"),
            }
        ],
    )
    assert budget_curve.main(["--dataset", str(folded[0]), *CURVE, "--fold", "1", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "budget_curve.csv").read_text().startswith("method,budget,")


@pytest.mark.slow  # two folds of the real head and readers, then --fold 1 alone: about a minute on 2 cores
def test_budget_curve_all_folds_rows_equal_the_fold_runs(folded, tmp_path):
    out, _ = folded
    assert budget_curve.main(["--dataset", str(out), *CURVE, "--all-folds", "--out", str(tmp_path / "all")]) == 0
    assert budget_curve.main(["--dataset", str(out), *CURVE, "--fold", "1", "--out", str(tmp_path / "one")]) == 0
    with open(tmp_path / "all" / "budget_curve.csv") as f:
        every = list(csv.DictReader(f))
    with open(tmp_path / "one" / "budget_curve.csv") as f:
        one = list(csv.DictReader(f))
    assert [{k: v for k, v in r.items() if k != "fold"} for r in every if r["fold"] == "1"] == one
    for r in (r for r in every if r["fold"] == "mean"):
        per = [
            float(x["auc"])
            for x in every
            if x["fold"] in ("0", "1") and x["method"] == r["method"] and x["budget"] == r["budget"]
        ]
        assert float(r["auc"]) == pytest.approx(np.mean(per), abs=1e-4)
        assert float(r["auc_std"]) == pytest.approx(np.std(per), abs=1e-4)


# ------------------------------------------------------------------ histojax evaluate --all-folds
def test_evaluate_all_folds_refuses_a_dataset_without_folds(folded, tmp_path, capsys):
    from baselines.evaluate import cli

    _, plain = folded
    for extra, words in (([], "dataset.json has no folds"), (["--fold", "0"], "not with --fold 0")):
        ds = plain if not extra else folded[0]
        assert (
            cli.main(
                ["--env", "HistoJAX-Easy-v0", "--dataset", str(ds), "--all-folds", *extra, "--out", str(tmp_path / "o")]
            )
            == 2
        )
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--all-folds" in err and words in err, err
        assert not (tmp_path / "o").exists()


def test_evaluate_all_folds_is_the_one_fold_run_on_every_fold(folded, tmp_path, monkeypatch, capsys):
    """Each fold is ``evaluate --fold I`` (its held-out side, in OUT/foldI; the rollouts stubbed: the real ones are
    the slow test's); OUT/eval.csv keeps each fold's rows and adds a mean and a std row per policy."""
    from baselines.evaluate import cli

    out, _ = folded
    seen = []

    def scored(config, params, out=None, **kw):  # config: the run's typed config (baselines.run_config)
        env_kwargs = config.env_kwargs
        seen.append((env_kwargs["fold"], env_kwargs["split"], env_kwargs["dataset"], out))
        f = env_kwargs["fold"]
        return {
            "random": {
                "episodes": 4,
                "success_rate": 0.25 + 0.5 * f,
                "mean_return": 1.0,
                "mean_length": 10.0,
                "mean_steps_to_success": float("nan"),
                "mean_fraction_read": 0.5,
                "mean_fields_of_view": 3.0,
                "diagnosis_auc": 0.6 + 0.2 * f,
                "diagnosis_tumour_slides": 2,
                "diagnosis_normal_slides": 3 + f,
            }
        }

    monkeypatch.setattr(cli, "evaluate", scored)
    assert (
        cli.main(
            [
                "--env",
                "HistoJAX-Easy-v0",
                "--dataset",
                str(out),
                "--all-folds",
                "--episodes",
                "4",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert [s[:3] for s in seen] == [(0, "test", str(out)), (1, "test", str(out))]
    assert [s[3] for s in seen] == [tmp_path / "fold0", tmp_path / "fold1"]
    assert all((tmp_path / f"fold{i}" / "eval.json").is_file() for i in range(2))  # each fold as --fold I writes it
    with open(tmp_path / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["fold"] for r in rows] == ["0", "1", "mean", "std"]
    mean, std = rows[2], rows[3]
    assert float(mean["success_rate"]) == 0.5 and float(std["success_rate"]) == 0.25
    assert float(mean["diagnosis_auc"]) == pytest.approx(0.7) and float(std["diagnosis_auc"]) == pytest.approx(0.1)
    assert mean["mean_steps_to_success"] == "" and mean["episodes"] == "8"  # undefined on every fold: empty
    record = json.loads((tmp_path / "eval.json").read_text())
    assert record["folds"] == 2 and [f["fold"] for f in record["per_fold"]] == [0, 1]
    assert record["summary"]["random"]["diagnosis_auc_std"] == pytest.approx(0.1)
    assert record["summary"]["random"]["mean_steps_to_success"] is None
    # the interval of the mean over the held-out slides of both folds pooled: 4 tumour, 7 normal
    from data_tools.metrics import auc_interval

    low, high = auc_interval(0.7, 4, 7)
    assert record["summary"]["random"]["diagnosis_auc_low"] == pytest.approx(low)
    assert float(mean["diagnosis_auc_high"]) == pytest.approx(high, abs=1e-6)
    printed = capsys.readouterr().out
    assert "mean ± std over 2 folds" in printed and f"diagnosis_auc 0.700 ± 0.100 [{low:.3f}, {high:.3f}]" in printed


def test_evaluate_fold_scores_the_folds_held_out_side(folded):
    from baselines.evaluate.cli import with_dataset

    out, _ = folded
    config = with_dataset({"env_id": "HistoJAX-Easy-v0", "env_kwargs": {}}, str(out), None, 1)
    assert config["env_kwargs"] == {"dataset": str(out), "split": "test", "fold": 1}
    trained = {"env_id": "HistoJAX-Easy-v0", "env_kwargs": {"dataset": str(out), "fold": 0}}
    assert with_dataset(trained, None, None, 1)["env_kwargs"]["fold"] == 1  # --fold I over the fold it trained on


@pytest.mark.slow  # two folds of real rollouts (random and scripted policies): about 1.5 minutes on 2 cores
def test_evaluate_all_folds_runs_the_reference_policies(folded, tmp_path):
    from baselines.evaluate import cli

    out, _ = folded
    assert (
        cli.main(
            [
                "--env",
                "HistoJAX-Easy-v0",
                "--dataset",
                str(out),
                "--all-folds",
                "--episodes",
                "2",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    record = json.loads((tmp_path / "eval.json").read_text())
    for policy in ("random", "scripted"):
        per = [json.loads((tmp_path / f"fold{i}" / "eval.json").read_text())["results"] for i in range(2)]
        reads = [next(iter(r.values()))[policy]["mean_fraction_read"] for r in per]
        assert record["summary"][policy]["mean_fraction_read"] == pytest.approx(np.mean(reads))
        assert record["summary"][policy]["mean_fraction_read_std"] == pytest.approx(np.std(reads))
