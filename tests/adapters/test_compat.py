"""HistoGym's API (histojax.adapters.histogym): the paper's Listing 1 runs with only the import changed."""

from __future__ import annotations

import numpy as np
import pytest

from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("results")


@pytest.fixture(scope="module")
def env(result_dir):
    from histojax.adapters.histogym import HistoEnv  # was: from gymhisto import HistoEnv

    img_path, xml_path, tile_size, result_path = str(SAMPLE_SLIDE), str(SAMPLE_ANNOTATIONS), 128, str(result_dir)
    return HistoEnv(img_path, xml_path, tile_size, result_path)


def test_listing_1_random_agent(env):
    # HistoGym's Listing 1, verbatim but for the import
    obs = env.reset()
    done = False
    total, steps = 0.0, 0
    while not done:
        action = env.action_space.sample()
        obs, reward, done, info = env.step(action)
        total += reward
        steps += 1
    assert steps == env.max_step == 2000
    assert obs.shape == (3, 128, 128) and obs.dtype == np.uint8
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float) and isinstance(done, bool) and isinstance(info, dict)
    assert np.isfinite(total) and -0.01 - 1e-6 <= reward <= 999.99 + 1e-3
    assert info["truncated"] and not info["terminated"]


def test_attributes_and_reset(env):
    assert (env.UP, env.DOWN, env.LEFT, env.RIGHT, env.ZOOM_IN, env.ZOOM_OUT, env.STAY) == tuple(range(7))
    assert env.action_space.n == 7 and env.action_space.contains(env.action_space.sample())
    assert env.observation_space.shape == (3, 128, 128)
    obs = env.reset()
    assert obs.shape == (3, 128, 128) and obs.dtype == np.uint8
    assert env.agent_pos == [0, 0, 0]  # HistoGym's fixed start: coarsest level, top-left
    assert env.count == 0 and env.state is obs
    obs, reward, done, _ = env.step(env.ZOOM_IN)
    assert env.agent_pos[0] == 1 and env.count == 1 and not done
    assert reward == pytest.approx(-0.01)  # HistoGym's reward: -0.01 away from the finest level
    obs, _, _, _ = env.step(np.int64(env.ZOOM_IN))  # numpy actions as from action_space.sample()
    assert env.agent_pos[0] == 2
    # the observation is the (channel-first) view of the jitted environment
    view = np.asarray(env.env.get_obs(env.jax_state, env.params))
    np.testing.assert_array_equal(obs, view.transpose(2, 0, 1))


def test_step_compiles_once(env):
    env.reset()
    for a in (0, 1, 2, 3, 4, 5, 6, np.int64(3), 9):
        env.step(a)
    assert env._step._cache_size() == 1


def test_render_modes_headless(env, result_dir, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("histojax.adapters.histogym.sys.platform", "linux")
    env.reset()
    env.step(env.ZOOM_IN)
    picture = env.render(mode="rgb_array")
    assert picture.ndim == 3 and picture.shape[2] == 3 and picture.dtype == np.uint8
    saved = env.render(mode="save")
    assert saved.parent == result_dir and saved.suffix == ".png" and saved.stat().st_size > 0
    saved.unlink()
    env._human_notice = False
    with pytest.warns(UserWarning, match="no display"):
        human = env.render(mode="human")
    assert human.is_file() and human.parent == result_dir
    with pytest.raises(ValueError, match="render mode"):
        env.render(mode="ansi")


def test_scenarios_and_bundle_reuse(result_dir):
    from histojax.adapters.histogym import HistoEnv

    hard = HistoEnv(
        str(SAMPLE_SLIDE),
        str(SAMPLE_ANNOTATIONS),
        128,
        str(result_dir),
        scenario="hard",
        reward="dense",
        max_step=5,
        seed=3,
    )
    assert hard.env.n_levels == 7 and hard.env.reward == "dense"
    done, n = False, 0
    while not done:
        _, _, done, _ = hard.step(hard.action_space.sample())
        n += 1
    assert n <= 5
    with pytest.raises(ValueError, match="scenario"):
        HistoEnv(str(SAMPLE_SLIDE), str(SAMPLE_ANNOTATIONS), 128, str(result_dir), scenario="impossible")
