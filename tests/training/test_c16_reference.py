"""experiments/c16_reference.py on a tiny semi-synthetic dataset: the table, resumable cells, bad
input; every method end to end (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import c16_reference

SHORT = {"max_steps_in_episode": 10}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, colour_feature_grid):
    from data_tools.datasets.synth.dataset import make_dataset

    root = tmp_path_factory.mktemp("c16ref") / "ds"
    spec = make_dataset(
        root,
        n_slides=4,
        size=(256, 256),
        seed=1,
        tile_size=32,
        level_sets=(3,),
        progress=False,
        previews=False,
        test_fraction=0.5,
    )
    assert len(spec["test"]) == 2
    for s in spec["slides"]:
        colour_feature_grid(root / s["bundle"])
    return root


def _argv(dataset, out, *extra):
    return [
        "--dataset",
        str(dataset),
        "--out",
        str(out),
        "--episodes",
        "8",
        "--seeds",
        "1",
        "--env",
        "Easy=HistoJAX-Easy-v0",
        "--env-kwargs",
        f"Easy={json.dumps(SHORT)}",
        "--env",
        "Diagnosis=HistoJAX-Easy-v0",
        "--env-kwargs",
        f"Diagnosis={json.dumps({**SHORT, 'task': 'classification'})}",
        *extra,
    ]


def test_reference_rows_are_written_and_kept_on_a_rerun(dataset, tmp_path, monkeypatch):
    out = tmp_path / "ref"
    assert c16_reference.main(_argv(dataset, out, "--methods", "random", "scripted", "--scenarios", "Easy")) == 0
    cells = json.loads((out / "reference.json").read_text())["cells"]
    assert set(cells) == {"random/Easy", "scripted/Easy"}
    for c in cells.values():
        assert c["episodes"] == 8 and 0.0 <= c["success_rate"] <= 1.0 and c["mean_length"] <= 10
        by = c["by_slide"]  # episodes of the two test slides counted apart
        assert len(by) <= 2 and sum(v["episodes"] for v in by.values()) == 8
        assert sum(v["successes"] for v in by.values()) == round(8 * c["success_rate"])
        assert c["tumour_slides"]["success_rate"] == c["success_rate"]  # synth: every slide has tumour
    table = (out / "reference.md").read_text()
    assert "| random |" in table and "Easy success" in table and "test split: 2 slides, 2 with tumour" in table

    # a rerun with the same budget keeps every cell; another budget recomputes
    def recompute(*args, **kwargs):
        raise RuntimeError("recomputed")

    monkeypatch.setattr(c16_reference, "reference_cells", recompute)
    assert c16_reference.main(_argv(dataset, out, "--methods", "random", "scripted", "--scenarios", "Easy")) == 0
    with pytest.raises(RuntimeError, match="recomputed"):
        c16_reference.main(_argv(dataset, out, "--methods", "random", "--scenarios", "Easy", "--episodes", "4"))


def test_bad_dataset_and_arguments_are_one_line_errors(tmp_path):
    with pytest.raises(SystemExit, match="cannot read dataset.json"):
        c16_reference.main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o")])
    (tmp_path / "dataset.json").write_text(json.dumps({"train": ["a"], "test": []}))
    with pytest.raises(SystemExit, match="non-empty 'train' and 'test'"):
        c16_reference.main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit, match="SCENARIO=VALUE"):
        c16_reference.main(["--dataset", str(tmp_path), "--env", "Tiny=HistoJAX-Easy-v0"])


def test_detection_success_counts_tumour_slides_only():
    spec = {"slides": [{"bundle": "bundles/T1", "label": 1}, {"bundle": "bundles/N1", "label": 0}]}
    labels = c16_reference.slide_labels(spec)
    assert labels == {"T1": 1, "N1": 0}
    assert c16_reference.slide_labels({"labels": {"bundles/A": 0}}) == {"A": 0}
    row = {
        "episodes": 10,
        "success_rate": 0.3,
        "mean_steps_to_success": 5.0,
        "by_slide": {
            "T1": {"episodes": 4, "successes": 3, "steps_to_success_sum": 15.0},
            "N1": {"episodes": 6, "successes": 0, "steps_to_success_sum": 0.0},
        },
    }
    assert c16_reference.on_tumour_slides(row, labels) == {
        "episodes": 4,
        "success_rate": 0.75,
        "mean_steps_to_success": 5.0,
    }
    # no normal slide among those drawn (or one slide): the row as it is
    assert c16_reference.on_tumour_slides(row, {})["success_rate"] == 0.3


@pytest.mark.slow
def test_every_method_end_to_end_on_a_tiny_budget(dataset, tmp_path):
    out = tmp_path / "ref"
    argv = _argv(
        dataset,
        out,
        "--scenarios",
        "Easy",
        "Diagnosis",
        "--steps",
        "256",
        "--set",
        "num_envs=8",
        "--set",
        "num_steps=16",
        "--set",
        "hidden=16",
        "--set",
        "num_minibatches=2",
        "--seeds",
        "2",
    )
    assert c16_reference.main(argv) == 0
    cells = json.loads((out / "reference.json").read_text())["cells"]
    expected = {f"{m}/{s}" for m in c16_reference.METHODS for s in ("Easy", "Diagnosis")} - {"scripted/Diagnosis"}
    assert set(cells) == expected
    for key, c in cells.items():
        assert 0.0 <= c["success_rate"] <= 1.0, key
        if key.split("/")[0] not in c16_reference.REFERENCE:
            assert (Path(c["run"]) / "params.msgpack").is_file() and "greedy" in c
            # trained on the kept training slides, scored on the held-back one too; mean ± std over 2 seeds
            assert c["validation"]["episodes"] == 16 and Path(c["curve_csv"]).is_file()
            headline = "accuracy" if key.endswith("Diagnosis") else "success"
            assert len(c["seeds"][headline]["per_seed"]) == 2 and c["seeds"][headline]["std"] >= 0
            if key.endswith("Diagnosis"):
                assert "auc" in c["seeds"] and "diagnosis_auc" in c
    assert json.loads((out / "ppo-rnn-easy" / "config.json").read_text())["obs_mode"] == "features"
    table = (out / "reference.md").read_text()
    assert "| scripted | " in table and "n/a" in table and "Diagnosis accuracy" in table and "Diagnosis AUC" in table
    assert " ± " in table and "held back for validation" in table
    val = json.loads((out / "validation" / "dataset.json").read_text())["validation"]
    assert len(val["train"]) == 1 and len(val["validation"]) == 1


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_feature_only_dataset_runs_the_rows_that_need_no_pixels(dataset, tmp_path):
    """A dataset made with ``--no-pixels`` (``pixels_kept: false`` in dataset.json): random is evaluated on
    features, the scripted policy on features (zoom where the view's tumour logit is high), the rows
    needing pixels are not run and the table says why, with the pixel-mode bytes."""
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    spec = json.loads((ds / "dataset.json").read_text())
    spec.update(pixels_kept=False, encoder="colour-stats", device_bytes={"pixels": 3 * 2**30, "features": 1})
    (ds / "dataset.json").write_text(json.dumps(spec))
    out = tmp_path / "ref"
    assert (
        c16_reference.main(_argv(ds, out, "--methods", "random", "scripted", "ppo-pixels", "--scenarios", "Easy")) == 0
    )
    cells = json.loads((out / "reference.json").read_text())["cells"]
    assert set(cells) == {"random/Easy", "scripted/Easy"}
    table = (out / "reference.md").read_text()
    assert "| scripted | not run" not in table and "| ppo-pixels | not run" in table
    assert "keeps no pixels" in table and "3.0 GiB on the device" in table
