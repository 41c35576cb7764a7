"""Pure-JAX wrappers, for gymnax / PureJaxRL / rejax users (jittable, vmappable, like the env):
episode statistics (PureJaxRL's :class:`LogWrapper` for the 6-value step) and the older gymnax
5-value step (:class:`GymnaxV0Wrapper`: ``obs, state, reward, done, info``)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from histojax.core.env import HistoEnv


class Wrapper:
    """Forwards every attribute it lacks to the wrapped environment ``_env``; copies and pickles
    (``copy.deepcopy`` and ``pickle`` make the object before ``_env`` is set: no forwarding then)."""

    def __init__(self, env):
        self._env = env

    def __getattr__(self, name):
        env = self.__dict__.get("_env")
        if env is None or (name.startswith("__") and name.endswith("__")):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(env, name)


@struct.dataclass
class LogEnvState:
    """The wrapped state plus running and last-finished episode statistics."""

    env_state: object
    episode_returns: jnp.ndarray
    episode_lengths: jnp.ndarray
    returned_episode_returns: jnp.ndarray
    returned_episode_lengths: jnp.ndarray
    returned_episode_success: jnp.ndarray
    timestep: jnp.ndarray


class LogWrapper(Wrapper):
    """Adds ``info["returned_episode_returns" | "returned_episode_lengths" | "returned_episode" |
    "returned_episode_success"]``: statistics of the last finished episode (PureJaxRL style)."""

    def reset(self, key, params=None):
        obs, env_state = self._env.reset(key, params)
        zero_f, zero_i = jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32)
        return obs, LogEnvState(env_state, zero_f, zero_i, zero_f, zero_i, jnp.zeros((), bool), zero_i)

    def step(self, key, state: LogEnvState, action, params=None):
        obs, env_state, reward, terminated, truncated, info = self._env.step(key, state.env_state, action, params)
        done = jnp.logical_or(terminated, truncated)
        returns = state.episode_returns + reward
        lengths = state.episode_lengths + 1
        state = LogEnvState(
            env_state=env_state,
            episode_returns=returns * (1 - done),
            episode_lengths=lengths * (1 - done),
            returned_episode_returns=jnp.where(done, returns, state.returned_episode_returns),
            returned_episode_lengths=jnp.where(done, lengths, state.returned_episode_lengths),
            returned_episode_success=jnp.where(done, info["success"], state.returned_episode_success),
            timestep=state.timestep + 1,
        )
        info = {
            **info,
            "returned_episode_returns": state.returned_episode_returns,
            "returned_episode_lengths": state.returned_episode_lengths,
            "returned_episode_success": state.returned_episode_success,
            "returned_episode": done,
        }
        return obs, state, reward, terminated, truncated, info


class GymnaxV0Wrapper(Wrapper):
    """The older gymnax step (gymnax < 1.0, PureJaxRL, rejax): ``(obs, state, reward, done, info)``
    with ``done = terminated or truncated`` and both flags kept in ``info["terminated"]`` /
    ``info["truncated"]``. ``info`` has no ``final_observation`` (older gymnax had none, and
    trainers that keep all of ``info`` as metrics would stack one observation per step); a
    ``HistoEnv`` with auto-reset is therefore wrapped with ``final_observation=False``, which
    extracts one view per step instead of two and gives the same trajectories."""

    def __init__(self, env):
        if isinstance(env, HistoEnv) and env.auto_reset and env.final_observation:
            env = dataclasses.replace(env, final_observation=False)
        super().__init__(env)

    def step(self, key, state, action, params=None):
        """``(obs, state, reward, done, info)``: one step of the wrapped env, flags merged."""
        obs, state, reward, terminated, truncated, info = self._env.step(key, state, action, params)
        info = {k: v for k, v in info.items() if k != "final_observation"}
        info = {**info, "terminated": terminated, "truncated": truncated}
        return obs, state, reward, jnp.logical_or(terminated, truncated), info


def vmap_reset(env, num_envs: int):
    """``reset`` over ``num_envs`` keys split from one: ``fn(key, params) -> (obs, state)`` batched."""
    return lambda key, params: jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), params)


__all__ = ["GymnaxV0Wrapper", "LogEnvState", "LogWrapper", "Wrapper", "vmap_reset"]
