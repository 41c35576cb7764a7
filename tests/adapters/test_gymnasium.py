"""The Gymnasium bridges: gymnasium's own env checker, and NEXT_STEP autoreset of the vector env."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402

import histojax  # noqa: E402
from histojax.adapters.gymnasium import GymnasiumEnv, GymnasiumVectorEnv  # noqa: E402


@pytest.mark.parametrize(
    "overrides", [{}, {"with_position": True, "obs_mode": "pixels_float"}, {"action_mode": "continuous"}]
)
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


def _sync_of_bridges(env, params, n):
    """Gymnasium's own SyncVectorEnv over ``n`` single-env bridges: the reference for the conventions."""
    return gymnasium.vector.SyncVectorEnv([lambda: GymnasiumEnv(env, params) for _ in range(n)])


def _assert_same(got, want):
    obs, reward, term, trunc, info = got
    obs_w, reward_w, term_w, trunc_w, info_w = want
    np.testing.assert_array_equal(obs, obs_w)
    np.testing.assert_allclose(reward, reward_w, rtol=1e-6)
    np.testing.assert_array_equal(term, term_w)
    np.testing.assert_array_equal(trunc, trunc_w)
    assert set(info) == set(info_w)
    for k in info:
        np.testing.assert_allclose(
            np.asarray(info[k], dtype=float), np.asarray(info_w[k], dtype=float), rtol=1e-6, err_msg=k
        )


def test_vector_env_follows_sync_vector_env_step_for_step():
    """Same seeds (an int, then a list), actions and reset_mask as Gymnasium's SyncVectorEnv over
    GymnasiumEnvs: the same observations, rewards, flags and masked info, also on the autoreset steps
    (all sub-environments at once: info is {}; some: their entries masked out)."""
    env, params = histojax.make("HistoJAX-Easy-v0", reward="histogym", max_steps_in_episode=3)
    n = 3
    ours, ref = GymnasiumVectorEnv(env, n, params), _sync_of_bridges(env, params, n)
    a, _ = ours.reset(seed=5)  # sub-environment i gets seed 5 + i
    b, _ = ref.reset(seed=5)
    np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(0)
    autoreset_steps, all_reset_steps = 0, 0
    for i in range(9):
        if i == 5:  # reset sub-environment 1 only, with a new seed; the others keep going
            mask = np.array([False, True, False])
            a, _ = ours.reset(seed=[None, 42, None], options={"reset_mask": mask})
            b, _ = ref.reset(seed=[None, 42, None], options={"reset_mask": mask})
            np.testing.assert_array_equal(a, b)
        actions = rng.integers(0, 7, n)
        got, want = ours.step(actions), ref.step(actions)
        _assert_same(got, want)
        all_reset_steps += got[4] == {}
        if "_success" in got[4] and not got[4]["_success"].all():
            autoreset_steps += 1
            assert not got[4]["success"][~got[4]["_success"]].any()  # no info from stepping a finished state
    assert autoreset_steps >= 2 and all_reset_steps >= 1


def test_vector_env_arrays_are_writable_and_gymnasium_wrappers_edit_them():
    env, params = histojax.make("HistoJAX-Easy-v0", obs_mode="pixels_float", with_position=True)
    venv = gymnasium.wrappers.vector.ClipReward(GymnasiumVectorEnv(env, 2, params), 0.0, 0.5)
    obs, _ = venv.reset(seed=0)
    obs, reward, term, trunc, info = venv.step(np.array([4, 6]))
    for array in (obs["pixels"], obs["position"], reward, term, trunc, info["tumour_fraction"]):
        assert array.flags.writeable
    obs["pixels"][0] = 0.0
    assert (reward >= 0).all() and (reward <= 0.5).all()


def test_make_vec_uses_the_batched_env():
    venv = gymnasium.make_vec("histojax/HistoJAX-Easy-v0", num_envs=2, max_steps_in_episode=7)
    assert isinstance(venv.unwrapped, GymnasiumVectorEnv) and venv.num_envs == 2
    assert int(venv.unwrapped.params.max_steps_in_episode) == 7
    obs, _ = venv.reset(seed=1)
    assert obs.shape == (2, 128, 128, 3)


def test_bridges_copy_and_pickle():
    import copy
    import pickle

    env, params = histojax.make("HistoJAX-Easy-v0")
    for bridge, duplicate in (
        (GymnasiumEnv(env, params), lambda x: pickle.loads(pickle.dumps(x))),
        (GymnasiumVectorEnv(env, 2, params), lambda x: pickle.loads(pickle.dumps(x))),
        (GymnasiumVectorEnv(env, 2, params), copy.deepcopy),
    ):
        bridge.reset(seed=4)
        twin = duplicate(bridge)
        action = bridge.action_space.sample()
        np.testing.assert_array_equal(twin.step(action)[0], bridge.step(action)[0])
