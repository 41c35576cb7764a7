"""Guards of the head fits and of scoring (one line naming the file, exit 2, nothing written half):

* ``head_mil_fit`` has the guards ``head_fit`` and ``learned_head_fit`` have: fewer than MIN_SLIDES_PER_CLASS training
  slides of a class refused with the minimum named; a chosen candidate whose validation AUC is below 0.5 or whose
  validation slope is negative refused, nothing saved;
* the encoder-scale warning ``dataset.json`` records (``encoder_scale``) is repeated by every head fit and by
  ``histojax evaluate``;
* a split of one class is refused by ``evaluate``'s head rows and by ``learned_head_fit --score`` ("undefined: one
  class"); an AUC left undefined after ITC-only slides are dropped is JSON null, never a bare NaN.

The stand-in pcam-cnn bundles of tests/reading/test_head.py and the TRIDENT-layout cohort of tests/learned_fixture.py."""

from __future__ import annotations

import json
import shutil

import jax
import jax.numpy as jnp
import pytest
from learned_fixture import make_cohort
from test_head import make_dataset

from baselines.reading import head_fit, head_mil_fit, learned_head_fit
from baselines.reading.fitting import MIN_SLIDES_PER_CLASS
from baselines.reading.slides import read_spec
from histojax.reading.heads.learned import LearnedHead, init_params

SCALE = {
    "encoder": "pcam-cnn",
    "encoder_mpp": 1.944,
    "tolerance": 1.5,
    "slides_out_of_scale": {"train_tumour_00_micro": 0.5, "train_normal_01": 0.5, "x": None},
}


def _err(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.strip().splitlines() if line and "loaded" not in line]


def _with_scale(ds):
    spec = json.loads((ds / "dataset.json").read_text())
    (ds / "dataset.json").write_text(json.dumps({**spec, "encoder_scale": SCALE}))
    return ds


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """6 training slides (3 per class): fewer than MIN_SLIDES_PER_CLASS of each once validation is held back."""
    return make_dataset(tmp_path_factory.mktemp("small") / "ds", n_train=6, n_test=2)


@pytest.fixture(scope="module")
def enough(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("enough") / "ds", n_train=20, n_test=2)


# ----------------------------------------------------------------------------- head_mil_fit's guards
def test_mil_fit_refuses_too_few_slides_per_class_before_reading(enough, tmp_path, capsys):
    out, cache = tmp_path / "head", tmp_path / "cache.npz"  # 10 per class, 6 of each held back: 4 < 5 to train on
    assert (
        head_mil_fit._main()(
            [
                "--dataset",
                str(enough),
                "--cache",
                str(cache),
                "--out",
                str(out),
                "--candidates",
                "stats",
                "--seeds",
                "1",
                "--val-fraction",
                "0.6",
            ]
        )
        == 2
    )
    err = _err(capsys)
    assert len(err) == 1 and "dataset.json" in err[0] and f"at least {MIN_SLIDES_PER_CLASS}" in err[0], err
    assert not out.exists() and not cache.exists()  # refused from dataset.json's labels: no slide read, no cache


@pytest.mark.parametrize(
    "full, slope, words", [(0.333, 1.0, "validation AUC is 0.333"), (0.9, -0.2, "slope is -0.200")]
)
def test_mil_fit_refuses_an_inverted_or_backwards_choice(enough, tmp_path, capsys, monkeypatch, full, slope, words):
    def fake(head, slides, shape, fractions=(0.1, 0.2), draws=5, seed=123):  # what validation measured
        return {"full": full, "slope": slope, **{f"read {f:g}": full for f in fractions}}

    monkeypatch.setattr(head_mil_fit, "validation_aucs", fake)
    out = tmp_path / "head"
    assert (
        head_mil_fit._main()(
            [
                "--dataset",
                str(enough),
                "--cache",
                str(tmp_path / "c.npz"),
                "--out",
                str(out),
                "--candidates",
                "stats",
                "--seeds",
                "1",
                "--val-fraction",
                "0.3",
            ]
        )
        == 2
    )
    err = [line for line in _err(capsys) if not line.startswith("  stats")]
    assert len(err) == 1 and words in err[0] and "nothing saved" in err[0] and "dataset.json" in err[0], err
    assert not out.exists()


def test_mil_validation_figures_carry_the_slope(enough, tmp_path):
    spec = read_spec(enough)
    slides = head_mil_fit.cache_grids(enough, spec["train"][:8], tmp_path / "c.npz", progress=False)
    shape = (max(s["tissue"].shape[0] for s in slides), max(s["tissue"].shape[1] for s in slides))
    from histojax.reading.heads.logit import LogitHead

    good = head_mil_fit.validation_aucs(LogitHead(k=1, top=1), slides, shape, fractions=(), draws=1)
    assert set(good) == {"full", "slope"} and good["slope"] > 0  # entry 62 is the stand-in's view logit


# ----------------------------------------------------------------------------- the scale warning, repeated
@pytest.mark.parametrize("fit", ["head_fit", "head_mil_fit", "learned_head_fit"])
def test_every_head_fit_repeats_the_scale_warning(small, tmp_path, capsys, fit):
    ds = _with_scale(shutil.copytree(small, tmp_path / "ds"))
    out = tmp_path / "head"
    argv = ["--dataset", str(ds), "--out", str(out)]
    main = {
        "head_fit": head_fit.main,
        "head_mil_fit": head_mil_fit._main(),
        "learned_head_fit": learned_head_fit._main(),
    }[fit]
    assert main(argv + (["--cache", str(tmp_path / "c.npz")] if fit == "head_mil_fit" else [])) == 2  # too few
    err = _err(capsys)
    warning = [line for line in err if line.startswith("warning:")]
    assert len(warning) == 1 and str(ds / "dataset.json") in warning[0], err
    assert "3 slide(s) are more than 1.5x from the 1.944 µm/px pcam-cnn" in warning[0]
    assert "train_tumour_00_micro at 0.5 µm/px" in warning[0]
    assert not out.exists()


