"""baselines.reproduce: one cell of each algorithm trains, evaluates and formats (slow: make test-all)."""

from __future__ import annotations

import pytest

from baselines.reproduce import _fmt_row, run_cell


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo", "dqn"])
def test_a_tiny_cell_runs_end_to_end(tmp_path, algo):
    row = run_cell(
        algo, "HistoJAX-Easy-v0", "discrete", "pixels", None, dict(steps=4096, seeds=1, episodes=8), tmp_path / algo
    )
    assert 0.0 <= row["success"] <= 1.0 and row["wall_s"] > 0
    assert (tmp_path / algo / "params.msgpack").is_file() and (tmp_path / algo / "eval").is_dir()
    line = _fmt_row(algo, row)
    assert line.startswith(f"| {algo} |") and "random agent" in line


def test_not_applicable_cells_say_why():
    assert "DQN needs discrete actions" in _fmt_row("x", None, "DQN needs discrete actions")
