"""Gymnasium bridges (needs ``pip install histojax[gymnasium]``): numpy in and out, for
Stable-Baselines3, Tianshou and other Gymnasium users.

* :class:`GymnasiumEnv` — one environment as a ``gymnasium.Env`` (``reset(seed=...)``,
  ``render_mode="rgb_array"``).
* :class:`GymnasiumVectorEnv` — ``num_envs`` environments as a ``gymnasium.vector.VectorEnv``,
  the whole batch stepped by one jitted ``vmap`` on the device, following Gymnasium 1.x's own
  ``SyncVectorEnv`` over ``GymnasiumEnv``\\ s step for step (same seeds and actions give the same
  arrays): ``NEXT_STEP`` autoreset (the step after an episode ends ignores that
  sub-environment's action and returns its reset observation with reward 0, both flags false and
  no ``info`` for it: every ``info[key]`` comes with a boolean mask ``info["_" + key]``),
  ``reset(seed=int | [int | None, ...])``, ``reset(options={"reset_mask": mask})``, writable
  numpy arrays. ``gymnasium.make_vec("histojax/<id>", num_envs=n)`` builds one.

Each sub-environment has its own JAX key: ``seed`` ``s`` starts it at ``PRNGKey(s)`` as
``GymnasiumEnv.reset(seed=s)`` does, and every reset or step splits it once.
"""

from __future__ import annotations

import dataclasses
import functools

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np

from histojax.core.env import HistoEnv
from histojax.core.spaces import to_gymnasium


def _without_autoreset(env: HistoEnv) -> HistoEnv:
    return dataclasses.replace(env, auto_reset=False)


def settings_only(env: HistoEnv) -> HistoEnv:
    """``env`` without its default params and bundles: the static argument of the bridges' jitted
    functions, which always pass params explicitly. Envs of equal settings are then equal, so all
    bridges over them share one compiled program, and no slide can be read from a wrong env."""
    return dataclasses.replace(env, _default_params=None, _bundle=None, _bundles=())


def single_spaces(env: HistoEnv, params):
    """Gymnasium ``(observation_space, action_space)`` of one environment: the env's own spaces
    converted (:func:`histojax.core.spaces.to_gymnasium`)."""
    return to_gymnasium(env.observation_space(params)), to_gymnasium(env.action_space(params))


def numpy_copy(tree):
    """``tree`` of device arrays as writable numpy arrays (copies, never read-only views)."""
    return jax.tree.map(np.array, tree)


def without_final_observation(info: dict) -> dict:
    """``info`` less ``final_observation`` (the bridges' envs never reset inside a step)."""
    return {k: v for k, v in info.items() if k != "final_observation"}


def seed_key(seed: int) -> jax.Array:
    """The JAX key a sub-environment starts from after ``reset(seed=seed)``."""
    return jax.random.PRNGKey(int(seed))


def seeded_keys(keys, seeds, mask, rng: np.random.Generator) -> jax.Array:
    """The ``(n, 2)`` keys after a reset: ``seed_key(seeds[i])`` where ``seeds[i]`` is not ``None``
    and ``mask[i]``, else the running key ``keys[i]`` (``keys=None``: fresh ones drawn from ``rng``)."""
    if keys is None:
        keys = np.stack([np.asarray(seed_key(rng.integers(0, 2**31 - 1))) for _ in seeds])
    else:
        keys = np.array(keys)
    for i, (s, m) in enumerate(zip(seeds, mask)):
        if s is not None and m:
            keys[i] = np.asarray(seed_key(s))
    return jnp.asarray(keys)


def split_keys(keys: jax.Array):
    """Per-row ``key, sub = jax.random.split(key)`` of a ``(n, 2)`` key batch: ``(keys, subs)``."""
    pair = jax.vmap(jax.random.split)(keys)
    return pair[:, 0], pair[:, 1]


def select(mask: jax.Array, a, b):
    """Rows of the trees ``a`` where ``mask`` (shape ``(n,)``) is true, else of ``b``."""

    def pick(x, y):
        return jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y)

    return jax.tree.map(pick, a, b)


