"""The env a trainer trains on, made from its config (spelled as ``histojax.make`` spells it): vmapped resets,
parameter initialisation, episode statistics and the random agent's reference figures."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

import histojax
from baselines.common.config import EnvConfig, canonical_config
from histojax.adapters.jax import LogWrapper


def pin_env_shapes(config, env_params):
    """``config`` (an :class:`~baselines.common.config.EnvConfig` or its dict; the same kind back) with the env's
    slide-dependent shapes recorded in ``env_kwargs``, so that the saved run rebuilds the same observation and action
    spaces on other slides: for ``glimpse``, the padded cell grid (``glimpse_grid``, cells; otherwise it is the
    largest grid of the slides loaded, and a policy trained on one dataset would not fit another's). Unchanged for
    the other modes."""
    from histojax.reading.modes.glimpse import GlimpseTables

    tables = getattr(env_params, "mode_data", None)
    if not isinstance(tables, GlimpseTables) or tables.step_obs:  # step_obs: cell-set policies fit any grid
        return config
    typed = isinstance(config, EnvConfig)
    kw = dict((config.env_kwargs if typed else config.get("env_kwargs")) or {})
    kw.setdefault("glimpse_grid", [int(v) for v in np.asarray(tables.grid)])
    return config.replace(env_kwargs=kw) if typed else {**config, "env_kwargs": kw}


def env_config(config) -> tuple[EnvConfig, bool]:
    """``(the env settings of config, whether it splits the slides over devices)`` for a trainer config (typed, or
    its dict: its env entries are read, the others left to the trainer)."""
    if isinstance(config, EnvConfig):
        return config, bool(getattr(config, "shard_slides", False))
    env_part = {k: v for k, v in canonical_config(config).items() if k in EnvConfig.field_names()}
    return EnvConfig.from_dict(env_part), bool(config.get("shard_slides"))


def make_env(config, auto_reset: bool = True, mesh: Mesh | None = None):
    """``(env, params)`` for ``config``'s env (a trainer config, typed or its dict): ``histojax.make`` of its
    ``env_id`` with its :meth:`~baselines.common.config.EnvConfig.make_arguments` (the slide or dataset, and the
    typed :class:`~histojax.make_options.MakeOptions`). With ``shard_slides`` and a ``mesh``, the slides are split
    over its devices (:func:`histojax.sharding.make_sharded`); without a mesh they all load on one device."""
    config, shard_slides = env_config(config)
    arguments, options = config.make_arguments(auto_reset)
    if shard_slides and mesh is not None:
        from histojax.sharding import make_sharded

        return make_sharded(config.env_id, mesh, **arguments, **options.given())
    return histojax.make(config.env_id, **arguments, **options.given())


def env_vmap(fn, num_args: int, mesh: Mesh | None = None, sharded_slides: bool = False):
    """``fn(*per_env_args, env_params)`` (an env's ``reset`` with 1 arg, ``step`` with 3) over a
    batch of envs: ``jax.vmap`` with the params shared, or, for slides sharded over ``mesh``,
    each device's block of envs on its own slides (:func:`histojax.sharding.vmap_local`)."""
    if sharded_slides:
        from histojax.sharding import vmap_local

        return vmap_local(fn, mesh, num_args)
    return jax.vmap(fn, in_axes=(0,) * num_args + (None,))


def reset_envs(env, key, env_params, num_envs: int, reset_all=None):
    """The trainers' first step: ``key`` → ``(key, k_init, obs, env_state)`` with ``num_envs``
    vmapped resets (``reset_all``, default ``jax.vmap(env.reset)``, see :func:`env_vmap`) and the
    observations pooled for the network (:func:`networks.preprocess_obs`).
    ``k_init`` is the key the network's parameters are made from, so :func:`params_initialiser`
    and the trainer see the same first observations."""
    from baselines.networks import preprocess_obs

    reset_all = reset_all or env_vmap(env.reset, 1)
    key, k_init, k_reset = jax.random.split(key, 3)
    obs, env_state = reset_all(jax.random.split(k_reset, num_envs), env_params)
    return key, k_init, preprocess_obs(obs), env_state


def params_initialiser(env, network, num_envs: int, reset_all=None, inputs=None):
    """``init_params(key, env_params)``: the network's parameters for a trainer's key, made on the
    first observations of :func:`reset_envs` (``network.init(key, *inputs(obs))``; by default the
    observations alone)."""

    def init_params(key, env_params):
        _, k_init, obs, _ = reset_envs(env, key, env_params, num_envs, reset_all)
        return network.init(k_init, *(inputs(obs) if inputs is not None else (obs,)))

    return init_params


def episode_stats(info: dict) -> dict:
    """Means over the episodes that finished in a batch of steps (any shape): ``episodes``,
    ``return``, ``success`` (rate), ``length`` and ``steps_to_success`` (mean length of the
    successful ones; NaN when none)."""
    done = info["returned_episode"].astype(jnp.float32)
    succ = info["returned_episode_success"].astype(jnp.float32) * done
    n, ns = done.sum(), succ.sum()
    length = info["returned_episode_lengths"].astype(jnp.float32)
    safe = lambda a, d: jnp.where(d > 0, a / jnp.maximum(d, 1.0), jnp.nan)  # noqa: E731
    return {
        "episodes": n,
        "return": safe((info["returned_episode_returns"] * done).sum(), n),
        "success": safe(ns, n),
        "length": safe((length * done).sum(), n),
        "steps_to_success": safe((length * succ).sum(), ns),
    }


def make_random_rollout(env, num_envs: int, num_steps: int):
    """A jitted function ``(key, params) -> (info, last observations)`` that runs ``num_steps`` steps of ``num_envs``
    random-agent environments (auto-reset, episode statistics, every observation extracted) with
    ``lax.scan`` over ``vmap``."""
    env = LogWrapper(env)
    space = env.action_space()

    def rollout(key, params):
        key, key_reset = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, key):
            state, _ = carry
            key_act, key_step = jax.random.split(key)
            action = jax.vmap(space.sample)(jax.random.split(key_act, num_envs))
            obs, state, reward, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key_step, num_envs), state, action, params
            )
            keep = ("returned_episode", "returned_episode_returns", "returned_episode_success")
            # the observations go into the carry, so every view is really extracted (a random agent
            # ignores them, and XLA would otherwise skip the crop and overstate steps/s)
            return (state, obs), {k: info[k] for k in keep}

        (_, last_obs), infos = jax.lax.scan(body, (state, obs), jax.random.split(key, num_steps))
        return infos, last_obs  # returning the carried views keeps them alive

    return jax.jit(rollout)


def random_agent_reference(
    config: dict, num_envs: int = 256, num_steps: int = 400, seed: int = 0, env_and_params=None
) -> dict:
    """Episode statistics of the uniform random agent on the same env (for the curves): the
    trainer's ``env_and_params`` when given (for slides sharded over devices, those of this
    process's first device), else the env made from ``config``."""
    if env_and_params is None:
        env, params = make_env(config)
    else:
        env, params = env_and_params
        env = getattr(env, "_env", env)  # the bare env under a LogWrapper
        if config.get("shard_slides"):
            from histojax.sharding import first_local_group

            params = params.replace(slide=first_local_group(params.slide))
    info, _ = jax.device_get(make_random_rollout(env, num_envs, num_steps)(jax.random.PRNGKey(seed), params))
    info = {**info, "returned_episode_lengths": np.zeros_like(info["returned_episode_returns"])}
    stats = jax.device_get(episode_stats(info))
    return {"return": float(stats["return"]), "success": float(stats["success"])}
