"""A navigator rewarded by the slide head (``baselines.reading.train_readers --action-mode discrete``): trained with
the env wrapped in ``HeadReward`` (no reading budget), then scored on the validation slides by
``baselines.reading.diagnosis`` (the head declares from the finest views it stood on), beside a ``--compare``
navigator; and ``experiments.navigator_ceiling``: the fraction a ``max_steps`` episode can read, and the readers
at each slide's own ceiling.

Slides made here (no third-party data), by the helpers of ``test_evaluate_readers``: 512 × 640 px pyramidal
TIFFs, a dark lesion on two of them, a 64-d stand-in for pcam-cnn features whose entry 62 is a view logit."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from test_evaluate_readers import HEAD, _dataset, _slide

TRAINER = [
    "--set",
    "num_steps=8",
    "--set",
    "num_minibatches=1",
    "--set",
    "update_epochs=1",
    "--set",
    "hidden=16",
    "--set",
    "print_progress=false",
]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("nav-slides")
    bundles = [
        _slide(root, "t0", (512, 640), (200, 260, 120), 0),
        _slide(root, "t1", (512, 640), (100, 100, 160), 1),
        _slide(root, "n0", (512, 640), None, 2),
        _slide(root, "n1", (512, 640), None, 3),
    ]
    HEAD.save(root / "head")
    return {"set": _dataset(root / "set", bundles), "head": root / "head", "root": root}


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory) -> Path:
    """``train_readers`` in discrete mode, 1 seed, 64 env steps: exit 0, its output folder."""
    from baselines.reading import train_readers

    out = tmp_path_factory.mktemp("nav-run") / "out"
    code = train_readers.main(
        [
            "--dataset",
            str(data["set"]),
            "--head",
            str(data["head"]),
            "--out",
            str(out),
            "--action-mode",
            "discrete",
            "--seeds",
            "1",
            "--total-steps",
            "64",
            "--num-envs",
            "2",
            "--gain",
            "fidelity",
            "--final",
            "0",
            "--val-fraction",
            "0.5",
            "--",
            *TRAINER,
        ]
    )
    assert code == 0
    return out


def test_is_navigator():
    from baselines.reading.train_readers import is_navigator

    assert is_navigator("discrete") and is_navigator("continuous")
    assert not is_navigator("glimpse:1") and not is_navigator("zoom_select")


@pytest.mark.slow  # PPO and greedy-rollout compiles: ~1-6 min on 2 shared CPU cores
def test_navigator_is_trained_with_the_head_and_scored_on_validation(trained):
    reward = json.loads((trained / "ppo" / "head_reward.json").read_text())
    assert reward["action_mode"] == "discrete" and reward["read_budget"] is None and reward["gain"] == "fidelity"
    config = json.loads((trained / "ppo" / "config.json").read_text())
    assert config["action_mode"] == "discrete" and "read_budget" not in config["env_kwargs"]
    # scored on the validation slides only: the scoring folder's test split is the validation split
    derived = json.loads((trained / "dataset.json").read_text())
    scoring = json.loads((trained / "validation-set" / "dataset.json").read_text())
    assert scoring["test"] == derived["validation"] and len(derived["validation"]) == 2
    assert not set(derived["validation"]) & set(derived["train"])
    rows = list(csv.DictReader((trained / "validation" / "readers.csv").open()))
    nav = [r for r in rows if r["reader"] == "navigator (ppo, head reward) (head declares)"]
    assert len(nav) == 1 and int(nav[0]["slides"]) == 2
    assert 0.0 <= float(nav[0]["fraction_read"]) <= 1.0 and 0.0 <= float(nav[0]["auc"]) <= 1.0
    assert {"overview only", "read everything"} <= {r["reader"] for r in rows}


@pytest.mark.slow
def test_compare_navigator_is_scored_beside(trained, data, tmp_path):
    """``--skip-training`` re-scores the run; ``--compare`` adds another navigator's row (here the same run)."""
    from baselines.reading import train_readers

    out = tmp_path / "again"
    import shutil

    shutil.copytree(trained, out)
    assert (
        train_readers.main(
            [
                "--dataset",
                str(data["set"]),
                "--head",
                str(data["head"]),
                "--out",
                str(out),
                "--action-mode",
                "discrete",
                "--seeds",
                "1",
                "--val-fraction",
                "0.5",
                "--skip-training",
                "--compare",
                "twin",
                str(out / "ppo"),
            ]
        )
        == 0
    )
    rows = {r["reader"]: r for r in csv.DictReader((out / "validation" / "readers.csv").open())}
    a, b = rows["navigator (ppo, head reward) (head declares)"], rows["twin (head declares)"]
    assert a["auc"] == b["auc"] and a["fraction_read"] == b["fraction_read"]  # greedy: the same run, the same reads