@functools.partial(jax.jit, static_argnums=0)
def _reset_one(env: HistoEnv, key, params):
    return env.reset(key, params)


@functools.partial(jax.jit, static_argnums=0)
def _step_one(env: HistoEnv, key, state, action, params):
    return env.step(key, state, action, params)


@functools.partial(jax.jit, static_argnums=0)
def _reset_batch(env: HistoEnv, keys, mask, old_obs, old_state, params):
    """Reset the sub-environments of ``mask`` (all when there is no old state): ``(obs, state, keys)``."""
    new_keys, subs = split_keys(keys)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(subs, params)
    if old_state is None:
        return obs, state, new_keys
    return select(mask, obs, old_obs), select(mask, state, old_state), select(mask, new_keys, keys)


@functools.partial(jax.jit, static_argnums=0)
def _step_batch_next(env: HistoEnv, keys, state, action, autoreset, params):
    """One ``NEXT_STEP`` step: sub-environments in ``autoreset`` reset, the others step; ``info``
    entries of the resetting ones are zero. ``(obs, state, reward, term, trunc, info, keys)``."""
    keys, subs = split_keys(keys)
    obs, new, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(subs, state, action, params)
    obs_re, state_re = jax.vmap(env.reset, in_axes=(0, None))(subs, params)
    stepped = jnp.logical_not(autoreset)
    info = {k: select(stepped, v, jnp.zeros_like(v)) for k, v in without_final_observation(info).items()}
    return (
        select(autoreset, obs_re, obs),
        select(autoreset, state_re, new),
        jnp.where(stepped, reward, 0.0),
        term & stepped,
        trunc & stepped,
        info,
        keys,
    )


class GymnasiumEnv(gymnasium.Env):
    """One histojax environment as a ``gymnasium.Env`` (numpy observations, Python scalars)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, env: HistoEnv, params=None, render_mode: str | None = None):
        self.env = _without_autoreset(env)
        self.params = env.default_params if params is None else params
        from histojax.registry import check_params

        check_params(env, self.params, where="GymnasiumEnv: params")
        self.observation_space, self.action_space = single_spaces(env, self.params)
        self.render_mode = render_mode
        self._static = settings_only(self.env)
        self._key = None
        self._state = None

    def reset(self, *, seed: int | None = None, options=None):
        """Start an episode; ``seed`` fixes the whole following trajectory."""
        super().reset(seed=seed)
        if seed is not None or self._key is None:
            self._key = seed_key(self.np_random.integers(0, 2**31 - 1) if seed is None else seed)
        self._key, key = jax.random.split(self._key)
        obs, self._state = _reset_one(self._static, key, self.params)
        return numpy_copy(obs), {}

    def step(self, action):
        """``(obs, reward, terminated, truncated, info)`` with numpy / Python values."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._key, key = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, info = _step_one(
            self._static, key, self._state, action, self.params
        )
        info = {k: v.item() if np.ndim(v) == 0 else v for k, v in numpy_copy(without_final_observation(info)).items()}
        return numpy_copy(obs), float(reward), bool(terminated), bool(truncated), info

    def render(self):
        """RGB uint8 picture of the slide with the current view (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self.env.render(self._state, self.params)


class GymnasiumVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` histojax environments stepped together by one jitted ``vmap`` (conventions in
    the module doc)."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": gymnasium.vector.AutoresetMode.NEXT_STEP}

    def __init__(self, env: HistoEnv, num_envs: int, params=None, render_mode: str | None = None):
        self.env = _without_autoreset(env)
        self.params = env.default_params if params is None else params
        from histojax.registry import check_params

        check_params(env, self.params, where="GymnasiumVectorEnv: params")
        self.num_envs = int(num_envs)
        self.single_observation_space, self.single_action_space = single_spaces(env, self.params)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.render_mode = render_mode
        self._keys = None  # (n, 2) device keys, one per sub-environment
        self._state = None  # batched EnvState on the device
        self._obs = None  # batched observation on the device (kept for reset_mask)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._static = settings_only(self.env)

    def _seed_keys(self, seed, mask: np.ndarray) -> jax.Array:
        """Keys after ``reset(seed=...)``: ``int`` s → ``s + i`` for sub-env ``i``; a list → one seed
        (or ``None``) each; ``None`` keeps the running keys (drawn from ``np_random`` at first)."""
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(int(seed))
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(
                    f"reset(seed=[...]) needs one seed per sub-environment ({self.num_envs}), got {len(seeds)}"
                )
        return seeded_keys(self._keys, seeds, mask, self.np_random)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        """Reset all sub-environments, or those of ``options["reset_mask"]`` (bool ``(n,)`` numpy
        array; the others keep their state and observation): ``(obs batch, {})``."""
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if mask is None or self._state is None:
            mask = np.ones(self.num_envs, dtype=bool)
        elif not (isinstance(mask, np.ndarray) and mask.dtype == np.bool_ and mask.shape == (self.num_envs,)):
            raise ValueError(
                f"options['reset_mask'] must be a numpy bool array of shape ({self.num_envs},), "
                f"got {type(mask).__name__} {getattr(mask, 'dtype', '')} {getattr(mask, 'shape', '')}"
            )
        elif not mask.any():
            raise ValueError("options['reset_mask'] resets no sub-environment (all False)")
        keys = self._seed_keys(seed, mask)
        self._obs, self._state, self._keys = _reset_batch(
            self._static, keys, jnp.asarray(mask), self._obs, self._state, self.params
        )
        self._autoreset = self._autoreset & ~mask
        return numpy_copy(self._obs), {}

    def step(self, actions):
        """``(obs, rewards, terminations, truncations, info)`` numpy batches (rewards float64),
        ``NEXT_STEP`` autoreset; ``info`` keys masked by ``info["_" + key]``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        autoreset = self._autoreset
        self._obs, self._state, reward, term, trunc, info, self._keys = _step_batch_next(
            self._static, self._keys, self._state, jnp.asarray(actions), jnp.asarray(autoreset), self.params
        )
        term, trunc = np.array(term), np.array(trunc)
        self._autoreset = term | trunc
        stepped = ~autoreset
        infos = {}
        if stepped.any():  # as SyncVectorEnv: a key only when some sub-environment gave it
            for k, v in numpy_copy(info).items():
                infos[k], infos["_" + k] = v, stepped.copy()
        return numpy_copy(self._obs), np.array(reward, dtype=np.float64), term, trunc, infos

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


