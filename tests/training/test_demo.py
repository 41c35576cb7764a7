"""`make demo` (``python -m baselines.demo``) end to end at the ``--quick`` budget: the files it
lists exist and are valid PNG / GIF / checkpoint, and its summary has numbers in range."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

from baselines import demo
from baselines.harness.logs import load_checkpoint

# --quick trains 3 updates; the last may finish no successful episode (NaN steps to success)
pytestmark = [
    pytest.mark.filterwarnings("ignore:Mean of empty slice:RuntimeWarning"),
    pytest.mark.filterwarnings("ignore:All-NaN slice encountered:RuntimeWarning"),
]


def _check_image(path: Path, fmt: str, min_frames: int = 1) -> None:
    with Image.open(path) as im:
        assert im.format == fmt, path
        assert im.width >= 100 and im.height >= 100, path
        assert getattr(im, "n_frames", 1) >= min_frames, path
        im.seek(0)
        extrema = im.convert("L").getextrema()
        assert extrema[0] < extrema[1], f"{path} is a blank image"


def _in_unit(v) -> bool:
    return math.isfinite(v) and 0.0 <= v <= 1.0


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert demo.main(["--quick", "--out", str(out)]) == 0
    return out, buf.getvalue()


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_quick_demo_writes_the_listed_files(quick_run):
    out, printed = quick_run
    summary = json.loads((out / "demo_summary.json").read_text())
    run, ev = out / "ppo-easy", out / "ppo-easy" / "eval"
    expected = {
        out / "demo_trajectory.png",
        out / "demo_trajectory.gif",
        run / "curve.png",
        run / "params.msgpack",
        run / "log.csv",
        ev / "trajectory_ppo_greedy.png",
        ev / "trajectory.gif",
        ev / "trajectory_ppo_sampled.png",
        ev / "trajectory_random.png",
    }
    assert {Path(f) for f in summary["files"]} == expected
    assert "files written:" in printed
    for f in [*expected, out / "demo_summary.json"]:
        assert f.is_file() and f.stat().st_size > 0, f
        assert str(f) in printed, f"{f} not in the printed summary"
    for png in (
        out / "demo_trajectory.png",
        run / "curve.png",
        ev / "trajectory_ppo_greedy.png",
        ev / "trajectory_ppo_sampled.png",
        ev / "trajectory_random.png",
        ev / "trajectory_scripted.png",
    ):
        _check_image(png, "PNG")
    _check_image(out / "demo_trajectory.gif", "GIF", min_frames=2)  # a random episode moves
    _check_image(ev / "trajectory.gif", "GIF")  # (an untrained policy may stand still: frames merge)
    # the checkpoint loads and is the demo's configuration
    params, config = load_checkpoint(run)
    assert config["env_id"] == "HistoJAX-Easy-v0" and config["with_position"] is True and config["seed"] == 0
    leaves = [np.asarray(a) for a in jax.tree.leaves(params)]
    assert leaves and all(a.shape[0] == 1 and np.isfinite(a).all() for a in leaves)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_quick_demo_summary_numbers(quick_run):
    out, printed = quick_run
    summary = json.loads((out / "demo_summary.json").read_text())
    assert "demo summary" in printed and "random agent, 16 envs" in printed
    (row,) = summary["random_agent_table"]  # --quick: Easy only
    assert row["env_id"] == "HistoJAX-Easy-v0" and row["levels"] == 3 and row["episodes"] >= 0
    assert math.isfinite(row["steps_per_second"]) and row["steps_per_second"] > 0
    ppo = summary["ppo"]
    assert ppo["env_steps_per_seed"] == 3 * 8 * 16 and ppo["seeds"] == 1 and ppo["seed"] == 0
    for k in ("train_seconds", "compile_seconds", "env_steps_per_second_all_seeds"):
        assert math.isfinite(ppo[k]) and ppo[k] > 0, k
    rows = summary["evaluation"]
    lines = printed.splitlines()
    assert set(rows) == {"ppo (greedy)", "ppo (sampled)", "random", "scripted"}
    for name, r in rows.items():
        assert r["episodes"] == demo.QUICK_EVAL_EPISODES, name
        assert _in_unit(r["success_rate"]), name
        # dense reward over <= 10 steps: -0.01 per step + potential difference in [-1, 1] + 10 on success
        assert math.isfinite(r["mean_return"]) and -1.11 <= r["mean_return"] <= 11.0 + 1e-6, name
        assert 1 <= r["mean_length"] <= demo.QUICK_STEP_LIMIT, name  # --quick cuts episodes at 10 steps
        # steps to success is defined exactly when some episode succeeded
        # (undefined is JSON null: no JSON file histojax writes holds NaN)
        steps = r["mean_steps_to_success"]
        assert (steps is not None and math.isfinite(steps)) == (r["success_rate"] > 0), name
        assert any(line.strip().startswith(name) and f"{r['success_rate']:.1%}" in line for line in lines), name
    assert math.isfinite(summary["wall_seconds"]) and summary["wall_seconds"] > 0


def test_no_train_writes_only_the_random_agent_table(tmp_path, capsys):
    assert demo.main(["--quick", "--no-train", "--out", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "demo_summary.json").read_text())
    assert summary["ppo"] is None and summary["evaluation"] is None
    assert not (tmp_path / "ppo-easy").exists()
    _check_image(tmp_path / "demo_trajectory.gif", "GIF", min_frames=2)
    assert "PPO" not in capsys.readouterr().out
