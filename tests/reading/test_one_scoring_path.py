"""One scoring path: ``readers`` and ``budget-curve`` give a reader the same AUC, to the last digit, for the same head,
slides, budgets and cells, both say which cells they read, and both write the AUC's 95 % interval; on the small
TRIDENT-layout cohort of tests/learned_fixture.py (6 test slides) with the planted head of test_budget_curve."""

from __future__ import annotations

import csv
import json

import jax.numpy as jnp
import numpy as np
import pytest
from learned_fixture import make_cohort
from test_budget_curve import planted_head

BUDGETS = ["0.05", "0.1", "0.5"]


pytestmark = pytest.mark.slow  # both commands end to end, ~20 CPU-s; the default cover of the same-AUC rule is
# test_budget_curve.py::test_the_score_reader_is_a_row_of_the_curve_of_a_learned_head (readers beside the curve)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """The cohort, its planted head, and the two commands' outputs on its test split at bundle level 1 (the glimpse
    level 1 of HistoJAX-Easy-v0 is bundle level 1 of the fixture's bundles)."""
    from baselines.reading import budget_curve, readers

    root = tmp_path_factory.mktemp("one-path")
    cohort = make_cohort(root / "ds", tumour=4, normal=4, test_tumour=3, test_normal=3, dim=16, signal=4.0, seed=1)
    # a prior that is not the score of an all-zero view: a slide with nothing read (5 %: a first cell larger than the
    # budget) scored its prior in the readers and a zero feature vector in the curve, which changed the ranking
    head = planted_head(cohort["direction"]).replace(prior_logit=jnp.float32(0.2)).save(root / "head")
    import contextlib
    import io

    printed = {}
    for name, call in (
        (
            "readers",
            lambda: readers.main(
                [
                    "--dataset",
                    str(cohort["root"]),
                    "--head",
                    str(head),
                    "--split",
                    "test",
                    "--seeds",
                    "3",
                    "--cell-level",
                    "1",
                    "--budgets",
                    *BUDGETS,
                    "--out",
                    str(root / "readers"),
                ]
            ),
        ),
        (
            "curve",
            lambda: budget_curve.main(
                [
                    "--dataset",
                    str(cohort["root"]),
                    "--env",
                    "HistoJAX-Easy-v0",
                    "--glimpse-level",
                    "1",
                    "--seeds",
                    "3",
                    "--steps",
                    "5",
                    "--budgets",
                    *BUDGETS,
                    "--head",
                    str(head),
                    "--out",
                    str(root / "curve"),
                ]
            ),
        ),
    ):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            assert call() == 0, err.getvalue()
        printed[name] = (out.getvalue(), err.getvalue())
    with open(root / "readers" / "readers.csv") as f:
        mine = {(r["reader"], r["budget"]): r for r in csv.DictReader(f)}
    with open(root / "curve" / "budget_curve.csv") as f:
        curve = {(r["method"], r["budget"]): r for r in csv.DictReader(f)}
    return {"readers": mine, "curve": curve, "printed": printed, "root": root}


PAIRS = [("random reader", "random reader + learned head"), ("score reader", "score reader + learned head")]


def test_readers_and_the_budget_curve_give_a_reader_the_same_auc(both):
    compared = 0
    for reader, method in PAIRS:
        for b in BUDGETS:
            r, c = both["readers"][(reader, f"{float(b):.4f}")], both["curve"][(method, f"{float(b):.4f}")]
            for field in ("auc", "auc_std", "auc_low", "auc_high", "fraction_read", "accuracy", "seeds"):
                assert r[field] == c[field], (reader, b, field, r[field], c[field])
            compared += 1
    r, c = both["readers"][("read everything", "1.0000")], both["curve"][("learned head, read everything", "1.0000")]
    assert r["auc"] == c["auc"] and r["auc_low"] == c["auc_low"]
    assert compared == 6


def test_both_print_the_cells_they_read(both):
    for name in ("readers", "curve"):
        out = both["printed"][name][0]
        assert "cells: " in out and "bundle level 1 (downsample 4" in out, out


def test_both_write_the_interval_and_warn_of_the_small_split(both):
    for name in ("readers", "curve"):
        err = both["printed"][name][1]
        assert sum("3 tumour and 3 normal slides" in line for line in err.splitlines()) == 1, err
    every = both["curve"][("learned head, read everything", "1.0000")]
    assert float(every["auc"]) == 1.0 and float(every["auc_high"]) == 1.0 and float(every["auc_low"]) < 0.7
    assert "AUC 1.000 [0." in both["printed"]["readers"][0]
    assert "fields_of_view" not in next(iter(both["curve"].values()))  # always empty without a policy: not written
    text = (both["root"] / "readers" / "readers.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    rows = json.loads(text)["rows"]
    assert all(np.isfinite(r["auc_low"]) and r["auc_low"] <= r["auc"] <= r["auc_high"] for r in rows)
