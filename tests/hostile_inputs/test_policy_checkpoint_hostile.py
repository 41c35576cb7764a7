"""A policy's checkpoint read by ``histojax evaluate RUN`` and every command scoring a run
(:func:`baselines.harness.logs.load_checkpoint`): a ``params.msgpack`` or ``config.json`` that is a FIFO is refused at
once (was: the read blocked for ever), parameters holding NaN or infinite values (a diverged run, whose every
score is NaN and whose AUC :mod:`data_tools.metrics` refuses) are refused naming the file, a ``config.json`` nested
past the parser or not an object is one line naming it (were a RecursionError / TypeError traceback)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from blocking_helpers import at_most
from flax import serialization

from baselines.harness.logs import load_checkpoint
from data_tools.errors import HistojaxDataError

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs need a POSIX system")
CONFIG = {"algo": "ppo", "env_id": "HistoJAX-Easy-v0"}


def _run(tmp_path: Path, w=(0.0, 1.0), config: str | None = None) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "params.msgpack").write_bytes(serialization.msgpack_serialize({"w": np.array(w, np.float32)}))
    (run / "config.json").write_text(json.dumps(CONFIG) if config is None else config)
    return run


def test_a_plain_checkpoint_loads(tmp_path):
    params, config = load_checkpoint(_run(tmp_path))
    assert config["algo"] == "ppo" and np.asarray(params["w"]).tolist() == [0.0, 1.0]


@pytest.mark.parametrize("name", ["params.msgpack", "config.json"])
def test_a_fifo_checkpoint_or_config_is_refused_at_once(tmp_path, name):
    """Was: ``read_bytes`` / ``read_text`` on the FIFO blocked for ever (``histojax evaluate RUN`` hung)."""
    run = _run(tmp_path)
    (run / name).unlink()
    os.mkfifo(run / name)
    with at_most(5), pytest.raises(HistojaxDataError, match=rf"{name}: is a FIFO, not a") as e:
        load_checkpoint(run)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("w", [(np.nan, 1.0), (np.inf, 0.0), (-np.inf, 0.0)])
def test_nan_or_infinite_parameters_are_refused_naming_the_file(tmp_path, w):
    """Was: loaded, and every score the policy gave was NaN (its AUC then refused by the metrics, naming no file)."""
    run = _run(tmp_path, w)
    with pytest.raises(HistojaxDataError, match=r"params\.msgpack: holds NaN or infinite parameters"):
        load_checkpoint(run)


@pytest.mark.parametrize(
    "config, words",
    [
        ("[" * 100_000 + "]" * 100_000, "not valid JSON"),  # was: RecursionError traceback
        ("[1]", "holds a JSON list, not a run's config"),  # was: TypeError in canonical_config
        ('"ppo"', "holds a JSON str, not a run's config"),
    ],
)
def test_a_config_nested_past_the_parser_or_not_an_object_is_one_line(tmp_path, config, words):
    run = _run(tmp_path, config=config)
    with pytest.raises(HistojaxDataError, match=words) as e:
        load_checkpoint(run)
    assert str(e.value).startswith(str(run / "config.json")) and "\n" not in str(e.value)


def test_histojax_evaluate_of_a_run_whose_params_are_a_fifo_is_one_line_exit_2(tmp_path, capsys):
    from histojax.cli import main

    run = _run(tmp_path)
    (run / "params.msgpack").unlink()
    os.mkfifo(run / "params.msgpack")
    with at_most(60):
        assert main(["evaluate", str(run), "--out", str(tmp_path / "eval")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "params.msgpack" in err[0], err
    assert not (tmp_path / "eval").exists()
