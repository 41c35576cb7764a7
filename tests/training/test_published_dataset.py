"""A published agent's config.json records no path of the machine it was trained on (published.json names the
dataset in words); one published before recorded its path: kept as provenance, never used unasked. ``histojax evaluate`` of a published agent
without ``--dataset`` says in one line which dataset it needs and how to build it (exit 2, nothing written), also
when a folder of the recorded name exists here; with ``--dataset`` it is scored there."""

from __future__ import annotations

import json
import shutil

import pytest

from baselines.evaluate.checks import is_published, published_dataset_refusal
from baselines.published_agents import PUBLISHED
from histojax.cli import main as histojax_main


def _one_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("error:")]
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize(
    "name",
    [
        "c16-v1-diagnosis",
        "c16-v1-hard-navigator",
        "c16-v1-zoom-reader",
        "c16-v2-set-reader",
        "c16-v2-head-navigator",
        "c16-v2-learned-set-reader",
    ],
)
def test_every_published_agent_names_the_dataset_it_needs(name, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "eval"
    assert histojax_main(["evaluate", str(PUBLISHED / name), "--episodes", "2", "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert json.loads((PUBLISHED / name / "config.json").read_text())["env_kwargs"]["dataset"] is None  # no path
    assert f"{PUBLISHED / name / 'config.json'}: a published agent" in line
    assert "records no path of the machine it was trained on; its published.json says it trained on" in line
    assert json.loads((PUBLISHED / name / "published.json").read_text())["trained_on"]["what"] in line
    assert "give --dataset DIR" in line and "histojax c16 --small --features --out c16-small" in line
    assert "pcam-cnn" in line and "docs/c16-benchmark.md#build-it" in line
    assert not out.exists()


def test_a_recorded_dataset_that_exists_here_is_not_used_unasked(tmp_path, capsys, monkeypatch):
    """Was: a published agent whose recorded folder exists on this machine (e.g. /work/c16-full) was scored on it
    without a word. Now refused, naming the folder as provenance; --split without --dataset too."""
    here = tmp_path / "c16-full"
    here.mkdir()
    (here / "dataset.json").write_text(json.dumps({"train": [], "test": []}))
    run = shutil.copytree(PUBLISHED / "c16-v1-zoom-reader", tmp_path / "agent")  # published.json comes with it
    config = json.loads((run / "config.json").read_text())
    config["env_kwargs"]["dataset"] = str(here)
    (run / "config.json").write_text(json.dumps(config))
    assert is_published(run) and not is_published(tmp_path)
    for extra in ([], ["--split", "test"]):
        assert histojax_main(["evaluate", str(run), "--episodes", "2", "--out", str(tmp_path / "e"), *extra]) == 2
        line = _one_line(capsys)
        assert f"as {here} (a folder of the machine it was trained on, kept as provenance" in line
        assert "give --dataset DIR" in line
    assert not (tmp_path / "e").exists()


def test_a_run_of_ones_own_is_not_refused(tmp_path):
    run = tmp_path / "mine"
    run.mkdir()
    assert (
        published_dataset_refusal(run, {"env_id": "HistoJAX-C16-Hard-v1", "env_kwargs": {"dataset": "somewhere"}})
        is None
    )


def test_the_published_readme_says_so():
    text = (PUBLISHED / "README.md").read_text()
    assert "provenance" in text and "--dataset" in text and "histojax c16 --small --features" in text