def make_gymnasium_vector_env(
    env_id: str, num_envs: int = 1, slide=None, render_mode: str | None = None, **overrides
) -> GymnasiumVectorEnv:
    """``histojax.make(env_id, slide, **overrides)`` as a :class:`GymnasiumVectorEnv` of ``num_envs``
    (what ``gymnasium.make_vec("histojax/<id>", num_envs)`` calls)."""
    from histojax.registry import make

    env, params = make(env_id, slide=slide, **overrides)
    return GymnasiumVectorEnv(env, num_envs, params, render_mode=render_mode)


def register_gymnasium_envs() -> None:
    """Register every histojax id with Gymnasium as ``"histojax/<id>"``, so
    ``gymnasium.make("histojax/HistoJAX-Easy-v0", slide=..., **overrides)`` and
    ``gymnasium.make_vec("histojax/HistoJAX-Easy-v0", num_envs=64, **overrides)`` work."""
    from histojax.registry import registered_envs

    for env_id in registered_envs():
        name = f"histojax/{env_id}"
        if name not in gymnasium.registry:
            gymnasium.register(
                name,
                entry_point="histojax.adapters.gymnasium:make_gymnasium_env",
                vector_entry_point="histojax.adapters.gymnasium:make_gymnasium_vector_env",
                kwargs={"env_id": env_id},
                disable_env_checker=True,
            )


__all__ = [
    "GymnasiumEnv",
    "GymnasiumVectorEnv",
    "make_gymnasium_env",
    "make_gymnasium_vector_env",
    "numpy_copy",
    "register_gymnasium_envs",
    "seed_key",
    "seeded_keys",
    "select",
    "settings_only",
    "single_spaces",
    "split_keys",
    "without_final_observation",
]

register_gymnasium_envs()
