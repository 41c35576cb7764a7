"""baselines.reading.train_readers.seed_curve: a multi-seed run's learning curve as mean ± std over seeds, from the
trainer's log.json (per_seed stored as (seeds, points)), computed by hand here."""

from __future__ import annotations

import csv
import json

import numpy as np

from baselines.reading.train_readers import seed_curve


def test_seed_curve_is_mean_and_std_over_seeds(tmp_path):
    steps = list(range(1000, 11000, 1000))
    rng = np.random.default_rng(0)
    ret = rng.normal(size=(3, len(steps)))
    length = rng.uniform(5, 10, size=(3, len(steps)))
    (tmp_path / "log.json").write_text(
        json.dumps({"step": steps, "per_seed": {"return": ret.tolist(), "length": length.tolist()}})
    )
    png, path = seed_curve(tmp_path, tmp_path / "c.png", tmp_path / "c.csv", smooth=2)
    assert png.stat().st_size > 0
    rows = list(csv.DictReader(open(path)))
    assert len(rows) == len(steps) - 1 and int(rows[0]["env_steps_per_seed"]) == 2000
    smoothed = (ret[:, :-1] + ret[:, 1:]) / 2
    np.testing.assert_allclose([float(r["return_mean"]) for r in rows], smoothed.mean(0), atol=1e-4)
    np.testing.assert_allclose([float(r["return_std"]) for r in rows], smoothed.std(0), atol=1e-4)
    np.testing.assert_allclose([float(r["return_seed1"]) for r in rows], smoothed[1], atol=1e-4)


def test_a_run_shorter_than_the_window_still_gets_its_curve(tmp_path):
    """5 log points and the default window of 8: the window shrinks to the run (a short training run's
    train_readers call must not fail after training)."""
    ret = np.arange(15, dtype=float).reshape(3, 5)
    (tmp_path / "log.json").write_text(
        json.dumps({"step": [1, 2, 3, 4, 5], "per_seed": {"return": ret.tolist(), "length": np.ones((3, 5)).tolist()}})
    )
    _, path = seed_curve(tmp_path, tmp_path / "c.png", tmp_path / "c.csv")
    rows = list(csv.DictReader(open(path)))
    assert len(rows) == 1 and float(rows[0]["return_mean"]) == ret.mean()


def test_updates_without_an_ended_episode_are_skipped_not_spread(tmp_path):
    """Episodes longer than an update log NaN where none ended: the running mean is over the points that
    have a value, so a curve of 200-step episodes is not NaN everywhere."""
    ret = np.array([[1.0, np.nan, 3.0, np.nan], [2.0, 4.0, np.nan, np.nan], [0.0, np.nan, np.nan, 6.0]])
    (tmp_path / "log.json").write_text(
        json.dumps(
            {
                "step": [1, 2, 3, 4],
                "per_seed": {"return": np.where(np.isnan(ret), None, ret).tolist(), "length": np.ones((3, 4)).tolist()},
            }
        )
    )
    _, path = seed_curve(tmp_path, tmp_path / "c.png", tmp_path / "c.csv", smooth=2)
    rows = list(csv.DictReader(open(path)))
    seeds = np.array([[float(r[f"return_seed{k}"]) for r in rows] for k in range(3)])
    np.testing.assert_allclose(seeds[0], [1.0, 3.0, 3.0])
    np.testing.assert_allclose(seeds[1], [3.0, 4.0, np.nan])
    np.testing.assert_allclose(seeds[2], [0.0, np.nan, 6.0])


def test_progress_lines_say_n_a_where_no_episode_ended(capsys):
    """The trainers' progress line shows ``n/a``, not ``nan``, for an update in which no episode ended."""
    from baselines.harness.logs import Progress

    progress = Progress(num_seeds=2, num_updates=2, steps_per_update=64, every=1, name="ppo test")
    nan = np.full(2, np.nan)
    progress(
        np.zeros(2, np.int32),
        {
            "return": nan,
            "success": nan,
            "steps_to_success": nan,
            "episodes": np.zeros(2),
            "length": nan,
            "entropy": np.array([1.5, 1.7]),
        },
    )
    progress(
        np.ones(2, np.int32),
        {
            "return": np.array([1.0, 2.0]),
            "success": np.array([0.5, 0.5]),
            "steps_to_success": nan,
            "episodes": np.ones(2),
            "length": np.array([200.0, 200.0]),
            "entropy": np.array([1.5, 1.7]),
        },
    )
    first, second = capsys.readouterr().out.splitlines()
    assert "return n/a  success n/a  steps-to-success n/a  length n/a  entropy 1.6" in first
    assert "return 1.500  success 50.0%  steps-to-success n/a  length 200" in second
    assert "nan" not in first + second
