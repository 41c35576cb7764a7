"""A published folder carries no path of the machine it was trained on: ``baselines/published/**`` holds no absolute
path and no folder of the training machine (``/work/``, ``scratch/``, ``runs/``); ``python -m baselines.publish``
writes none into a new folder (the dataset, slides and head by folder name in ``published.json``'s ``trained_on``);
every published agent still loads, types its config and is scored on the dataset given with ``--dataset``."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from flax import serialization

from baselines import ppo, ppo_rnn
from baselines.evaluate.checks import published_dataset_refusal
from baselines.evaluate.cli import with_dataset
from baselines.harness.logs import load_checkpoint
from baselines.publish import main as publish_main
from baselines.publish import publish
from baselines.published_agents import PUBLISHED

MACHINE = re.compile(r"(^|[\s\"'=(])(/[\w.~-]|~/|[A-Za-z]:\\)|/work/|scratch/|(^|[/\s\"'])runs/")
FILES = sorted(p for p in PUBLISHED.rglob("*") if p.is_file() and p.name != "README.md")
AGENTS = sorted(p for p in PUBLISHED.iterdir() if (p / "params.msgpack").is_file())
CLASSES = {"ppo": ppo.PPOConfig, "ppo_rnn": ppo_rnn.PPORNNConfig}


def _strings(obj):
    if isinstance(obj, str):
        yield obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _strings(k)
            yield from _strings(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _strings(v)


def machine_paths(folder: Path, also: tuple[str, ...] = ()) -> list[str]:
    """``FILE: text`` for every string of a JSON file under ``folder`` that is an absolute path or names a folder
    of a training machine, and every file (any kind, bytes) that holds one of ``also`` or ``/work/``."""
    found = []
    for f in sorted(p for p in Path(folder).rglob("*") if p.is_file()):
        data = f.read_bytes()
        for s in ("/work/", *also):
            if s.encode() in data:
                found.append(f"{f}: holds {s}")
        if f.suffix in (".json", ".csv"):
            texts = _strings(json.loads(data)) if f.suffix == ".json" else data.decode().split(",")
            found += [f"{f}: {s!r}" for s in texts if MACHINE.search(s)]
    return found


def test_the_published_folders_are_scanned():
    assert len(AGENTS) >= 5 and any(f.name == "published.json" for f in FILES)
    assert machine_paths(PUBLISHED / "c16-v2-head") == []
    assert MACHINE.search("/work/c16-full") and MACHINE.search("runs/r6/ref/validation")
    assert MACHINE.search("/tmp/x") and MACHINE.search("scratch/sr-g2") and not MACHINE.search("c16-full")
    assert not MACHINE.search("baselines/published/c16-v2-head") and not MACHINE.search("sr-g2/ppo")
    assert not MACHINE.search("seeds (0.709 / 0.714)") and MACHINE.search("at (/home/me/set)")


def test_no_published_file_holds_a_path_of_the_training_machine():
    """Was: config.json recorded /work/c16-full, /work/scratch/sr-g2, runs/r6/ref/validation; published.json's
    source_run and head_reward.json's dataset the same."""
    assert machine_paths(PUBLISHED) == []


@pytest.mark.parametrize("run", AGENTS, ids=lambda p: p.name)
def test_every_published_agent_names_its_dataset_and_reads_its_config(run, tmp_path):
    params, config = load_checkpoint(run)
    assert config["env_kwargs"]["dataset"] is None and config["slide"] is None
    record = json.loads((run / "published.json").read_text())
    trained = record["trained_on"]
    assert trained["dataset"] == "c16-full" and trained["split"] == "train" and trained["slides"] in (128, 145, 180)
    assert "c16-full" in trained["what"] and "docs/c16-benchmark.md#build-it" in trained["build"]
    assert "/" not in record["source_run"].split("/", 1)[-1]  # a run's folder name (with its parent for OUT/ppo)
    line = published_dataset_refusal(run, config)  # without --dataset: one line naming what to give
    assert line.startswith(f"{run / 'config.json'}: a published agent") and "give --dataset DIR" in line
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "dataset.json").write_text(json.dumps({"train": [], "test": []}))
    scored = with_dataset(config, ds)  # with --dataset: scored there, its own entries kept
    assert scored["env_kwargs"]["dataset"] == str(ds) and scored["env_kwargs"]["split"] == "test"
    assert {k: v for k, v in scored["env_kwargs"].items() if k not in ("dataset", "split")} == {
        k: v for k, v in config["env_kwargs"].items() if k not in ("dataset", "split")
    }
    typed = CLASSES[config["algo"]].from_dict(json.loads((run / "config.json").read_text()), where=str(run))
    assert typed.env_kwargs["dataset"] is None
    arguments, _ = typed.replace(env_kwargs=scored["env_kwargs"]).make_arguments()
    assert arguments["dataset"] == str(ds)


