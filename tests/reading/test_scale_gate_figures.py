"""The figures of the scale gate (experiments/c16_scale_gate.py): lesions found above every normal slide, the paired
AUC difference of two scales over the same slides, and the view-logit entry of the pcam-cnn family."""

import json

import numpy as np
import pytest

from baselines.reading.budget_curve import PCAM_CNN_VIEW_LOGIT, view_logit_dim
from experiments.c16_scale_gate import ceiling_rule, found, paired_difference, plot_scales


def test_found_counts_tumour_slides_above_the_highest_normal_slide():
    scores = np.array([0.9, 0.2, 0.5, 0.6, 0.1, 0.55])
    classes = ["macro", "micro", "micro", "normal", "normal", "ITC"]
    assert found(scores, classes) == {"ITC": 0, "micro": 0, "macro": 1}
    assert found(scores + np.array([0, 0, 0.2, 0, 0, 0.1]), classes) == {"ITC": 1, "micro": 1, "macro": 1}


def test_paired_difference_of_identical_scales_is_zero_and_a_better_scale_is_positive():
    rng = np.random.default_rng(0)
    y = np.array([1] * 12 + [0] * 18)
    weak = rng.normal(size=(3, 30)) + 0.5 * y
    same = paired_difference(weak, weak, y, reps=200)
    assert same == {"diff": 0.0, "low": 0.0, "high": 0.0}
    strong = weak + 3.0 * y
    lift = paired_difference(weak, strong, y, reps=200)
    assert lift["diff"] > 0.1 and 0.0 < lift["low"] <= lift["diff"] <= lift["high"]


@pytest.mark.parametrize("encoder, dim", [("pcam-cnn", PCAM_CNN_VIEW_LOGIT), ("pcam-cnn96", PCAM_CNN_VIEW_LOGIT),
                                          ("colour-stats", None)])  # fmt: skip
def test_view_logit_entry_is_known_for_the_pcam_cnn_family_only(tmp_path, encoder, dim):
    (tmp_path / "dataset.json").write_text(json.dumps({"encoder": encoder}))
    assert view_logit_dim(tmp_path) == dim


def _methods(rows):
    return {m: {k: {"auc": a, "found_mean": {"micro": f}} for k, (a, f) in zip(("coarse", "native"), pair)}
            for m, pair in rows.items()}  # fmt: skip


def test_gate_is_on_the_best_head_of_each_scale_not_a_weak_head_catching_up():
    # the learned head gains 0.07 but stays under the logit head, whose best is not lifted: the ceiling is unchanged
    weak_catches_up = _methods({"logit head": ((0.94, 9), (0.93, 9)), "learned head": ((0.79, 3), (0.86, 4)),
                                "encoder top3": ((0.90, 5), (0.99, 12))})  # fmt: skip
    ceiling, lift, micro, go = ceiling_rule(weak_catches_up)
    assert not go and ceiling["native"]["head"] == "logit head" and lift == pytest.approx(-0.01) and micro == 0
    assert ceiling_rule(_methods({"logit head": ((0.90, 9), (0.935, 9))}))[3]  # +0.035 AUC
    assert ceiling_rule(_methods({"logit head": ((0.94, 9), (0.93, 11))}))[3]  # two more micrometastases


def test_plot_of_both_scales_is_written(tmp_path):
    names, classes = ["Normal_001", "Normal_002", "Tumor_001"], ["normal", "normal", "micro"]
    scores = {k: {"scores": {n: [float(i)] for i, n in enumerate(names)}} for k in ("coarse", "native")}
    plot_scales({"methods": {"logit head": scores}}, names, classes, tmp_path / "gate.png")
    assert (tmp_path / "gate.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
