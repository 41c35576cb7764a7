"""``EnvParams`` changed after ``make``: the host check names the field, and
``histojax.debug.checked`` catches the same values inside ``jit`` (compiled once for the module)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental import checkify

import histojax
from histojax.debug import checked
from histojax.registry import check_params

BAD = {  # the values of the issue: each moved, froze, truncated or scored silently wrong before
    "stride-wraps": ("stride", float(2**31)),
    "stride-negative": ("stride", -3.0),
    "stride-nan": ("stride", float("nan")),
    "max_steps-negative": ("max_steps_in_episode", -5),
    "step_cost-nan": ("step_cost", float("nan")),
    "success_threshold-zero": ("success_threshold", 0.0),
    "dense_weight-inf": ("dense_weight", float("inf")),
    "start_level-fraction": ("start_level", 0.5),
}


@pytest.fixture(scope="module")
def easy(sample_envs):
    return sample_envs["HistoJAX-Easy-v0"]


@pytest.fixture(scope="module")
def checked_fns(easy):
    env, _ = easy
    return checked(env)


def test_valid_params_pass(easy, checked_fns):
    env, params = easy
    check_params(env, params)
    check_params(env, params.replace(stride=0.5, max_steps_in_episode=7, step_cost=0.0))
    reset, step = checked_fns
    err, (obs, state) = reset(jax.random.key(0), params)
    err.throw()
    err, _ = step(jax.random.key(1), state, jnp.int32(histojax.RIGHT), params)
    err.throw()


@pytest.mark.parametrize("case", sorted(BAD))
def test_host_check_names_the_field(easy, case):
    env, params = easy
    field, value = BAD[case]
    with pytest.raises(ValueError, match=f"{field}="):
        check_params(env, params.replace(**{field: value}))


def test_host_check_of_a_vmapped_batch(easy):
    env, params = easy
    check_params(env, params.replace(stride=np.array([0.5, 1.0, 2.0], np.float32)))
    with pytest.raises(ValueError, match="stride="):
        check_params(env, params.replace(stride=np.array([0.5, -1.0, 2.0], np.float32)))


@pytest.mark.parametrize("case", sorted(BAD))
def test_checked_reset_and_step_catch_it(easy, checked_fns, case):
    env, params = easy
    field, value = BAD[case]
    reset, step = checked_fns
    _, (_, state) = reset(jax.random.key(0), params)
    bad = params.replace(**{field: value})
    err, _ = reset(jax.random.key(0), bad)
    with pytest.raises(checkify.JaxRuntimeError, match=field):
        err.throw()
    err, _ = step(jax.random.key(1), state, jnp.int32(histojax.RIGHT), bad)
    with pytest.raises(checkify.JaxRuntimeError, match=field):
        err.throw()


def test_trainer_and_evaluate_refuse_bad_params(easy):
    """The entry points that take params from the user check them on the host before compiling."""
    from baselines.episodes.rollout import run_episodes

    env, params = easy
    with pytest.raises(ValueError, match="evaluate: env params: stride="):
        run_episodes(
            env,
            params.replace(stride=-3.0),
            lambda key, obs: jnp.zeros(obs.shape[0], jnp.int32),
            jax.random.key(0),
            num_episodes=2,
        )


def test_gymnasium_adapter_refuses_bad_params(easy):
    pytest.importorskip("gymnasium")
    from histojax.adapters.gymnasium import GymnasiumEnv

    env, params = easy
    with pytest.raises(ValueError, match="GymnasiumEnv: params: max_steps_in_episode="):
        GymnasiumEnv(env, params.replace(max_steps_in_episode=-5))


def test_ppo_trainer_refuses_bad_params():
    """``run(keys, params)`` of a trainer checks params given after make before compiling anything."""
    from baselines import ppo
    from baselines.harness.runner import run_seeds

    train = ppo.make_train(
        dict(
            env_id="HistoJAX-Easy-v0",
            num_envs=4,
            num_steps=8,
            total_timesteps=64,
            update_epochs=1,
            num_minibatches=2,
            hidden=8,
            num_seeds=1,
            print_progress=False,
        )
    )
    keys = jax.random.split(jax.random.key(0), 1)
    with pytest.raises(ValueError, match="train: env params: stride="):
        run_seeds(train, keys, train.env_params.replace(stride=float("nan")))
