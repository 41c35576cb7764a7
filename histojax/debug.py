"""Debug checks behind a flag: ``checkify``-wrapped ``reset`` / ``step`` that verify the
environment's invariants at run time (off by default: the plain functions have no checks).

    reset, step = histojax.debug.checked(env)          # jitted, checkified
    err, (obs, state, reward, terminated, truncated, info) = step(key, state, action, params)
    err.throw()                                          # raises on the first broken invariant

Checked: the ``EnvParams`` (the rules of :func:`histojax.registry.validate_params`: ``stride``,
``max_steps_in_episode``, ``success_threshold``, finite reward settings, ``start_level``), and (on the input and the output state): the view lies inside its level, ``z`` is a valid level, ``t`` is non-negative, the
reward is finite and inside the preset's documented range, float observations are finite.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.experimental import checkify

from histojax.core.modes.base import Navigation
from histojax.core.rewards import classification_bounds, reward_bounds


def _check_state(env, state, params):
    s, t = params.slide.select(state.slide_index), env.tile_size
    checkify.check((state.z >= 0) & (state.z < env.n_levels), "level z={z} outside [0, n_levels)", z=state.z)
    z = jnp.clip(state.z, 0, env.n_levels - 1)
    checkify.check((state.x >= 0) & (state.x + t <= s.level_width[z]), "view x={x} leaves level {z}", x=state.x, z=z)
    checkify.check((state.y >= 0) & (state.y + t <= s.level_height[z]), "view y={y} leaves level {z}", y=state.y, z=z)
    checkify.check(state.t >= 0, "negative step count t={t}", t=state.t)


def _check_params(env, params):
    """The rules of :func:`histojax.registry.validate_params` on traced ``EnvParams``: a value changed
    after ``make`` that would wrap, swap or freeze the moves or make rewards NaN is reported by name."""
    t = env.tile_size
    stride = jnp.asarray(params.stride, jnp.float32)
    checkify.check(
        jnp.isfinite(stride) & (stride * t >= 1) & (stride * t <= 2.0**30),
        f"stride={{s}} view widths: need 1 <= stride × tile_size ({t} px) <= 2**30 px",
        s=stride,
    )
    steps = jnp.asarray(params.max_steps_in_episode)
    whole = (steps == jnp.round(steps)) if jnp.issubdtype(steps.dtype, jnp.floating) else True
    checkify.check(
        whole & (steps >= 1) & (steps <= 2**31 - 2),
        "max_steps_in_episode={m} must be a whole number of steps in [1, 2**31 - 2]",
        m=steps,
    )
    threshold = jnp.asarray(params.success_threshold, jnp.float32)
    checkify.check(
        (threshold > 0) & (threshold <= 1), "success_threshold={v} must be a tumour fraction in (0, 1]", v=threshold
    )
    for field in ("step_cost", "success_bonus", "histogym_scale", "dense_weight", "diagnosis_reward"):
        value = jnp.asarray(getattr(params, field), jnp.float32)
        checkify.check(jnp.isfinite(value), f"{field}={{v}} must be finite", v=value)
    level = jnp.asarray(params.start_level)
    whole = (level == jnp.round(level)) if jnp.issubdtype(level.dtype, jnp.floating) else True
    checkify.check(whole, "start_level={v} must be a whole level number (0 = coarsest, -1 = finest)", v=level)
    if not isinstance(env.action, Navigation):  # static: a reading mode would ignore it
        checkify.check(
            level == 0,
            f"start_level={{v}} is for the navigation modes; {env.action.name!r} episodes start at the coarsest level",
            v=level,
        )


def _check_obs(obs):
    for leaf in jax.tree.leaves(obs):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            checkify.check(jnp.all(jnp.isfinite(leaf)), "non-finite observation")


def checked(env):
    """Jitted, checkified ``(reset, step)`` of ``env``; each returns ``(error, outputs)``."""

    def reset(key, params):
        _check_params(env, params)
        obs, state = env.reset(key, params)
        _check_state(env, state, params)
        _check_obs(obs)
        return obs, state

    def step(key, state, action, params):
        _check_params(env, params)  # params changed after make: named before they wrap or freeze a move
        _check_state(env, state, params)  # a broken input state is a bug upstream: say so
        out = env.step(key, state, action, params)
        obs, new_state, reward, terminated, truncated, info = out
        low, high = classification_bounds(params) if env.task == "classification" else reward_bounds(env.reward, params)
        checkify.check(jnp.isfinite(reward), "non-finite reward {r}", r=reward)
        checkify.check(
            (reward >= low - 1e-4) & (reward <= high + 1e-4), "reward {r} outside the documented range", r=reward
        )
        _check_state(env, new_state, params)
        _check_obs(obs)
        return out

    errors = checkify.user_checks
    return jax.jit(checkify.checkify(reset, errors=errors)), jax.jit(checkify.checkify(step, errors=errors))
