"""Reward presets. ``f`` is the tumour fraction of the view in ``[0, 1]`` (from the rasterised
mask); success means ``f >= success_threshold`` at the finest level. Constants live in ``EnvParams``.

* ``"histogym"`` — HistoGym's rule, computed correctly: ``histogym_scale * f - step_cost`` at the
  finest level, ``-step_cost`` elsewhere; never terminates (only the step limit ends an episode).
  Range ``[-step_cost, histogym_scale - step_cost]``; defaults ``[-0.01, 999.99]``.
* ``"sparse"`` — ``success_bonus`` on success (and the episode terminates), ``-step_cost`` otherwise.
  Range ``{-step_cost, success_bonus}``; defaults ``{-0.01, 10}``.
* ``"dense"`` — ``-step_cost + dense_weight * (Φ(s') - Φ(s)) + success_bonus * success`` with the
  potential ``Φ = f * (z + 1) / n_levels`` (potential-based shaping: more tumour and finer is
  better); terminates on success. Range ``[-step_cost - dense_weight,
  -step_cost + dense_weight + success_bonus]``; defaults ``[-1.01, 10.99]``.
"""

from __future__ import annotations

import jax.numpy as jnp

PRESETS = ("histogym", "sparse", "dense")


def potential(fraction, z, n_levels: int):
    """Shaping potential ``Φ = f * (z + 1) / n_levels`` in ``[0, 1]``."""
    return fraction * (z + 1).astype(jnp.float32) / n_levels


def reward(preset: str, params, fraction, z, prev_fraction, prev_z, success, n_levels: int):
    """The reward of a transition under ``preset`` (a Python string: chosen at trace time)."""
    at_finest = z == n_levels - 1
    if preset == "histogym":
        return jnp.where(at_finest, params.histogym_scale * fraction, 0.0) - params.step_cost
    if preset == "sparse":
        return jnp.where(success, params.success_bonus, -params.step_cost)
    if preset == "dense":
        shaping = potential(fraction, z, n_levels) - potential(prev_fraction, prev_z, n_levels)
        return -params.step_cost + params.dense_weight * shaping + jnp.where(success, params.success_bonus, 0.0)
    raise ValueError(f"unknown reward preset {preset!r}; choose one of {PRESETS}")


def reward_bounds(preset: str, params):
    """Documented ``(min, max)`` of the reward under ``preset`` (traceable: works inside jit)."""
    c, b = params.step_cost, params.success_bonus
    if preset == "histogym":
        return -c, params.histogym_scale - c
    if preset == "sparse":
        return jnp.minimum(-c, b), jnp.maximum(-c, b)
    w = params.dense_weight
    return -c - w, -c + w + b


def reward_range(preset: str, params) -> tuple[float, float]:
    """Documented ``(min, max)`` of the reward under ``preset`` for these constants, as floats."""
    low, high = reward_bounds(preset, params)
    return float(low), float(high)


def classification_reward(params, declared, correct):
    """``task="classification"``: ``-step_cost``, plus ``±diagnosis_reward`` when a diagnosis is
    declared (right / wrong). Range ``[-step_cost - d, d - step_cost]``; defaults ``[-1.01, 0.99]``."""
    d = params.diagnosis_reward
    return -params.step_cost + jnp.where(declared, jnp.where(correct, d, -d), 0.0)


def classification_bounds(params):
    """Documented ``(min, max)`` of :func:`classification_reward` (traceable)."""
    return -params.step_cost - params.diagnosis_reward, params.diagnosis_reward - params.step_cost


def classification_range(params) -> tuple[float, float]:
    """:func:`classification_bounds` as floats."""
    low, high = classification_bounds(params)
    return float(low), float(high)


def terminates_on_success(preset: str) -> bool:
    """Whether reaching the target ends the episode (all presets but ``"histogym"``)."""
    return preset != "histogym"
