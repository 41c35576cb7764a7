"""histojax as a gymnax environment: gymnax's own classes and wrappers run it unchanged, jit with the
env as a static argument never confuses two envs, wrappers copy and pickle, and code written for the
old 5-value step (PureJaxRL's shape) keeps its metrics small."""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import pickle
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tifffile

import histojax
from histojax.adapters.jax import GymnaxV0Wrapper, LogWrapper

gymnax = pytest.importorskip("gymnax")
from gymnax.environments import environment as gymnax_environment  # noqa: E402
from gymnax.environments import spaces as gymnax_spaces  # noqa: E402
from gymnax.wrappers import purerl  # noqa: E402
from gymnax.wrappers.gym import GymnaxToGymWrapper  # noqa: E402

KEY = jax.random.PRNGKey(0)
GYMNAX_INFO_KEYS = {"terminated", "truncated", "final_observation"}  # what gymnax 1.0's step always adds


@pytest.fixture(scope="module")
def blank_bundle(tmp_path_factory):
    """A small noise slide without tumour, built with the sample's tile size (128) and Easy levels."""
    from data_tools.bundle import build_bundle

    root = tmp_path_factory.mktemp("blank")
    rng = np.random.default_rng(3)
    tifffile.imwrite(root / "blank.tif", rng.integers(0, 120, (600, 800, 3), dtype=np.uint8), photometric="rgb")
    return build_bundle(root / "blank.tif", root / "bundle", level_sets=(3,), progress=False)


@pytest.fixture(scope="module")
def easy():
    return histojax.make("HistoJAX-Easy-v0", reward="histogym", max_steps_in_episode=4)


# ------------------------------------------------------------------ equality / jit with a static env
def test_jit_with_static_env_keeps_each_envs_slide_and_settings(blank_bundle):
    a, _ = histojax.make("HistoJAX-Easy-v0")
    b, _ = histojax.make("HistoJAX-Easy-v0", slide=blank_bundle, max_steps_in_episode=3)

    @functools.partial(jax.jit, static_argnums=0)
    def first_look(env, key):  # params=None: the env's own slide and settings
        obs, state = env.reset(key)
        return obs, state, env.default_params.max_steps_in_episode

    for env, limit in ((a, 100), (b, 3), (a, 100)):
        obs, state, got_limit = first_look(env, KEY)
        z, x, y = int(state.z), int(state.x), int(state.y)
        np.testing.assert_array_equal(np.asarray(obs), env.bundles[0].pixels[z][y : y + 128, x : x + 128])
        assert int(got_limit) == limit
    assert a != b and hash(a) != hash(b)


def test_equality_is_settings_by_value_and_data_by_identity(easy):
    env, _ = easy
    assert dataclasses.replace(env) == env and hash(dataclasses.replace(env)) == hash(env)
    assert dataclasses.replace(env, final_observation=False) != env
    assert copy.deepcopy(env) != env  # same content, other arrays: compiled anew, never confused
    again, _ = histojax.make("HistoJAX-Easy-v0", reward="histogym", max_steps_in_episode=4)
    assert again != env


# ------------------------------------------------------------------ gymnax's classes and info keys
def test_env_and_spaces_are_gymnax_classes():
    env, params = histojax.make("HistoJAX-Easy-v0", with_position=True)
    assert isinstance(env, gymnax_environment.Environment)
    assert isinstance(env.action_space(params), gymnax_spaces.Discrete)
    obs_space = env.observation_space(params)
    assert isinstance(obs_space, gymnax_spaces.Dict) and isinstance(obs_space.spaces["pixels"], gymnax_spaces.Box)
    obs, state = env.reset(KEY, params)
    assert bool(obs_space.contains(obs))  # gymnax's Dict reads members by attribute; ours takes the dict
    cont, cparams = histojax.make("HistoJAX-Easy-v0", action_mode="continuous")
    space = cont.action_space(cparams)
    assert isinstance(space, gymnax_spaces.Box) and not isinstance(space, gymnax_spaces.Discrete)
    assert space.shape == (3,) and float(space.low) == -1.0
    gym_space = gymnax_spaces.gymnax_space_to_gym_space(obs_space)
    assert gym_space.contains(jax.tree.map(np.asarray, obs))
    assert bool(env.is_truncated(state.replace(t=jnp.int32(100)), params))


@pytest.mark.parametrize("overrides", [{}, {"auto_reset": False}, {"final_observation": False}])
def test_info_has_gymnax_keys_in_every_mode(easy, overrides):
    env, params = easy
    env = dataclasses.replace(env, **overrides)
    _, state = env.reset(KEY, params)
    obs, state, reward, term, trunc, info = jax.jit(env.step)(KEY, state, 6, params)
    assert GYMNAX_INFO_KEYS | {"discount"} <= set(info)
    assert bool(info["terminated"]) == bool(term) and bool(info["truncated"]) == bool(trunc)
    final = info["final_observation"]
    if env.auto_reset and not env.final_observation:
        assert final.shape == (0,)  # the key without a wrong view: code that uses it fails loudly
    else:
        np.testing.assert_array_equal(np.asarray(final), np.asarray(obs))  # no reset happened here


