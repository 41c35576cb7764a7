"""The experiment drivers that read a dataset's ``dataset.json`` themselves refuse a malformed or incomplete one in one
line naming it, exit 2 (was: a ``KeyError`` / ``TypeError`` traceback, exit 1, from ``experiments.c16_sanity``,
``experiments.heldout_targets`` and ``experiments.c16_slide_ceiling``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from experiments import c16_sanity, c16_slide_ceiling, heldout_targets, read_dataset

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(params=["not json", {"train": 5}, ["a", "list"], {"train": ["b"], "test": [3], "slides": [1]}])
def bad(request, tmp_path):
    text = request.param if isinstance(request.param, str) else json.dumps(request.param)
    (tmp_path / "dataset.json").write_text(text)
    return tmp_path


@pytest.mark.parametrize(
    "main, extra",
    [
        (c16_sanity.run_main, ["--split", "test"]),
        (c16_sanity.run_main, []),
        (heldout_targets.main, []),
        (c16_slide_ceiling.main, []),
    ],
)
def test_a_bad_dataset_json_is_one_line_naming_it(main, extra, bad, capsys):
    assert main(["--dataset", str(bad), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {bad / 'dataset.json'}: "), err


def test_read_dataset_names_what_is_missing(tmp_path):
    from data_tools.errors import HistojaxDataError

    with pytest.raises(HistojaxDataError, match="dataset.json: missing"):
        read_dataset(tmp_path)
    (tmp_path / "dataset.json").write_text(json.dumps({"train": ["a"], "test": ["b"]}))
    assert read_dataset(tmp_path)["test"] == ["b"]
    with pytest.raises(HistojaxDataError, match="has no 'slides' list of slide records"):
        read_dataset(tmp_path, ("slides",))


def test_a_missing_bundle_found_while_training_is_one_line(tmp_path, capsys, monkeypatch):
    (tmp_path / "dataset.json").write_text(json.dumps({"train": ["b"], "test": ["b"]}))
    from data_tools.bundle_files.reading import read_metadata

    monkeypatch.setattr(heldout_targets, "run_scenario", lambda *a, **k: read_metadata(tmp_path / "b"))  # as training
    assert heldout_targets.run_main(["--dataset", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "metadata.json" in err[0], err


def test_in_a_real_process_there_is_no_traceback(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"train": 5}))
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.c16_slide_ceiling", "--dataset", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr + proc.stdout, proc.stderr
