"""The budget curve (``baselines.reading.budget_curve``): its rows on synthetic cell tables, its slide heads through
the one head protocol (the MIL is a ``learned-attention-mil`` head, the max-logit head a logit head), the score
reader of a learned head (``--head``) on the TRIDENT-layout cohort, and a scored split of one class refused."""

from __future__ import annotations

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_budget_rows_csv_and_png(tmp_path):
    from baselines.reading.budget_curve import budget_rows
    from baselines.reading.csv_files import write_curve_csv
    from baselines.reading.plots import plot_curve

    rng = np.random.default_rng(0)

    def slide(label):
        cell = np.repeat(np.arange(8), 4)
        x = rng.normal(size=(32, 3)).astype(np.float32)
        if label:
            x[cell == 5] += 3.0  # one cell of "tumour"
        low = np.stack([x[cell == c].mean(0) for c in range(8)])
        return {
            "instances": x,
            "instance_cell": cell,
            "cells": low,
            "valid": np.ones(8, bool),
            "cell_views": np.full(8, 4),
            "total": 32,
        }

    labels = np.array([0, 1] * 6)
    tables = [slide(y) for y in labels]
    rows = budget_rows((tables[:8], labels[:8]), (tables[8:], labels[8:]), budgets=(0.25, 0.5), seeds=2, steps=30)
    assert {r["method"] for r in rows} == {"MIL, read everything", "random reader + MIL", "attention reader + MIL"}
    assert all(r["fraction_read"] <= r["budget"] + 1e-9 and 0 <= r["auc"] <= 1 for r in rows)
    assert write_curve_csv(rows, tmp_path / "c.csv").read_text().count("\n") == len(rows) + 1
    assert plot_curve(rows, tmp_path / "c.png").stat().st_size > 1000


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_max_logit_rows_find_a_small_focus_that_attention_dilutes():
    """The max-pooling rows (a fixed instance logit, as pcam-cnn's ``max l``): one tumour view among 400 sets
    the slide's score; the logit reader reads the cell whose overview logit is highest first, so it finds the
    focus at the smallest budget; the calibration makes scores probabilities without changing their order."""
    from baselines.reading.budget_curve import (
        MAX_LOGIT_NAMES,
        bag_scores,
        bags,
        budget_rows,
        fit_max_logit,
        method_scores,
    )
    from data_tools.metrics import roc_auc
    from histojax.reading.heads.logit import statistic_batch

    rng = np.random.default_rng(0)

    def slide(label, k):
        cell = np.repeat(np.arange(20), 20)
        x = rng.normal(size=(400, 4)).astype(np.float32)
        x[:, 3] = rng.normal(-4.0, 1.0, 400)  # the logit: tissue far below 0
        if label:
            x[k * 20 + 3, 3] = 6.0  # one tumour view in cell k
        low = np.stack([x[cell == c].max(0) for c in range(20)])  # the overview sees the focus, faintly
        return {
            "instances": x,
            "instance_cell": cell,
            "cells": low,
            "valid": np.ones(20, bool),
            "cell_views": np.full(20, 20),
            "total": 400,
        }

    labels = np.array([0, 1] * 8)
    tables = [slide(y, i % 20) for i, y in enumerate(labels)]
    head = fit_max_logit(*bags(tables[:8]), labels[:8], dim=3)
    x, m = bags(tables[8:])
    raw = np.asarray(statistic_batch(head, x[:, :, None, 3], m[:, :, None]))  # the largest view logit read
    assert roc_auc(raw, labels[8:]) == 1.0
    assert np.array_equal(np.argsort(bag_scores(head, x, m)), np.argsort(raw))  # calibration keeps order
    assert ((bag_scores(head, x, m) > 0.5) == labels[8:]).all()
    scores = method_scores(head, tables[8:], budgets=(0.05,), seeds=3, names=MAX_LOGIT_NAMES)
    assert roc_auc(scores[(MAX_LOGIT_NAMES[2], 0.05)][0][0], labels[8:]) == 1.0  # one cell read: the right one
    rows = budget_rows(
        (tables[:8], labels[:8]), (tables[8:], labels[8:]), budgets=(0.05,), seeds=2, steps=30, max_dim=3
    )
    assert set(MAX_LOGIT_NAMES) <= {r["method"] for r in rows}


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_cross_validation_scores_every_slide_once():
    from baselines.reading.budget_curve import cross_validated_rows

    rng = np.random.default_rng(1)
    labels = np.array([0, 1] * 4)
    tables = []
    for y in labels:
        x = rng.normal(size=(8, 2)).astype(np.float32) + 2.0 * y
        tables.append(
            {
                "instances": x,
                "instance_cell": np.arange(8),
                "cells": x,
                "valid": np.ones(8, bool),
                "cell_views": np.ones(8, int),
                "total": 8,
            }
        )
    rows = cross_validated_rows(tables, labels, folds=2, budgets=(0.5,), seeds=1, steps=20)
    assert all(r["slides"] == 8 for r in rows) and len(rows) == 3


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_budget_curve_mil_is_the_heads_gated_attention():
    """The budget curve's "read everything" classifier is histojax.reading.heads.mil's gated attention (one MIL):
    its batched bag scores equal attention_pool on each bag alone, its attention sums to 1 and leaves unread
    instances at 0, and training separates bags whose tumour instances carry a signal."""
    from baselines.reading.budget_curve import bag_scores, train_mil
    from histojax.reading.heads.mil import attention_pool, attention_weights

    rng = np.random.default_rng(0)
    bags = rng.normal(size=(24, 12, 6)).astype(np.float32)
    masks = rng.random((24, 12)) < 0.8
    masks[:, 0] = True
    labels = np.arange(24) % 2
    bags[labels == 1, :3, 2] += 3.0
    head = train_mil(bags, masks, labels, steps=150)
    p = bag_scores(head, bags, masks)
    alone = [
        float(jax.nn.sigmoid(attention_pool(head.params, jnp.asarray(b), jnp.asarray(m))[0]))
        for b, m in zip(bags, masks)
    ]
    np.testing.assert_allclose(p, alone, rtol=1e-5, atol=1e-6)
    att = np.asarray(attention_weights(head.params, jnp.asarray(bags[1]), jnp.asarray(masks[1])))
    assert att.sum() == pytest.approx(1.0, abs=1e-5) and np.all(att[~masks[1]] == 0)
    assert p[labels == 1].min() > p[labels == 0].max()