# ------------------------------------------------------------------ gymnax's own wrappers, unchanged
def test_gymnax_purerl_wrappers_run_unchanged(easy):
    env, params = easy
    wrapped = purerl.LogWrapper(purerl.FlattenObservationWrapper(purerl.StickyActionWrapper(env, 0.5)))
    assert wrapped.observation_space(params).shape == (128 * 128 * 3,)
    keys = jax.random.split(KEY, 3)
    obs, state = jax.vmap(wrapped.reset, in_axes=(0, None))(keys, params)
    step = jax.jit(jax.vmap(wrapped.step, in_axes=(0, 0, 0, None)))
    sticky = []
    for i in range(4):
        actions = jnp.full((3,), i % 7)
        obs, state, reward, term, trunc, info = step(
            jax.random.split(jax.random.fold_in(KEY, i), 3), state, actions, params
        )
        sticky.append(np.asarray(state.env_state.last_action))
    assert obs.shape == (3, 128 * 128 * 3) and info["final_observation"].shape == (3, 128 * 128 * 3)
    assert bool(info["returned_episode"].all()) and (np.asarray(info["returned_episode_lengths"]) == 4).all()
    assert np.isfinite(np.asarray(info["returned_episode_returns"])).all()
    assert (np.stack(sticky)[0] == 0).all()  # the first replayed action is gymnax's initial 0


@pytest.mark.parametrize("overrides", [{"auto_reset": False}, {"final_observation": False}])
def test_flatten_wrapper_runs_on_lean_and_non_resetting_envs(easy, overrides):
    env, params = easy
    wrapped = purerl.FlattenObservationWrapper(dataclasses.replace(env, **overrides))
    obs, state = wrapped.reset(KEY, params)
    obs, state, *_, info = wrapped.step(KEY, state, 6, params)  # KeyError before: no final_observation
    assert obs.shape == (128 * 128 * 3,)


def test_gymnax_to_gym_wrapper_runs_unchanged(easy):
    env, params = easy
    genv = GymnaxToGymWrapper(env, params, seed=1)
    assert genv.action_space.n == 7 and genv.observation_space.shape == (128, 128, 3)
    obs, _ = genv.reset(seed=2)
    assert genv.observation_space.contains(np.asarray(obs))
    for i in range(4):
        obs, reward, terminated, truncated, info = genv.step(i % 7)
        assert genv.observation_space.contains(np.asarray(obs))
    assert bool(truncated) and info["final_observation"].shape == (128, 128, 3)


def test_gymnax_to_vector_gym_wrapper_runs_through_a_plain_wrapper(easy):
    from gymnax.wrappers.gym import GymnaxToVectorGymWrapper

    from histojax.adapters.jax import Wrapper

    env, params = easy
    with pytest.raises(dataclasses.FrozenInstanceError):  # it assigns to env.reset / env.step
        GymnaxToVectorGymWrapper(env, 2, params)
    venv = GymnaxToVectorGymWrapper(Wrapper(env), 2, params)
    obs, _ = venv.reset(seed=0)
    obs, reward, term, trunc, info = venv.step(np.array([4, 6]))
    assert obs.shape == (2, 128, 128, 3) and reward.shape == (2,) and info["final_observation"].shape == obs.shape


# ------------------------------------------------------------------ copies
@pytest.mark.parametrize("wrap", [LogWrapper, GymnaxV0Wrapper])
def test_wrappers_deepcopy_and_pickle(easy, wrap):
    env, params = easy
    wrapped = wrap(env)
    for clone in (copy.deepcopy(wrapped), pickle.loads(pickle.dumps(wrapped))):
        assert type(clone) is wrap and clone.n_levels == env.n_levels
        obs, _ = clone.reset(KEY, params)
        np.testing.assert_array_equal(np.asarray(obs), np.asarray(wrapped.reset(KEY, params)[0]))
    with pytest.raises(AttributeError):
        wrapped.no_such_attribute


# ------------------------------------------------------------------ PureJaxRL's shape: old 5-value step
class _Flatten5:
    """A 5-value flattening wrapper that, like PureJaxRL's, accepts only gymnax ``Box`` observations."""

    def __init__(self, env):
        self._env = env

    def __getattr__(self, name):
        return getattr(self.__dict__["_env"], name)

    def observation_space(self, params):
        space = self._env.observation_space(params)
        assert isinstance(space, gymnax_spaces.Box), "Only Box spaces are supported for now."
        return gymnax_spaces.Box(space.low, space.high, (int(np.prod(space.shape)),), space.dtype)

    def reset(self, key, params=None):
        obs, state = self._env.reset(key, params)
        return obs.reshape(-1), state

    def step(self, key, state, action, params=None):
        obs, state, reward, done, info = self._env.step(key, state, action, params)
        return obs.reshape(-1), state, reward, done, info


