"""A split that ends with one class: said in the dataset summary, and refused (one line, exit 2, nothing written)
by what scores AUC on it instead of printing 1.000 or nan."""

from __future__ import annotations

import jax.numpy as jnp
from test_head import make_dataset

from baselines.reading import readers
from data_tools.datasets.cli import _report
from histojax.reading.heads.logit import LogitHead


def test_the_dataset_summary_says_a_split_holds_one_class(tmp_path, capsys):
    dataset = {
        "train": ["bundles/a", "bundles/b"],
        "test": ["bundles/c", "bundles/d"],
        "labels": {"a": 1, "b": 0, "c": 1, "d": 1},
    }
    _report(tmp_path, dataset, {"e": "unreadable"}, {})
    out = capsys.readouterr().out
    note = [line for line in out.splitlines() if "only" in line]
    assert len(note) == 1 and "test split holds only tumour slides (2; others failed)" in note[0]
    assert "AUC is undefined" in note[0] and "train split" not in out.split("note:")[-1]


def test_readers_refuse_a_one_class_split(tmp_path, capsys):
    ds = make_dataset(tmp_path / "ds", n_train=4, n_test=1)  # the test split: one tumour slide
    head = LogitHead(
        cal_a=jnp.float32(1.0),
        cal_b=jnp.float32(0.0),
        prior_logit=jnp.float32(0.0),
        dim=62,
        k=1,
        top=1,
        encoder="pcam-cnn",
    ).save(tmp_path / "head")
    out = tmp_path / "readers"
    assert readers.main(["--dataset", str(ds), "--head", str(head), "--split", "test", "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "loaded" not in line]
    assert len(err) == 1 and "needs tumour and normal slides" in err[0]
    assert not out.exists()
