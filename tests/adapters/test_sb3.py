"""Stable-Baselines3 (the ``sb3`` extra; ``make test-integrations``): SB3's env checker on the
Gymnasium bridge, the ``VecEnv`` adapter step for step against SB3's own DummyVecEnv over
bridges, and PPO learning on the adapter."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

sb3 = pytest.importorskip("stable_baselines3")
from stable_baselines3.common.env_checker import check_env  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor  # noqa: E402

import histojax  # noqa: E402
from histojax.adapters.gymnasium import GymnasiumEnv  # noqa: E402
from histojax.adapters.sb3 import SB3VecEnv, make_sb3_vec_env  # noqa: E402


@pytest.mark.parametrize("overrides", [{}, {"with_position": True}, {"action_mode": "continuous"}])
def test_sb3_check_env_passes_on_the_bridge(overrides):
    env, params = histojax.make("HistoJAX-Easy-v0", **overrides)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3's checker warns on every contract slip (read-only arrays too)
        check_env(GymnasiumEnv(env, params), warn=True)


def _same(got, want):
    obs, rewards, dones, infos = got
    obs_w, rewards_w, dones_w, infos_w = want
    np.testing.assert_array_equal(obs, obs_w)
    np.testing.assert_allclose(rewards, rewards_w, rtol=1e-6)
    np.testing.assert_array_equal(dones, dones_w)
    for info, info_w in zip(infos, infos_w):
        assert set(info) == set(info_w)
        for k in info:
            np.testing.assert_allclose(
                np.asarray(info[k], dtype=float), np.asarray(info_w[k], dtype=float), rtol=1e-6, err_msg=k
            )


def test_vec_env_adapter_follows_dummy_vec_env_step_for_step():
    env, params = histojax.make("HistoJAX-Easy-v0", max_steps_in_episode=3)
    n = 3
    ours = SB3VecEnv(env, n, params)
    ref = DummyVecEnv([lambda: GymnasiumEnv(env, params) for _ in range(n)])
    assert ours.observation_space == ref.observation_space and ours.action_space == ref.action_space
    ours.seed(7)
    ref.seed(7)
    np.testing.assert_array_equal(ours.reset(), ref.reset())
    rng = np.random.default_rng(1)
    ended = 0
    for _ in range(7):
        actions = rng.integers(0, 7, n)
        got = ours.step(actions)
        _same(got, ref.step(actions))
        ended += int(got[2].sum())
        assert got[0].flags.writeable
    assert ended >= n  # every sub-env's episode ended at least once (3-step limit)
    assert ours.get_attr("n_levels") == [3, 3, 3] and ours.env_is_wrapped(object) == [False] * n


def test_ppo_learns_on_the_vec_env_adapter():
    venv = VecMonitor(make_sb3_vec_env("HistoJAX-Easy-v0", 4, max_steps_in_episode=16))
    model = sb3.PPO("CnnPolicy", venv, n_steps=32, batch_size=64, n_epochs=2, seed=0, verbose=0)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*not writable.*")  # torch on read-only numpy arrays
        model.learn(total_timesteps=256)  # two rollouts of 4 x 32 steps
    assert model.num_timesteps == 256 and len(model.ep_info_buffer) >= 4  # 16-step episodes were logged
    obs = venv.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (4,) and ((action >= 0) & (action < 7)).all()