def _make_train(num_envs: int, num_steps: int, num_updates: int):
    """A PPO-shaped trainer over the old 5-value step that keeps *all* of ``info`` as metrics."""
    import flax.linen as nn
    import optax

    env, params = histojax.make("HistoJAX-Easy-v0", max_steps_in_episode=8)
    env = _Flatten5(GymnaxV0Wrapper(env))
    n_actions = env.action_space(params).n
    obs_shape = env.observation_space(params).shape

    class Policy(nn.Module):
        @nn.compact
        def __call__(self, x):
            h = nn.tanh(nn.Dense(16)(x.astype(jnp.float32) / 255.0))
            return nn.Dense(n_actions)(h), nn.Dense(1)(h)[..., 0]

    net, tx = Policy(), optax.adam(1e-3)

    def train(key):
        key, k_init, k_reset = jax.random.split(key, 3)
        weights = net.init(k_init, jnp.zeros(obs_shape))
        opt = tx.init(weights)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, num_envs), params)

        def update(carry, _):
            weights, opt, obs, state, key = carry

            def env_step(carry, _):
                obs, state, key = carry
                key, k_act, k_step = jax.random.split(key, 3)
                logits, value = net.apply(weights, obs)
                action = jax.random.categorical(k_act, logits)
                next_obs, state, reward, done, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                    jax.random.split(k_step, num_envs), state, action, params
                )
                return (next_obs, state, key), (obs, action, reward, done, value, info)

            (obs, state, key), (b_obs, b_act, b_rew, b_done, b_val, info) = jax.lax.scan(
                env_step, (obs, state, key), None, num_steps
            )

            def loss(w):
                logits, value = net.apply(w, b_obs)
                logp = jax.nn.log_softmax(logits)
                chosen = jnp.take_along_axis(logp, b_act[..., None], axis=-1)[..., 0]
                advantage = b_rew - b_val * (1 - b_done)
                return -(chosen * jax.lax.stop_gradient(advantage)).mean() + ((value - b_rew) ** 2).mean()

            grads = jax.grad(loss)(weights)
            changes, opt = tx.update(grads, opt)
            return (optax.apply_updates(weights, changes), opt, obs, state, key), info

        _, metrics = jax.lax.scan(update, (weights, opt, obs, state, key), None, num_updates)
        return metrics

    return train


def test_purejaxrl_shaped_training_keeps_all_info_small():
    num_envs, num_steps, num_updates = 4, 8, 2
    metrics = jax.jit(_make_train(num_envs, num_steps, num_updates))(KEY)
    transitions = num_envs * num_steps * num_updates
    per_step = sum(int(a.nbytes) for a in jax.tree.leaves(metrics)) / transitions
    assert "final_observation" not in metrics and {"terminated", "truncated", "success"} <= set(metrics)
    assert per_step <= 64, f"{per_step:.0f} bytes of info per env step (a view is 49152)"
    assert bool(metrics["truncated"].any())  # 16 steps per env with an 8-step limit


def test_gymnax_v0_wrapper_steps_one_view_and_same_trajectory(easy):
    env, params = easy
    old = GymnaxV0Wrapper(env)
    assert old.final_observation is False  # wrapped lean: nobody reads the last view through it
    _, s_new = env.reset(KEY, params)
    s_old = s_new
    for i in range(6):
        k = jax.random.fold_in(KEY, i)
        o_new, s_new, r_new, te, tr, _ = env.step(k, s_new, i % 7, params)
        o_old, s_old, r_old, done, info = old.step(k, s_old, i % 7, params)
        np.testing.assert_array_equal(np.asarray(o_new), np.asarray(o_old))
        assert float(r_new) == float(r_old) and bool(done) == bool(te | tr)


# ------------------------------------------------------------------ without gymnax
def test_without_gymnax_the_stand_in_spaces_work():
    code = """
import sys
sys.modules["gymnax"] = None  # as if gymnax were not installed
import jax, jax.numpy as jnp, histojax
from histojax.core import spaces
assert not spaces.GYMNAX and histojax.HistoEnv.__mro__[1] is object
env = histojax.HistoEnv(n_levels=3, with_position=True)
assert type(env.action_space()) is spaces.Discrete and env.action_space().n == 7
space = env.observation_space()
obs = space.sample(jax.random.PRNGKey(0))
assert bool(space.contains(obs)) and not bool(space.contains({**obs, "position": jnp.full(3, 2.0)}))
assert obs["pixels"].dtype == jnp.uint8 and obs["pixels"].shape == (128, 128, 3)
print("ok")
"""
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ), timeout=300
    )
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
