"""Gymnasium bridges (needs ``pip install histojax[gymnasium]``): numpy in and out, for
Stable-Baselines3, Tianshou and other Gymnasium users.

* :class:`GymnasiumEnv` — one environment as a ``gymnasium.Env`` (``reset(seed=...)``,
  ``render_mode="rgb_array"``).
* :class:`GymnasiumVectorEnv` — ``num_envs`` environments as a ``gymnasium.vector.VectorEnv``,
  the whole batch stepped by one jitted ``vmap`` on the device, with Gymnasium's default
  ``NEXT_STEP`` autoreset: the step after an episode ends ignores that sub-environment's action
  and returns its reset observation with reward 0 and both flags false.
"""
from __future__ import annotations

import dataclasses

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces as gym_spaces

from histojax.env import HistoEnv


def _without_autoreset(env: HistoEnv) -> HistoEnv:
    return dataclasses.replace(env, auto_reset=False)


def single_spaces(env: HistoEnv, params):
    """Gymnasium ``(observation_space, action_space)`` of one environment."""
    t = env.tile_size
    if env.obs_mode == "features":
        view = gym_spaces.Box(-np.inf, np.inf, (params.slide.features.shape[-1],), np.float32)
    elif env.obs_mode == "pixels":
        view = gym_spaces.Box(0, 255, (t, t, 3), np.uint8)
    else:
        view = gym_spaces.Box(0.0, 1.0, (t, t, 3), np.float32)
    obs_space = view
    if env.with_position:
        key = "features" if env.obs_mode == "features" else "pixels"
        obs_space = gym_spaces.Dict({key: view, "position": gym_spaces.Box(0.0, 1.0, (3,), np.float32)})
    if env.action_mode == "discrete":
        action_space = gym_spaces.Discrete(env.num_actions)
    else:
        action_space = gym_spaces.Box(-1.0, 1.0, (env.num_actions,), np.float32)
    return obs_space, action_space


def _numpy(tree):
    return jax.tree.map(np.asarray, jax.device_get(tree))


class GymnasiumEnv(gymnasium.Env):
    """One histojax environment as a ``gymnasium.Env`` (numpy observations, Python scalars)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, env: HistoEnv, params=None, render_mode: str | None = None):
        self.env = _without_autoreset(env)
        self.params = env.default_params if params is None else params
        self.observation_space, self.action_space = single_spaces(env, self.params)
        self.render_mode = render_mode
        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self.env.step)
        self._key = None
        self._state = None

    def reset(self, *, seed: int | None = None, options=None):
        """Start an episode; ``seed`` fixes the whole following trajectory."""
        super().reset(seed=seed)
        if seed is not None or self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)) if seed is None else seed)
        self._key, key = jax.random.split(self._key)
        obs, self._state = self._reset(key, self.params)
        return _numpy(obs), {}

    def step(self, action):
        """``(obs, reward, terminated, truncated, info)`` with numpy / Python values."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._key, key = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, info = self._step(key, self._state, action, self.params)
        info = {k: v.item() if np.ndim(v) == 0 else v for k, v in _numpy(info).items()}
        return _numpy(obs), float(reward), bool(terminated), bool(truncated), info

    def render(self):
        """RGB uint8 picture of the slide with the current view (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self.env.render(self._state, self.params)


class GymnasiumVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` histojax environments stepped together by one jitted ``vmap``."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": gymnasium.vector.AutoresetMode.NEXT_STEP}

    def __init__(self, env: HistoEnv, num_envs: int, params=None, render_mode: str | None = None):
        self.env = _without_autoreset(env)
        self.params = env.default_params if params is None else params
        self.num_envs = int(num_envs)
        self.single_observation_space, self.single_action_space = single_spaces(env, self.params)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.render_mode = render_mode
        inner = self.env
        batch_reset = jax.vmap(inner.reset, in_axes=(0, None))
        batch_step = jax.vmap(inner.step, in_axes=(0, 0, 0, None))

        def step(key, state, action, autoreset, params):
            keys = jax.random.split(key, self.num_envs)
            obs, new, reward, term, trunc, info = batch_step(keys, state, action, params)
            obs_re, state_re = batch_reset(keys, params)

            def pick(a, b):
                mask = autoreset.reshape(autoreset.shape + (1,) * (a.ndim - 1))
                return jnp.where(mask, a, b)

            obs = jax.tree.map(pick, obs_re, obs)
            new = jax.tree.map(pick, state_re, new)
            zero = jnp.zeros_like(term)
            return (obs, new, jnp.where(autoreset, 0.0, reward), jnp.where(autoreset, zero, term),
                    jnp.where(autoreset, zero, trunc), info)

        self._reset = jax.jit(lambda key, params: batch_reset(jax.random.split(key, self.num_envs), params))
        self._step = jax.jit(step)
        self._key = None
        self._state = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | None = None, options=None):
        """Reset all sub-environments: ``(obs batch, info)``."""
        if seed is not None:
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(seed)
        if seed is not None or self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)) if seed is None else seed)
        self._key, key = jax.random.split(self._key)
        obs, self._state = self._reset(key, self.params)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        return _numpy(obs), {}

    def step(self, actions):
        """``(obs, rewards, terminations, truncations, info)`` batches (numpy), NEXT_STEP autoreset."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._key, key = jax.random.split(self._key)
        obs, self._state, reward, term, trunc, info = self._step(
            key, self._state, jnp.asarray(actions), jnp.asarray(self._autoreset), self.params)
        term, trunc = np.asarray(term), np.asarray(trunc)
        self._autoreset = term | trunc
        return _numpy(obs), np.asarray(reward, dtype=np.float32), term, trunc, _numpy(info)

    def render(self):
        """Picture of sub-environment 0 (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self.env.render(jax.tree.map(lambda a: a[0], self._state), self.params)


def make_gymnasium_env(env_id: str, slide=None, render_mode: str | None = None, **overrides) -> GymnasiumEnv:
    """``histojax.make(env_id, slide, **overrides)`` as a :class:`GymnasiumEnv`."""
    from histojax.registry import make

    env, params = make(env_id, slide=slide, **overrides)
    return GymnasiumEnv(env, params, render_mode=render_mode)


def register_gymnasium_envs() -> None:
    """Register every histojax id with Gymnasium as ``"histojax/<id>"``, so
    ``gymnasium.make("histojax/HistoJAX-Easy-v0", slide=..., **overrides)`` works."""
    from histojax.registry import registered_envs

    for env_id in registered_envs():
        name = f"histojax/{env_id}"
        if name not in gymnasium.registry:
            gymnasium.register(name, entry_point="histojax.gymnasium_bridge:make_gymnasium_env",
                               kwargs={"env_id": env_id}, disable_env_checker=True)


register_gymnasium_envs()
