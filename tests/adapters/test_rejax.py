"""rejax (the ``rejax`` extra; ``make test-integrations``), an RL library written for gymnax
environments, trains PPO on histojax unchanged but for the line that makes the env: rejax steps the
old 5-value API, so the env goes in through ``GymnaxV0Wrapper``."""

from __future__ import annotations

import jax
import numpy as np
import pytest

rejax = pytest.importorskip("rejax")

import histojax  # noqa: E402
from histojax.adapters.jax import GymnaxV0Wrapper  # noqa: E402


def test_rejax_ppo_trains_and_evaluates():
    env, params = histojax.make("HistoJAX-Easy-v0", max_steps_in_episode=8)
    algo = rejax.PPO.create(
        env=GymnaxV0Wrapper(env),
        env_params=params,
        total_timesteps=128,
        eval_freq=64,
        num_envs=4,
        num_steps=16,
        num_epochs=1,
        num_minibatches=2,
        agent_kwargs={"hidden_layer_sizes": (16,)},
    )
    ts, (lengths, returns) = jax.jit(algo.train)(jax.random.PRNGKey(0))
    lengths, returns = np.asarray(lengths), np.asarray(returns)
    assert lengths.shape == (3, 128)  # before training and after each 64 steps, 128 evaluation episodes
    assert ((lengths >= 1) & (lengths <= 8)).all() and np.isfinite(returns).all()
    assert int(ts.actor_ts.step) == 2 * 1 * 2  # 2 iterations x 1 epoch x 2 minibatches of updates
    assert int(ts.global_step) == 128