def test_evaluate_repeats_the_scale_warning(tmp_path, capsys):
    from histojax.cli import main as histojax_main

    c = make_cohort(tmp_path / "ds", tumour=1, normal=1, test_tumour=1, test_normal=1, dim=8)
    ds = _with_scale(c["root"])
    code = histojax_main(
        [
            "evaluate",
            "--env",
            "HistoJAX-Reading-v0",
            "--action-mode",
            "glimpse:1",
            "--dataset",
            str(ds),
            "--split",
            "test",
            "--episodes",
            "1",
            "--out",
            str(tmp_path / "ev"),
        ]
    )
    err = _err(capsys)
    assert code == 2  # 3-level bundles under a 5-level id: refused after the warnings, in one line
    warning = [line for line in err if line.startswith("warning:")]
    assert len(warning) == 1 and str(ds / "dataset.json") in warning[0] and "pcam-cnn" in warning[0], err


# ----------------------------------------------------------------------------- one class: undefined
@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("one-class")
    c = make_cohort(root / "ds", tumour=1, normal=1, test_tumour=2, test_normal=2, dim=8, seed=3)
    head = LearnedHead(
        params=init_params(jax.random.PRNGKey(0), 8, 4, 4, 1),
        features_dim=8,
        hidden=4,
        attention=4,
        prior_logit=jnp.float32(0.0),
    )
    head.save(root / "head")
    spec = json.loads((c["root"] / "dataset.json").read_text())
    one = shutil.copytree(c["root"], root / "one")
    (one / "dataset.json").write_text(json.dumps({**spec, "test": [e for e in spec["test"] if "tumour" in e]}))
    return {"ds": c["root"], "one": one, "head": root / "head"}


def test_score_refuses_a_split_of_one_class(cohort, capsys):
    assert (
        learned_head_fit._main()(
            ["--dataset", str(cohort["one"]), "--score", str(cohort["head"]), "--split", "test", "--quiet"]
        )
        == 2
    )
    err = _err(capsys)
    assert len(err) == 1 and "undefined: one class" in err[0] and str(cohort["one"] / "dataset.json") in err[0], err


def test_score_writes_null_for_an_auc_one_class_leaves_undefined(cohort, capsys, monkeypatch):
    monkeypatch.setattr(
        learned_head_fit,
        "lesion_classes",  # every tumour slide ITC-only: no tumour once they go
        lambda slides: ["ITC" if s["label"] else "normal" for s in slides],
    )
    assert (
        learned_head_fit._main()(
            ["--dataset", str(cohort["ds"]), "--score", str(cohort["head"]), "--split", "test", "--quiet"]
        )
        == 0
    )
    line = capsys.readouterr().out.strip().splitlines()[-1]
    record = json.loads(line, parse_constant=lambda c: pytest.fail(f"bare {c} in the JSON: {line}"))
    assert record["auc_without_itc"] is None and "undefined: one class" in record["auc_without_itc_note"]
    assert 0.0 <= record["auc"] <= 1.0
    assert set(record["found"]) == {"ITC"} and record["found"]["ITC"].endswith("/2")


def test_found_above_every_normal_slide_counts_per_class():
    from baselines.reading.learned_head_fit import found_above_normal

    classes = ["normal", "normal", "macro", "micro", "micro", "ITC"]
    assert found_above_normal([0.0, 1.0, 2.0, 1.0, 3.0, -1.0], classes) == {
        "ITC": "0/1",
        "micro": "1/2",
        "macro": "1/1",
    }


def test_evaluate_refuses_head_rows_on_one_class(cohort):
    """Was: the head rows ran and printed 'undef.' for every AUC; now refused before any episode, one line naming
    dataset.json."""
    from baselines.evaluate.scoring import evaluate
    from data_tools.errors import HistojaxDataError
    from histojax.reading import heads

    config = {
        "env_id": "HistoJAX-Reading-v0",
        "action_mode": "glimpse:1",
        "obs_mode": "features",
        "hidden": 8,
        "env_kwargs": {"dataset": str(cohort["one"]), "split": "test", "n_levels": 3, "read_budget": 0.2},
    }
    with pytest.raises(HistojaxDataError, match="undefined: one class") as e:
        evaluate(config, None, num_episodes=1, head=heads.load(cohort["head"]))
    assert str(e.value).startswith(str(cohort["one"] / "dataset.json")) and len(str(e.value).splitlines()) == 1
    assert "only tumour slides (2)" in str(e.value)


@pytest.mark.slow  # a whole MIL fit (about 25 s on 2 cores); the record's default tests: test_head_provenance.py, test_head.py
def test_mil_fit_records_the_slides_it_was_fitted_and_chosen_on(enough, tmp_path):
    out = tmp_path / "head"
    assert (
        head_mil_fit._main()(
            [
                "--dataset",
                str(enough),
                "--cache",
                str(tmp_path / "c.npz"),
                "--out",
                str(out),
                "--candidates",
                "stats",
                "--seeds",
                "1",
                "--val-fraction",
                "0.3",
            ]
        )
        == 0
    )
    seen = json.loads((out / "config.json").read_text())["slides_seen"]
    spec = json.loads((enough / "dataset.json").read_text())
    assert seen["fitted"] == sorted(e.split("/")[-1] for e in spec["train"]) and len(seen["validation"]) == 6
    assert seen["split"] == "train" and seen["fold"] is None and "seal" in seen["dataset"]