@pytest.mark.slow
def test_head_diagnosis_scores_the_sampled_policy(trained, data, tmp_path, monkeypatch):
    """``head_diagnosis --sampled`` rolls the navigator's sampled policy (greedy=False, key = the seed) and says so in
    the row's name; its reads are those of ``navigator_reads(..., greedy=False)``."""
    from baselines.reading import diagnosis

    calls = []
    reads = diagnosis.navigator_reads

    def spy(*a, **kw):
        calls.append(kw.get("greedy"))
        return reads(*a, **kw)

    monkeypatch.setattr(diagnosis, "navigator_reads", spy)
    scoring = trained / "validation-set"
    assert (
        diagnosis.main(
            [
                "--dataset",
                str(scoring),
                "--head",
                str(data["head"]),
                "--navigator",
                "nav",
                str(trained / "ppo"),
                "--sampled",
                "--seeds",
                "2",
                "--out",
                str(tmp_path / "s"),
            ]
        )
        == 0
    )
    rows = {r["reader"]: r for r in csv.DictReader((tmp_path / "s" / "readers.csv").open())}
    assert calls == [False] and "nav (head declares, sampled)" in rows
    assert json.loads((tmp_path / "s" / "readers.json").read_text())["sampled"] is True


def test_ceiling_fractions():
    from experiments.navigator_ceiling import ceiling_fractions

    slides = [
        {"tissue": np.ones((10, 40), bool)},
        {"tissue": np.ones((5, 5), bool)},
        {"tissue": np.zeros((3, 3), bool)},
    ]
    np.testing.assert_allclose(ceiling_fractions(slides, 200), [0.5, 1.0, 1.0])
    np.testing.assert_allclose(ceiling_fractions(slides, 4), [0.01, 0.16, 1.0])


def test_ceiling_rows(data, tmp_path, capsys):
    """At a ceiling that covers every slide the per-slide-ceiling readers read everything (same AUC); at 40
    views they read at most 40 of each slide's tissue views (whole cells that fit)."""
    from experiments import navigator_ceiling

    for steps, out in ((10_000, tmp_path / "all"), (40, tmp_path / "few")):
        assert (
            navigator_ceiling.main(
                [
                    "--dataset",
                    str(data["set"]),
                    "--head",
                    str(data["head"]),
                    "--split",
                    "train",
                    "--max-steps",
                    str(steps),
                    "--budgets",
                    "0.05",
                    "--seeds",
                    "2",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
    full = {r["reader"]: r for r in csv.DictReader((tmp_path / "all" / "readers.csv").open())}
    for name in ("logit reader", "random reader", "search reader"):
        row = full[f"{name}, per-slide ceiling"]
        assert float(row["fraction_read"]) == pytest.approx(1.0) and row["auc"] == full["read everything"]["auc"]
    few = {r["reader"]: r for r in csv.DictReader((tmp_path / "few" / "readers.csv").open())}
    summary = json.loads((tmp_path / "few" / "ceiling.json").read_text())
    assert 40 / summary["tissue_views_max"] <= summary["ceiling_median"] <= 40 / summary["tissue_views_min"]
    for name in ("logit reader", "random reader", "search reader"):
        row = few[f"{name}, per-slide ceiling"]
        assert float(row["budget"]) == pytest.approx(summary["ceiling_median"], abs=1e-3)
        assert 0 < float(row["fraction_read"]) and float(row["fraction_max"]) <= summary["ceiling_max"] + 1e-9
    assert "per-slide ceiling" in capsys.readouterr().out


def test_ceiling_bad_input_is_one_line(data, tmp_path, capsys):
    from experiments import navigator_ceiling

    assert (
        navigator_ceiling.main(
            ["--dataset", str(tmp_path / "nope"), "--head", str(data["head"]), "--out", str(tmp_path / "o")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err and not (tmp_path / "o").exists()


def test_params_from_leaves():
    """The parameters are the first run of leaves with the network's shapes (seeds on axis 0), not the
    optimiser's moments after them; no such run is one ValueError."""
    from experiments.checkpoint_to_run import params_from_leaves

    template = {"dense": {"kernel": np.zeros((4, 3)), "bias": np.zeros(3)}}
    params = [np.full((2, 3), 1.0), np.full((2, 4, 3), 2.0)]  # flattened: bias, kernel (sorted keys)
    moments = [np.full((2, 3), 9.0), np.full((2, 4, 3), 9.0)]
    got = params_from_leaves(template, [np.zeros(2, np.int32), *params, *moments], 2)
    np.testing.assert_array_equal(got["dense"]["bias"], params[0])
    np.testing.assert_array_equal(got["dense"]["kernel"], params[1])
    with pytest.raises(ValueError, match="parameter shapes"):
        params_from_leaves(template, [np.zeros(2), np.zeros((2, 5))], 2)
