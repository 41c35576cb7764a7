"""The logit head fit (baselines.reading.head_fit) refuses, in one line naming dataset.json and saving nothing,
a chosen head whose validation AUC is below 0.5 or whose calibration slope is not positive, and fewer training
slides per class than MIN_SLIDES_PER_CLASS (the stand-in pcam-cnn bundles of tests/reading/test_head.py)."""

from __future__ import annotations

import pytest
from test_head import make_dataset

from baselines.reading import fitting, head_fit
from baselines.reading.slides import HeadDataError


def test_check_head_refuses_inverted_and_negative_slopes(tmp_path):
    with pytest.raises(HeadDataError, match=r"validation AUC is 0\.333 \(< 0\.5") as e:
        fitting.check_head(tmp_path, 0.333, 1.0)
    assert str(e.value).startswith(str(tmp_path / "dataset.json")) and len(str(e.value).splitlines()) == 1
    with pytest.raises(HeadDataError, match=r"slope is -0\.208"):
        fitting.check_head(tmp_path, 0.9, -0.208)
    with pytest.raises(HeadDataError, match="AUC is nan"):
        fitting.check_head(tmp_path, float("nan"), 1.0)
    fitting.check_head(tmp_path, 0.5, 0.1)  # accepted


def test_too_few_slides_per_class_is_refused_naming_the_minimum(tmp_path, capsys):
    ds = make_dataset(tmp_path / "ds", n_train=20, n_test=2)  # 10 per class, 6 each held back: 4 < 5
    out = tmp_path / "head"
    assert head_fit.main(["--dataset", str(ds), "--out", str(out), "--ks", "1", "--val-fraction", "0.6"]) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "loaded" not in line]  # progress
    assert len(err) == 1 and "dataset.json" in err[0] and f"at least {fitting.MIN_SLIDES_PER_CLASS}" in err[0]
    assert not out.exists()


def test_an_inverted_choice_is_refused_and_nothing_saved(tmp_path, capsys, monkeypatch):
    ds = make_dataset(tmp_path / "ds", n_train=20, n_test=2)
    real = head_fit.choose

    def inverted(train, val, cands):  # the entry read ranks tumour below normal on validation
        best, table = real(train, val, cands)
        return best, [{**r, "validation_auc": 0.333} for r in table]

    monkeypatch.setattr(head_fit, "choose", inverted)
    out = tmp_path / "head"
    assert head_fit.main(["--dataset", str(ds), "--out", str(out), "--ks", "1", "--val-fraction", "0.3"]) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "loaded" not in line]  # progress
    assert len(err) == 1 and "validation AUC is 0.333" in err[0] and "nothing saved" in err[0]
    assert not out.exists()