# ----------------------------------------------------------------------------- on the TRIDENT-layout cohort
CURVE = ["--env", "HistoJAX-Easy-v0", "--glimpse-level", "1", "--seeds", "2", "--steps", "20"]


def planted_head(direction: np.ndarray):
    """A learned-attention-mil head whose per-view score is the planted tumour direction ``x · q₀`` of the cohort's
    features (two ReLU units, ``relu(x·q₀) − relu(−x·q₀)``) and whose attention is uniform: a slide's logit is the
    mean per-view score of the views read."""
    from histojax.reading.heads.learned import LearnedHead

    d = len(direction)
    q = jnp.asarray(direction, jnp.float32)
    params = {
        "mu": jnp.zeros(d),
        "sd": jnp.ones(d),
        "w1": jnp.stack([q, -q], 1),
        "b1": jnp.zeros(2),
        "V": jnp.zeros((2, 1)),
        "bV": jnp.zeros(1),
        "U": jnp.zeros((2, 1)),
        "bU": jnp.zeros(1),
        "wa": jnp.ones(1),
        "wc": jnp.asarray([1.0, -1.0]),
        "bc": jnp.zeros(()),
    }
    return LearnedHead(params=params, features_dim=d, hidden=2, attention=1, encoder="imported")


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    from learned_fixture import make_cohort

    return make_cohort(
        tmp_path_factory.mktemp("curve-cohort") / "ds",
        tumour=4,
        normal=4,
        test_tumour=3,
        test_normal=3,
        dim=16,
        signal=4.0,
        seed=1,
    )


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_the_score_reader_is_a_row_of_the_curve_of_a_learned_head(cohort, tmp_path):
    """``--head`` (a learned head: kind learned-attention-mil, per-view scores): its rows beside the MIL's, the score
    reader reading cells by the head's per-view score of their coarse features; on the planted cohort it reads the
    tumour cells first, so at 10 % it separates the slides as reading everything does, and better than at random."""
    from histojax.reading import heads

    head_dir = planted_head(cohort["direction"]).save(tmp_path / "head")
    assert heads.load(head_dir).kind == "learned-attention-mil"
    from baselines.reading import budget_curve

    out = tmp_path / "curve"
    assert (
        budget_curve.main(
            [
                "--dataset",
                str(cohort["root"]),
                *CURVE,
                "--budgets",
                "0.1",
                "0.5",
                "--head",
                str(head_dir),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = {(r["method"], float(r["budget"])): r for r in _rows(out / "budget_curve.csv")}
    methods = {m for m, _ in rows}
    assert {"MIL, read everything", "random reader + MIL", "attention reader + MIL"} <= methods
    assert {"learned head, read everything", "random reader + learned head", "score reader + learned head"} <= methods
    score = rows[("score reader + learned head", 0.1)]
    assert 0.0 < float(score["fraction_read"]) <= 0.1 + 1e-9 and int(score["slides"]) == 6
    assert float(rows[("learned head, read everything", 1.0)]["auc"]) == 1.0
    assert float(score["auc"]) == 1.0
    assert float(score["auc"]) >= float(rows[("random reader + learned head", 0.1)]["auc"])
    assert (out / "budget_curve.png").stat().st_size > 1000
    # one scoring path: the readers on the same cells (glimpse level 1 of Easy-v0 is bundle level 1) give the head's
    # rows the same figures, to the last digit (tests/reading/test_one_scoring_path.py: more budgets, a non-zero prior)
    from baselines.reading import readers

    assert (
        readers.main(
            [
                "--dataset",
                str(cohort["root"]),
                "--head",
                str(head_dir),
                "--split",
                "test",
                "--seeds",
                "2",
                "--cell-level",
                "1",
                "--budgets",
                "0.1",
                "0.5",
                "--out",
                str(tmp_path / "readers"),
            ]
        )
        == 0
    )
    mine = {(r["reader"], float(r["budget"])): r for r in _rows(tmp_path / "readers" / "readers.csv")}
    for reader, method in (
        ("random reader", "random reader + learned head"),
        ("score reader", "score reader + learned head"),
    ):
        for b in (0.1, 0.5):
            for field in ("auc", "auc_std", "auc_low", "auc_high", "fraction_read", "accuracy"):
                assert mine[(reader, b)][field] == rows[(method, b)][field], (reader, b, field)


def test_a_head_the_curve_cannot_score_as_a_set_is_one_line(cohort, tmp_path, capsys):
    """A logit head (neighbourhoods of the view grid) and a learned head of another feature length: one line naming
    the head's config.json, exit 2, nothing written."""
    from baselines.reading import budget_curve
    from histojax.reading.heads.logit import LogitHead

    logit = LogitHead(dim=0, k=3, encoder=None).save(tmp_path / "logit")
    other = planted_head(np.eye(8)[0]).save(tmp_path / "other")
    for head, words in ((logit, "pools neighbourhoods"), (other, "8-d features")):
        out = tmp_path / f"out-{head.name}"
        assert (
            budget_curve.main(
                ["--dataset", str(cohort["root"]), *CURVE, "--budgets", "0.5", "--head", str(head), "--out", str(out)]
            )
            == 2
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(head / "config.json") in err[0] and words in err[0], err
        assert not out.exists()


def test_the_curve_refuses_a_split_of_one_class(tmp_path, capsys):
    """A test split that ends with one class (here only tumour slides): one line naming dataset.json, AUC undefined,
    exit 2, nothing written; not a curve of AUC 1.000 or nan."""
    from learned_fixture import make_cohort

    from baselines.reading import budget_curve

    root = make_cohort(tmp_path / "ds", tumour=2, normal=2, test_tumour=2, test_normal=0, dim=8)["root"]
    out = tmp_path / "curve"
    assert budget_curve.main(["--dataset", str(root), *CURVE, "--budgets", "0.5", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(root / "dataset.json") in err[0], err
    assert "undefined: one class" in err[0] and "only tumour slides (2)" in err[0]
    assert not out.exists()
    # cross-validation over all slides holds both classes: it runs
    assert (
        budget_curve.main(["--dataset", str(root), *CURVE, "--budgets", "0.5", "--folds", "2", "--out", str(out)]) == 0
    )
