"""The slide-level metrics: the AUC counted by sorting equals the pairwise count, runs on a million scores, and
inputs no figure can be measured on are refused in one line while one class stays an explicit "undefined"."""

import time

import numpy as np
import pytest

from data_tools.metrics import (
    MetricInputError,
    accuracy,
    auc_interval,
    auc_over_runs,
    format_auc,
    roc_auc,
    roc_auc_with_interval,
)


def pairwise_auc(scores, labels) -> float:
    """The definition: P(positive > negative) + P(tie) / 2 over every pair (an n⁺ × n⁻ matrix)."""
    s, y = np.asarray(scores, np.float64), np.asarray(labels).astype(bool)
    pos, neg = s[y], s[~y]
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


@pytest.mark.parametrize("seed", range(20))
def test_auc_by_sorting_equals_the_pairwise_count_with_ties(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 400))
    levels = int(rng.integers(1, 12))  # few distinct scores: many ties, inside and across classes
    scores = rng.integers(0, levels, n) / max(levels - 1, 1) if seed % 2 else rng.random(n)
    labels = rng.random(n) < rng.uniform(0.1, 0.9)
    labels[:2] = [True, False]  # both classes
    assert roc_auc(scores, labels) == pairwise_auc(scores, labels)


def test_auc_counts_negative_and_positive_zero_as_tied():
    assert roc_auc([0.0, -0.0], [1, 0]) == 0.5 == pairwise_auc([0.0, -0.0], [1, 0])


def test_auc_of_a_million_scores_in_seconds():
    # the pairwise matrix would hold 2.5 × 10¹¹ cells (MemoryError); by sorting: well under a second, O(n) memory.
    # Known construction: positives score i + 0.5 for i < 500 000, negatives score j: positive i beats the
    # i + 1 negatives 0..i, so U = Σ (i + 1) = n (n + 1) / 2 and AUC = (n + 1) / (2 n).
    n = 500_000
    scores = np.concatenate([np.arange(n) + 0.5, np.arange(n, dtype=np.float64)])
    labels = np.concatenate([np.ones(n, bool), np.zeros(n, bool)])
    start = time.perf_counter()
    auc = roc_auc(scores, labels)
    assert time.perf_counter() - start < 10.0
    assert auc == (n + 1) / (2 * n)
    # and all tied: one half exactly
    assert roc_auc(np.zeros(2 * n), labels) == 0.5


def test_one_class_is_undefined_not_refused():
    assert np.isnan(roc_auc([0.1, 0.2], [1, 1]))
    assert np.isnan(roc_auc([], []))
    assert format_auc(roc_auc([0.3], [0]), float("nan"), float("nan")) == "AUC undefined (one class)"
    r = roc_auc_with_interval([0.1, 0.2], [0, 0])
    assert np.isnan(r["auc"]) and np.isnan(r["auc_low"]) and (r["n_tumour"], r["n_normal"]) == (0, 2)
    assert all(np.isnan(v) for v in auc_interval(float("nan"), 3, 4))
    assert all(np.isnan(v) for v in auc_interval(0.8, 0, 4))


@pytest.mark.parametrize(
    "scores, labels, words",
    [
        ([0.1, 0.2, 0.3], [0, 1], "3 scores but 2 labels"),
        ([0.1, float("nan"), 0.3], [0, 1, 1], "NaN or infinite scores: 1 of 3 (first at index 1"),
        ([0.1, float("inf")], [0, 1], "NaN or infinite scores"),
        ([-float("inf"), 0.2], [0, 1], "NaN or infinite scores"),
        ([0.1, 0.2, 0.3], [0, 1, 2], "labels other than 0/1: 1 of 3 (first at index 2"),
        ([0.1, 0.2], [0, float("nan")], "labels other than 0/1"),
        ([[0.1, 0.2]], [0, 1], "must be 1-D"),
        (["a", "b"], [0, 1], "scores are not numbers"),
    ],
)
def test_degenerate_inputs_are_refused_in_one_line(scores, labels, words):
    for measure in (roc_auc, accuracy, roc_auc_with_interval):
        with pytest.raises(MetricInputError, match="^[^\n]*$") as err:
            measure(scores, labels)
        assert words in str(err.value)
        assert isinstance(err.value, ValueError)


def test_runs_of_the_wrong_length_or_with_nan_are_refused():
    with pytest.raises(MetricInputError, match="3 scores but 2 labels"):
        auc_over_runs([[0.1, 0.2, 0.3]], [0, 1])
    with pytest.raises(MetricInputError, match="NaN or infinite"):
        auc_over_runs([[0.1, 0.2], [0.3, float("nan")]], [0, 1])
    assert auc_over_runs([[0.1, 0.9], [0.9, 0.1]], [0, 1])["auc"] == 0.5


@pytest.mark.parametrize(
    "auc, n_pos, n_neg, words",
    [
        (1.5, 3, 4, "an AUC lies in [0, 1], not 1.5"),
        (float("inf"), 3, 4, "an AUC lies in [0, 1], not inf"),
        (-0.1, 3, 4, "an AUC lies in [0, 1]"),
        (0.8, -1, 4, "n_pos must be a count of slides"),
        (0.8, 3, 2.5, "n_neg must be a count of slides"),
    ],
)
def test_interval_refuses_what_is_not_an_auc_or_a_count(auc, n_pos, n_neg, words):
    with pytest.raises(MetricInputError) as err:
        auc_interval(auc, n_pos, n_neg)
    assert words in str(err.value)
