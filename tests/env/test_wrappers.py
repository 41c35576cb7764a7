"""LogWrapper statistics and the older 5-value step."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import histojax
from histojax.adapters.jax import GymnaxV0Wrapper, LogWrapper


def test_log_wrapper_counts_returns_and_lengths():
    env, params = histojax.make("HistoJAX-Easy-v0", reward="histogym", max_steps_in_episode=7)
    logged = LogWrapper(env)
    key = jax.random.PRNGKey(1)
    _, state = logged.reset(key, params)
    step = jax.jit(logged.step)
    total = 0.0
    for i in range(7):
        _, state, reward, term, trunc, info = step(jax.random.fold_in(key, i), state, i % 7, params)
        total += float(reward)
    assert bool(trunc) and bool(info["returned_episode"])
    assert int(info["returned_episode_lengths"]) == 7
    assert (
        float(info["returned_episode_returns"]) == np.float32(total)
        or abs(float(info["returned_episode_returns"]) - total) < 1e-3
    )
    assert float(state.episode_returns) == 0.0 and int(state.episode_lengths) == 0
    assert logged.action_space(params).n == 7  # attributes pass through


def test_gymnax_v0_wrapper_returns_five_values():
    env, params = histojax.make("HistoJAX-Easy-v0", max_steps_in_episode=1)
    old = GymnaxV0Wrapper(env)
    obs, state = old.reset(jax.random.PRNGKey(0), params)
    out = old.step(jax.random.PRNGKey(0), state, 6, params)
    assert len(out) == 5
    obs, state, reward, done, info = out
    assert bool(done) and bool(info["truncated"]) and not bool(info["terminated"])
    assert obs.shape == (128, 128, 3) and "final_observation" not in info  # old gymnax had none
    assert jnp.issubdtype(reward.dtype, jnp.floating)
