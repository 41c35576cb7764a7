"""The AUC interval every command prints: Newcombe's score interval, honest at AUC 1.0 on a few slides."""

import json
import math

import numpy as np
import pytest

from data_tools.metrics import (
    SMALL_SPLIT_PER_CLASS,
    auc_interval,
    format_auc,
    json_number,
    roc_auc,
    roc_auc_with_interval,
    small_split_warning,
)


def test_perfect_separation_on_six_slides_is_not_a_point():
    low, high = auc_interval(1.0, 2, 4)
    assert high == 1.0 and low < 0.6


def test_interval_holds_the_estimate_and_narrows_with_slides():
    widths = []
    for n in (4, 13, 50, 200):
        low, high = auc_interval(0.8, n, n)
        assert 0.0 <= low < 0.8 < high <= 1.0
        widths.append(high - low)
    assert widths == sorted(widths, reverse=True)


def test_interval_is_symmetric_under_label_swap():
    low, high = auc_interval(0.7, 10, 20)
    low2, high2 = auc_interval(0.3, 20, 10)
    assert math.isclose(low, 1 - high2, abs_tol=1e-9) and math.isclose(high, 1 - low2, abs_tol=1e-9)


def test_interval_covers_the_true_auc_about_95_percent_of_the_time():
    rng = np.random.default_rng(0)
    hits = 0
    trials = 400
    # normal scores N(0, 1), tumour N(1.2, 1): true AUC = Phi(1.2 / sqrt 2)
    true_auc = 0.5 * (1 + math.erf(1.2 / 2))
    for _ in range(trials):
        s = np.concatenate([rng.normal(1.2, 1, 15), rng.normal(0, 1, 20)])
        y = np.r_[np.ones(15), np.zeros(20)]
        r = roc_auc_with_interval(s, y)
        hits += r["auc_low"] <= true_auc <= r["auc_high"]
    assert 0.90 <= hits / trials <= 0.99


def test_one_class_gives_undefined_and_json_null():
    r = roc_auc_with_interval([0.1, 0.2], [1, 1])
    assert math.isnan(r["auc"]) and math.isnan(r["auc_low"])
    assert format_auc(r["auc"], r["auc_low"], r["auc_high"]) == "AUC undefined (one class)"
    text = json.dumps({k: json_number(v) for k, v in r.items()}, allow_nan=False)
    assert '"auc": null' in text


def test_format_and_agreement_with_roc_auc():
    s, y = [0.9, 0.8, 0.3, 0.2, 0.6], [1, 1, 0, 0, 0]
    r = roc_auc_with_interval(s, y)
    assert r["auc"] == roc_auc(s, y) and (r["n_tumour"], r["n_normal"]) == (2, 3)
    assert format_auc(r["auc"], r["auc_low"], r["auc_high"]).startswith("AUC 1.000 [0.")


def test_small_split_warning_names_counts_and_remedy():
    line = small_split_warning(2, 4, "the test split")
    assert "2 tumour and 4 normal" in line and "--folds" in line and "\n" not in line
    assert small_split_warning(SMALL_SPLIT_PER_CLASS, 40, "the test split") is None
    assert small_split_warning(40, SMALL_SPLIT_PER_CLASS - 1, "the test split") is not None


def test_other_levels_are_refused():
    with pytest.raises(ValueError):
        auc_interval(0.8, 10, 10, level=0.9)


def test_the_small_split_warning_states_the_interval_computed_at_its_counts():
    """It quotes the interval auc_interval gives at the split's own counts and its half-width, not an AUC measured."""
    low, high = auc_interval(0.85, 5, 7)
    line = small_split_warning(5, 7, "fold 1's validation share")
    assert f"[{low:.2f}, {high:.2f}]" in line and f"±{(high - low) / 2:.2f}" in line
    assert "near 0.85" in line and "an AUC of 0.85 on it" not in line
