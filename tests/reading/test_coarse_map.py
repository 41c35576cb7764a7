"""``action_mode="discrete:map"``: the navigator's observation holds a coarse map of one feature entry on the
visited map's 16 × 16 blocks (``histojax.reading.coarse_map``), recomputed here view by view through the env's own
feature lookup (``modes.view_features``); it is the slide's, fixed through the episode and across auto-resets.

Slides made here: ``data_tools synth`` (2 tumour + 2 normal, 320 × 256 px, 32-px views, 3 levels) with
``colour-stats`` features."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from slide_helpers import synth_feature_dataset

import histojax
from histojax.core import seen_views
from histojax.core.modes.base import view_features

ENTRY = 2


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return synth_feature_dataset(tmp_path_factory.mktemp("coarse-map-ds"), n_slides=2, negatives=2)


def _make(dataset, **kw):
    return histojax.make("HistoJAX-Easy-v0", dataset=str(dataset), split="all", obs_mode="features", **kw)


def _by_hand(env, params, level: int) -> list[np.ndarray]:
    """Per slide: each block's largest entry over the level-``level`` views that share a finest tissue view's
    centre, read one by one with the env's feature lookup; blocks without tissue: the slide's lowest."""
    t, f, m = env.tile_size, env.n_levels - 1, seen_views.VISITED_MAP
    maps = []
    for slide, bundle in seen_views.per_slide(params, env.bundles):
        ds = np.asarray(slide.downsample, np.float64)
        tissue = seen_views.tissue_views(bundle, slide, t)
        gh, gw = tissue.shape
        blocks = {}
        for fy, fx in zip(*np.nonzero(tissue)):
            x = int(np.floor((fx * t + t / 2) * ds[f] / ds[level] - t / 2))
            y = int(np.floor((fy * t + t / 2) * ds[f] / ds[level] - t / 2))
            v = float(view_features(slide, jnp.int32(level), jnp.int32(x), jnp.int32(y))[ENTRY])
            key = (fy * m // gh, fx * m // gw)
            blocks[key] = max(blocks.get(key, -np.inf), v)
        low = min(blocks.values())
        maps.append(np.array([[blocks.get((by, bx), low) for bx in range(m)] for by in range(m)], np.float32))
    return maps


@pytest.mark.parametrize("level", [-3, -2, -1])
def test_the_map_is_each_blocks_largest_coarse_entry(dataset, level):
    env, params = _make(dataset, action_mode="discrete:map", map_feature=ENTRY, map_level=level)
    expected = _by_hand(env, params, level + env.n_levels)
    assert len(expected) == 4 and (level == -3 or any(np.ptp(e) > 0 for e in expected))  # -3: 1-4 views a slide
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    obs, state = reset(jax.random.split(jax.random.key(0), 16), params)
    slides = np.asarray(state.slide_index)
    assert len(set(slides.tolist())) > 1
    for e, i in enumerate(slides):
        np.testing.assert_allclose(np.asarray(obs["coarse_map"][e]), expected[i], rtol=1e-6)
    space = env.observation_space(params)
    assert space.spaces["coarse_map"].shape == (16, 16) and set(obs) == set(space.spaces)


def test_the_map_is_fixed_through_steps_and_follows_the_slide_across_auto_resets(dataset):
    env, params = _make(dataset, action_mode="discrete:map", map_feature=ENTRY, start_level=-1, max_steps_in_episode=3)
    table = np.asarray(params.mode_data.coarse_map)
    step = jax.jit(env.step)
    obs, state = env.reset(jax.random.key(1), params)
    for i in range(9):  # three episodes: the map is always that of the slide of the state
        np.testing.assert_array_equal(np.asarray(obs["coarse_map"]), table[int(state.slide_index)])
        obs, state, *_ = step(jax.random.key(i + 2), state, jnp.int32(i % 4), params)
    assert int(state.z) == env.n_levels - 1  # a finest start after the auto-resets


def test_map_settings_are_checked(dataset):
    with pytest.raises(TypeError, match="discrete:map needs map_feature"):
        _make(dataset, action_mode="discrete:map")
    with pytest.raises(TypeError, match="map_feature is for discrete:map only"):
        _make(dataset, action_mode="discrete:memory", map_feature=ENTRY)
    with pytest.raises(ValueError, match=r"map_feature=99: .*metadata.json: its .* feature grid has \d+ entries"):
        _make(dataset, action_mode="discrete:map", map_feature=99)
    with pytest.raises(ValueError, match="map_level=5 is not one of the 3 levels"):
        _make(dataset, action_mode="discrete:map", map_feature=ENTRY, map_level=5)
    with pytest.raises(ValueError, match="action_mode must be one of"):
        histojax.make("HistoJAX-Easy-v0", action_mode="discrete:mapp")


def _obs(target=(3, 12), position=(0.5, 0.5, 1.0), visited=None):
    cm = np.zeros((16, 16), np.float32)
    cm[target] = 5.0
    return {
        "coarse_map": jnp.asarray(cm),
        "visited": jnp.asarray(np.zeros((16, 16), np.float32) if visited is None else visited),
        "position": jnp.asarray(position, jnp.float32),
        "features": jnp.zeros(4),
    }


def test_map_follower_walks_to_the_highest_unread_block():
    from baselines.episodes.policies import map_follower_policy

    def act(**kw):
        return int(map_follower_policy(jax.random.key(0), _obs(**kw), epsilon=0.0))

    # target block (3, 12): centre (12.5 / 16, 3.5 / 16) = (0.78, 0.22)
    assert act(position=(0.5, 0.5, 1.0)) == histojax.ZOOM_OUT  # finest, far: travel higher up
    assert act(position=(0.5, 0.5, 0.75)) == histojax.ZOOM_OUT  # still below the travel level
    assert act(position=(0.5, 0.5, 0.5)) == histojax.RIGHT  # at the travel level: longer axis first
    assert act(position=(0.78, 0.6, 0.5)) == histojax.UP
    assert act(position=(0.78, 0.22, 0.5)) == histojax.ZOOM_IN  # over the block: down to the finest
    assert act(position=(0.78, 0.22, 1.0)) in (histojax.UP, histojax.DOWN, histojax.LEFT, histojax.RIGHT)  # reads it
    assert act(position=(0.70, 0.22, 1.0)) == histojax.RIGHT  # finest, near but outside: step towards it
    read = np.zeros((16, 16), np.float32)
    read[3, 12] = 0.6  # read enough: the next highest block
    cm_next = _obs(position=(0.5, 0.5, 0.5), visited=read)
    cm_next["coarse_map"] = cm_next["coarse_map"].at[14, 1].set(4.0)
    assert int(map_follower_policy(jax.random.key(0), cm_next, epsilon=0.0)) == histojax.LEFT


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_evaluate_scores_the_map_follower_through_the_head(dataset):
    """``evaluate`` through a head: the reference rows (random, the map follower) are scored by the head (AUC)."""
    from baselines.evaluate.scoring import evaluate
    from histojax.reading.heads.logit import LogitHead

    head = LogitHead(
        cal_a=jnp.float32(1.0),
        cal_b=jnp.float32(0.0),
        prior_logit=jnp.float32(0.0),
        dim=ENTRY,
        k=1,
        top=1,
        encoder=None,
    )
    config = {
        "env_id": "HistoJAX-Easy-v0",
        "action_mode": "discrete:map",
        "obs_mode": "features",
        "max_steps_in_episode": 12,
        "env_kwargs": {"dataset": str(dataset), "split": "all", "map_feature": ENTRY, "start_level": -1},
    }
    rows = evaluate(config, None, num_episodes=8, head=head, head_reward={"gain": "fidelity", "final": 0.0})
    assert set(rows) == {"random", "scripted"}
    for row in rows.values():
        assert 0.0 <= row["diagnosis_auc"] <= 1.0 and row["mean_fraction_read"] > 0
