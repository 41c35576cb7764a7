"""A Stable-Baselines3 ``VecEnv`` over the batched env (needs ``pip install histojax[sb3]``): SB3's
algorithms step ``num_envs`` histojax environments with one jitted ``vmap`` on the device instead of
one Python env at a time.

    venv = SB3VecEnv(*histojax.make("HistoJAX-Easy-v0"), num_envs=16)   # or make_sb3_vec_env(id, 16)
    model = stable_baselines3.PPO("CnnPolicy", VecMonitor(venv)).learn(10_000)

It follows SB3's own ``DummyVecEnv`` over :class:`~histojax.adapters.gymnasium.GymnasiumEnv`\\ s step
for step (same seeds and actions give the same arrays): ``reset()`` resets every sub-environment
(with the seeds of ``venv.seed(s)``, ``s + i`` for sub-env ``i``, used once); a sub-environment
whose episode ends resets within the same step, its last observation in
``infos[i]["terminal_observation"]`` and ``infos[i]["TimeLimit.truncated"]`` true when the step
limit (not success) ended it; ``dones = terminated | truncated``; rewards float32; numpy arrays
are writable copies. ``infos[i]`` also holds ``tumour_fraction``, ``success``, ``discount``,
``terminated`` and ``truncated`` as Python scalars. Episode returns for SB3's logger come from
wrapping the adapter in ``VecMonitor``.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from histojax.adapters.gymnasium import (
    _reset_batch,
    _without_autoreset,
    numpy_copy,
    seeded_keys,
    select,
    settings_only,
    single_spaces,
    split_keys,
    without_final_observation,
)
from histojax.core.env import HistoEnv


@functools.partial(jax.jit, static_argnums=0)
def _step_batch_same(env: HistoEnv, keys, state, action, params):
    """One step with SB3's same-step reset; each sub-env's key is split once for the step and once
    more for the reset when its episode ended (as ``GymnasiumEnv.step`` then ``reset``):
    ``(obs, state, reward, terminated, truncated, info, final_obs, keys)``."""
    keys, subs = split_keys(keys)
    obs, new, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(subs, state, action, params)
    done = term | trunc
    keys_re, subs_re = split_keys(keys)
    obs_re, state_re = jax.vmap(env.reset, in_axes=(0, None))(subs_re, params)
    return (
        select(done, obs_re, obs),
        select(done, state_re, new),
        reward,
        term,
        trunc,
        without_final_observation(info),
        obs,
        select(done, keys_re, keys),
    )


class SB3VecEnv(VecEnv):
    """``num_envs`` histojax environments as one Stable-Baselines3 ``VecEnv`` (see the module doc)."""

    def __init__(self, env: HistoEnv, num_envs: int, params=None, render_mode: str | None = None):
        self.env = _without_autoreset(env)
        self.params = env.default_params if params is None else params
        self.render_mode = render_mode
        self._static = settings_only(self.env)
        self._keys = None
        self._state = None
        self._actions = None
        self._rng = np.random.default_rng()
        observation_space, action_space = single_spaces(env, self.params)
        super().__init__(int(num_envs), observation_space, action_space)

    def reset(self):
        """Reset every sub-environment (seeds of ``seed()`` once, else the running keys): obs batch."""
        keys = seeded_keys(self._keys, self._seeds, np.ones(self.num_envs, bool), self._rng)
        obs, self._state, self._keys = _reset_batch(self._static, keys, None, None, None, self.params)
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return numpy_copy(obs)

    def step_async(self, actions: np.ndarray) -> None:
        """Remember ``actions`` (``(num_envs,)`` ints or ``(num_envs, k)`` floats) for :meth:`step_wait`."""
        self._actions = np.asarray(actions)

    def step_wait(self):
        """``(obs, rewards float32, dones bool, infos)`` of one step of every sub-environment."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        obs, self._state, reward, term, trunc, info, final_obs, self._keys = _step_batch_same(
            self._static, self._keys, self._state, self._actions, self.params
        )
        term, trunc = np.array(term), np.array(trunc)
        dones = term | trunc
        info = numpy_copy(info)
        infos = [{k: v[i].item() for k, v in info.items()} for i in range(self.num_envs)]
        if dones.any():
            final_obs = numpy_copy(final_obs)
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = jax.tree.map(lambda a: a[i], final_obs)
        for i in range(self.num_envs):
            infos[i]["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
        return numpy_copy(obs), np.array(reward, dtype=np.float32), dones, infos

    def close(self) -> None:
        """Nothing to release (the device arrays go with the object)."""

    def _state_of(self, i: int):
        return jax.tree.map(lambda a: a[i], self._state)

    def get_images(self):
        """RGB pictures (slide, current view) of every sub-environment (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return [None] * self.num_envs
        return [self.env.render(self._state_of(i), self.params) for i in range(self.num_envs)]

    def get_attr(self, attr_name: str, indices=None) -> list:
        """``attr_name`` of each sub-environment: the adapter's own (``render_mode``, ``params``, what
        :meth:`set_attr` set), else the ``HistoEnv``'s (all sub-environments share one)."""
        source = self if attr_name in self.__dict__ else self.env
        value = getattr(source, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        """Set an attribute shared by all sub-environments (one ``HistoEnv``): only for all of them."""
        if list(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError("the sub-environments of SB3VecEnv share one HistoEnv: set attributes for all of them")
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        """Call ``HistoEnv.<method_name>``; ``render`` draws each sub-environment's own state."""
        indices = list(self._get_indices(indices))
        if method_name == "render":
            return [self.env.render(self._state_of(i), self.params) for i in indices]
        method = getattr(self.env, method_name)
        return [method(*method_args, **method_kwargs) for _ in indices]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        """No sub-environment is wrapped by a Gymnasium wrapper (use ``VecMonitor`` on the adapter)."""
        return [False for _ in self._get_indices(indices)]


def make_sb3_vec_env(env_id: str, num_envs: int, slide=None, render_mode: str | None = None, **overrides) -> SB3VecEnv:
    """``histojax.make(env_id, slide, **overrides)`` as an :class:`SB3VecEnv` of ``num_envs``."""
    from histojax.registry import make

    env, params = make(env_id, slide=slide, **overrides)
    return SB3VecEnv(env, num_envs, params, render_mode=render_mode)


__all__ = ["SB3VecEnv", "make_sb3_vec_env"]
