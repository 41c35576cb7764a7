"""The Gymnasium bridges: gymnasium's own env checker, and NEXT_STEP autoreset of the vector env."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402

import histojax  # noqa: E402
from histojax.wrappers import GymnasiumEnv, GymnasiumVectorEnv  # noqa: E402


@pytest.mark.parametrize("overrides", [{}, {"with_position": True, "obs_mode": "pixels_float"},
                                       {"action_mode": "continuous"}])
def test_gymnasium_env_passes_check_env(overrides):
    genv = gymnasium.make("histojax/HistoJAX-Easy-v0", render_mode="rgb_array", **overrides)
    with warnings.catch_warnings():
        warnings.simplefilter("error", category=UserWarning)  # the checker warns on contract slips
        check_env(genv.unwrapped, skip_render_check=False)
    assert isinstance(genv.unwrapped, GymnasiumEnv)
    obs, info = genv.reset(seed=3)
    assert genv.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = genv.step(genv.action_space.sample())
    assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    assert genv.render().ndim == 3


def test_same_seed_same_trajectory():
    env, params = histojax.make("HistoJAX-Easy-v0")
    a, b = GymnasiumEnv(env, params), GymnasiumEnv(env, params)
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    np.testing.assert_array_equal(oa, ob)
    for action in [4, 0, 3, 4, 1]:
        ra = a.step(action)
        rb = b.step(action)
        np.testing.assert_array_equal(ra[0], rb[0])
        assert ra[1:4] == rb[1:4]


def test_vector_env_next_step_autoreset():
    env, params = histojax.make("HistoJAX-Easy-v0", reward="histogym", max_steps_in_episode=3)
    venv = GymnasiumVectorEnv(env, num_envs=4, params=params)
    assert venv.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (4, 128, 128, 3) and venv.observation_space.contains(obs)
    flags = []
    rewards = []
    for _ in range(5):
        obs, reward, term, trunc, info = venv.step(venv.action_space.sample())
        assert venv.observation_space.contains(obs) and reward.shape == (4,)
        flags.append(trunc.copy())
        rewards.append(reward.copy())
    # truncated at the 3rd step; the 4th step is the reset step (reward 0, no flags); the episode restarts
    assert [bool(f.all()) for f in flags] == [False, False, True, False, False]
    np.testing.assert_array_equal(rewards[3], 0.0)
    assert int(venv._state.t[0]) == 1  # one step into the new episode
    venv.close()