# ----------------------------------------------------------------------------- publish writes no machine path
@pytest.fixture
def run(tmp_path) -> Path:
    """A run folder as the trainers and train_readers leave it, recording this machine's paths everywhere: the
    dataset, a slide, slides, and a head fitted elsewhere whose config records the dataset it was fitted on."""
    data = tmp_path / "work" / "scratch" / "my-set"
    head = tmp_path / "work" / "heads" / "my-head"
    shutil.copytree(PUBLISHED / "c16-v2-head", head)
    cfg = json.loads((head / "config.json").read_text())
    cfg["fitted_on"]["dataset"] = str(data)
    (head / "config.json").write_text(json.dumps(cfg))
    run = tmp_path / "work" / "runs" / "r1" / "ppo"
    config = {
        **ppo.DEFAULTS,
        "env_id": "HistoJAX-C16-Diagnosis-v2",
        "slide": str(tmp_path / "bundle"),
        "env_kwargs": {"dataset": str(data), "split": "train", "slides": [str(tmp_path / "b1")], "read_budget": 0.1},
        "num_seeds": 2,
        "seed": 0,
    }
    params = {"params": {"w": np.zeros((2, 3), np.float32)}}
    run.mkdir(parents=True)
    (run / "params.msgpack").write_bytes(serialization.msgpack_serialize(params))
    (run / "config.json").write_text(json.dumps(config))
    (run / "log.json").write_text(json.dumps({"summary": {"algo": "ppo", "seeds": 2}}))
    (run / "log.csv").write_text("step,mean_return\n2048,0.5\n")
    (run / "head_reward.json").write_text(
        json.dumps(
            {
                "head": str(head),
                "head_name": "2x2 mean, max",
                "gain": "fidelity",
                "final": 0.0,
                "read_cost": 0.0,
                "dataset": str(data),
            }
        )
    )
    return run


@pytest.mark.parametrize("seed", [None, 1])
def test_publish_writes_no_path_of_this_machine(run, tmp_path, seed):
    """Was: published.json's source_run was the run's absolute path, config.json kept the dataset's, the head's
    head_source and the copied head's fitted_on its own."""
    dest = publish(
        run,
        "mine",
        root=tmp_path / "published",
        seed=seed,
        chosen_by={"by": "validation"},
        trained_on="my slides, train split: histojax dataset SLIDES --out DIR",
    )
    assert machine_paths(dest, also=(str(tmp_path),)) == []
    record = json.loads((dest / "published.json").read_text())
    assert record["source_run"] == "r1/ppo"
    assert record["trained_on"] == {
        "dataset": "my-set",
        "split": "train",
        "slides": ["b1"],
        "slide": "bundle",
        "what": "my slides, train split: histojax dataset SLIDES --out DIR",
    }
    params, config = load_checkpoint(dest)
    assert config["env_kwargs"] == {"dataset": None, "split": "train", "slides": None, "read_budget": 0.1}
    assert config["slide"] is None and ppo.PPOConfig.from_dict(config).env_kwargs["read_budget"] == 0.1
    assert params["params"]["w"].shape[0] == (2 if seed is None else 1)
    reward = json.loads((dest / "head_reward.json").read_text())
    assert (reward["head"], reward["head_source"], reward["dataset"]) == ("head", "my-head", "my-set")
    assert json.loads((dest / "head" / "config.json").read_text())["fitted_on"]["dataset"] == "my-set"
    assert (dest / "head" / "params.json").read_bytes() == (PUBLISHED / "c16-v2-head" / "params.json").read_bytes()


def test_publish_of_a_run_with_a_published_head_names_it_in_the_repository(run, tmp_path, capsys):
    reward = json.loads((run / "head_reward.json").read_text())
    (run / "head_reward.json").write_text(json.dumps({**reward, "head": str(PUBLISHED / "c16-v2-head")}))
    assert publish_main([str(run), "mine", "--root", str(tmp_path / "published")]) == 0
    dest = tmp_path / "published" / "mine"
    reward = json.loads((dest / "head_reward.json").read_text())
    assert reward["head"] == reward["head_source"] == "baselines/published/c16-v2-head"
    assert not (dest / "head").exists() and machine_paths(dest, also=(str(tmp_path),)) == []
    assert json.loads((dest / "published.json").read_text())["trained_on"]["dataset"] == "my-set"


def test_the_readme_says_so():
    text = (PUBLISHED / "README.md").read_text()
    assert "trained_on" in text and "no path of the machine" in text and "/work/" not in text


def test_split_or_fold_without_dataset_on_a_config_of_no_dataset_path_is_one_line(capsys):
    """Was: a published config.json copied without its published.json, evaluated with --fold 0 and no --dataset:
    "expected str, bytes or os.PathLike object, not NoneType"."""
    _, config = load_checkpoint(PUBLISHED / "c16-v1-diagnosis")
    for kw in ({"fold": 0}, {"split": "test"}):
        with pytest.raises(SystemExit) as e:
            with_dataset(config, **kw)
        assert e.value.code == 2
        assert "records no dataset it trained on; give --dataset DIR too" in capsys.readouterr().err
