"""Invariants of the dynamics, checked with hypothesis on the embedded slide.

Each jitted function below is compiled once for the module (fixed shapes), then called
for every example: ``deadline=None`` because the first call compiles.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis_examples import examples

import histojax
from histojax import STAY, ZOOM_IN, ZOOM_OUT

T_STEPS = 30
# 40 examples each under `make test-all`, 10 in `make test`
SETTINGS = settings(deadline=None, max_examples=examples(40, 10), derandomize=True)
actions_strategy = st.lists(st.integers(-2, 9), min_size=T_STEPS, max_size=T_STEPS)  # includes invalid codes


@functools.lru_cache(maxsize=None)
def scenario(env_id: str, reward: str = "dense", auto_reset: bool = True):
    env, params = histojax.make(env_id, reward=reward, auto_reset=auto_reset)
    return env, params, jax.jit(env.step), jax.jit(functools.partial(rollout, env))


def rollout(env, key, actions, params):
    """Run ``actions`` from a reset; returns per-step states, rewards, flags (stacked on axis 0)."""
    _, state = env.reset(key, params)

    def body(state, inp):
        k, a = inp
        _, new, reward, term, trunc, info = env.step(k, state, a, params)
        return new, (new, reward, term, trunc, info["success"])

    keys = jax.random.split(key, actions.shape[0])
    return state, jax.lax.scan(body, state, (keys, actions))[1]


ENV_IDS = ["HistoJAX-Easy-v0", "HistoJAX-Hard-v0"]


@pytest.mark.parametrize("env_id", ENV_IDS)
@SETTINGS
@given(actions=actions_strategy, seed=st.integers(0, 2**31 - 1))
def test_view_stays_inside_the_level(env_id, actions, seed):
    env, params, _, run = scenario(env_id)
    _, (states, *_rest) = run(jax.random.PRNGKey(seed), jnp.asarray(actions, jnp.int32), params)
    z, x, y = (np.asarray(a) for a in (states.z, states.x, states.y))
    w = np.asarray(params.slide.level_width)[z]
    h = np.asarray(params.slide.level_height)[z]
    assert np.all((z >= 0) & (z < env.n_levels))
    assert np.all((x >= 0) & (x + env.tile_size <= w)) and np.all((y >= 0) & (y + env.tile_size <= h))


@pytest.mark.parametrize("env_id", ENV_IDS)
@SETTINGS
@given(level=st.integers(0, 6), u=st.floats(0, 1), v=st.floats(0, 1))
def test_zoom_in_then_out_returns_to_the_same_place(env_id, level, u, v):
    env, params, step, _ = scenario(env_id, reward="histogym", auto_reset=False)
    z = level % (env.n_levels - 1)  # any level but the finest
    t = env.tile_size
    w, h = int(params.slide.level_width[z]), int(params.slide.level_height[z])
    x, y = round(u * (w - t)), round(v * (h - t))
    ratio = float(params.slide.downsample[z] / params.slide.downsample[z + 1])
    fx, fy = round((x + t / 2) * ratio - t / 2), round((y + t / 2) * ratio - t / 2)
    wf, hf = int(params.slide.level_width[z + 1]), int(params.slide.level_height[z + 1])
    assume(0 <= fx <= wf - t and 0 <= fy <= hf - t)  # away from the borders of the finer level
    s = histojax.EnvState(z=jnp.int32(z), x=jnp.int32(x), y=jnp.int32(y), t=jnp.int32(0), slide_index=jnp.int32(0))
    key = jax.random.PRNGKey(0)
    _, s_in, *_ = step(key, s, ZOOM_IN, params)
    assert int(s_in.z) == z + 1
    _, s_out, *_ = step(key, s_in, ZOOM_OUT, params)
    assert (int(s_out.z), int(s_out.x), int(s_out.y)) == (z, x, y)


@pytest.mark.parametrize("reward", ["histogym", "sparse", "dense"])
@SETTINGS
@given(actions=actions_strategy, seed=st.integers(0, 2**31 - 1))
def test_rewards_are_finite_and_in_the_documented_range(reward, actions, seed):
    env, params, _, run = scenario("HistoJAX-Easy-v0", reward=reward)
    _, (_, rewards, term, _, success) = run(jax.random.PRNGKey(seed), jnp.asarray(actions, jnp.int32), params)
    rewards = np.asarray(rewards)
    low, high = env.reward_range(params)
    assert np.all(np.isfinite(rewards))
    assert np.all(rewards >= low - 1e-5) and np.all(rewards <= high + 1e-5)
    np.testing.assert_array_equal(np.asarray(term), np.asarray(success) & (reward != "histogym"))


@SETTINGS
@given(max_steps=st.integers(1, T_STEPS - 1), seed=st.integers(0, 2**31 - 1))
def test_t_counts_steps_and_truncation_is_exactly_at_max_steps(max_steps, seed):
    env, params, _, run = scenario("HistoJAX-Medium-v0", reward="histogym")  # never terminates
    params = params.replace(max_steps_in_episode=max_steps)
    start, (states, _, term, trunc, _) = run(jax.random.PRNGKey(seed), jnp.full(T_STEPS, STAY, jnp.int32), params)
    trunc, t = np.asarray(trunc), np.asarray(states.t)
    assert not np.any(np.asarray(term))
    expected = np.zeros(T_STEPS, bool)
    expected[max_steps - 1 :: max_steps] = True  # truncated at step max_steps, then again after each auto-reset
    np.testing.assert_array_equal(trunc, expected)
    # t grows by one per step and restarts at 0 after the auto-reset
    np.testing.assert_array_equal(t, np.where(expected, 0, (np.arange(T_STEPS) % max_steps) + 1))
    # the auto-reset state is a valid start: coarsest level, on a start position
    after = np.nonzero(expected)[0]
    assert np.all(np.asarray(states.z)[after] == 0)
    logits = np.asarray(params.slide.start_logits)
    assert np.all(np.isfinite(logits[np.asarray(states.y)[after], np.asarray(states.x)[after]]))


@SETTINGS
@given(actions=st.lists(st.integers(0, 6), min_size=8, max_size=8), seed=st.integers(0, 2**31 - 1))
def test_vmap_of_step_equals_a_loop_of_steps(actions, seed):
    env, params, step, _ = scenario("HistoJAX-Hard-v0")
    batched = _vmapped_step(env)
    keys = jax.random.split(jax.random.PRNGKey(seed), 8)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    acts = jnp.asarray(actions, jnp.int32)
    out_b = batched(keys, states, acts, params)
    for i in range(8):
        s_i = jax.tree.map(lambda a: a[i], states)
        out_i = step(keys[i], s_i, acts[i], params)
        for leaf_b, leaf_i in zip(jax.tree.leaves(out_b), jax.tree.leaves(out_i)):
            np.testing.assert_array_equal(np.asarray(leaf_b[i]), np.asarray(leaf_i))


@functools.lru_cache(maxsize=None)
def _vmapped_step(env):
    return jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))


@settings(deadline=None, max_examples=examples(10, 2), derandomize=True)
@given(actions=st.lists(st.integers(0, 6), min_size=12, max_size=12), seed=st.integers(0, 2**31 - 1))
def test_jitted_equals_not_jitted_and_same_key_same_trajectory(actions, seed):
    env, params, step, _ = scenario("HistoJAX-Medium-v0")
    key = jax.random.PRNGKey(seed)
    _, s_j = env.reset(key, params)
    s_n = s_j
    for i, a in enumerate(actions):
        k = jax.random.fold_in(key, i)
        o_j, s_j, r_j, te_j, tr_j, _ = step(k, s_j, a, params)
        with jax.disable_jit():
            o_n, s_n, r_n, te_n, tr_n, _ = env.step(k, s_n, a, params)
        np.testing.assert_array_equal(np.asarray(o_j), np.asarray(o_n))
        assert float(r_j) == pytest.approx(float(r_n), abs=1e-6)
        assert [int(v) for v in jax.tree.leaves(s_j)] == [int(v) for v in jax.tree.leaves(s_n)]
        assert (bool(te_j), bool(tr_j)) == (bool(te_n), bool(tr_n))
