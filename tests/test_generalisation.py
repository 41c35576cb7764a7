"""Issue 25: training that generalises (validation split, schedules, observation normalisation),
no numpy warnings from windows without episodes, publishing a run and scoring it on any dataset."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from baselines import common, ppo


def test_finite_mean_and_extremes_say_nan_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(common.finite_mean([np.nan, np.nan]))
        assert common.finite_mean([1.0, np.nan, 3.0]) == 2.0
        m = common.finite_mean(np.array([[np.nan, np.nan], [1.0, np.nan]]), axis=1)
        assert np.isnan(m[0]) and m[1] == 1.0
        assert np.isnan(common.finite_extreme([np.nan], np.min))
        assert common.finite_extreme([2.0, np.nan, -1.0], np.min) == -1.0
        assert common.finite_extreme([2.0, np.nan, -1.0], np.max) == 2.0
        s = common.smooth(np.array([[np.nan, np.nan, 1.0], [np.nan, 2.0, np.nan]]), 2)
        assert np.isnan(s[0, 0]) and np.isnan(s[0, 1]) and s[0, 2] == 1.0 and s[1, 2] == 2.0


def test_tiny_hard_run_where_no_episode_ends_writes_its_logs_without_warnings(tmp_path):
    """Hard with a long step limit and a tiny budget: no episode ends in most windows (the run that
    printed "Mean of empty slice" from the logs and the final window); NaN is recorded instead."""
    config = dict(ppo.DEFAULTS, env_id="HistoJAX-Hard-v0", with_position=True, num_envs=2, seed=0, num_steps=8, total_timesteps=64,
                  update_epochs=1, num_minibatches=2, hidden=16, num_seeds=2, print_progress=True, log_every=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        _, _, summary = common.run_and_save("ppo", ppo.make_train, config, tmp_path / "run")
    assert np.isnan(summary["final"]["steps_to_success"])
    assert (tmp_path / "run" / "log.csv").read_text().count("\n") == 5
