"""``EnvParams.start_level``: navigation episodes that start at another level than the coarsest,
centred on the coarsest start view, inside the level; the default keeps HistoGym's start."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import histojax


@pytest.fixture(scope="module")
def hard():
    env, params = histojax.make("HistoJAX-Hard-v0")  # 7 levels of the embedded sample slide
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    return env, params, reset


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), level=st.integers(-9, 9), random_start=st.booleans())
def test_start_level_starts_there_centred_on_the_coarsest_start_view(hard, seed, level, random_start):
    env, params, reset = hard
    keys = jax.random.split(jax.random.key(seed), 8)
    base = params.replace(random_start=random_start)
    _, coarse = reset(keys, base)
    _, start = reset(keys, base.replace(start_level=level))
    n, t = env.n_levels, env.tile_size
    z = min(max(level + n if level < 0 else level, 0), n - 1)
    np.testing.assert_array_equal(np.asarray(start.z), z)
    np.testing.assert_array_equal(np.asarray(start.slide_index), np.asarray(coarse.slide_index))
    np.testing.assert_array_equal(np.asarray(start.t), 0)
    ds = np.asarray(params.slide.downsample, np.float64)
    width, height = np.asarray(params.slide.level_width)[z], np.asarray(params.slide.level_height)[z]
    x, y = np.asarray(start.x), np.asarray(start.y)
    assert ((x >= 0) & (x <= width - t) & (y >= 0) & (y <= height - t)).all()  # inside the level
    if z == 0:
        np.testing.assert_array_equal(x, np.asarray(coarse.x))
        np.testing.assert_array_equal(y, np.asarray(coarse.y))
    # the centres agree in level-0 px (up to rounding), unless the view was clamped at the level's edge
    for got, c0, size in ((x, np.asarray(coarse.x), width), (y, np.asarray(coarse.y), height)):
        centre0 = (c0 + t / 2) * ds[0]
        centre = (got + t / 2) * ds[z]
        inside = (got > 0) & (got < size - t)
        assert (np.abs(centre - centre0)[inside] <= ds[z]).all()


def test_the_default_start_is_the_coarsest_level_and_unchanged(hard):
    env, params, reset = hard
    assert params.start_level == 0
    keys = jax.random.split(jax.random.key(3), 16)
    _, a = reset(keys, params)
    _, b = reset(keys, params.replace(start_level=jnp.int32(0)))
    assert (np.asarray(a.z) == 0).all()
    for f in ("x", "y", "z", "slide_index"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))


def test_a_finest_start_steps_and_auto_resets_at_the_finest_level():
    env, params = histojax.make("HistoJAX-Easy-v0", start_level=-1, max_steps_in_episode=3)
    _, state = env.reset(jax.random.key(0), params)
    assert int(state.z) == env.n_levels - 1
    step = jax.jit(env.step)
    for i in range(3):
        _, state, _, _, truncated, _ = step(jax.random.key(i + 1), state, histojax.RIGHT, params)
    assert bool(truncated) and int(state.t) == 0 and int(state.z) == env.n_levels - 1  # the new episode's start


def test_start_level_is_refused_where_it_cannot_apply():
    with pytest.raises(ValueError, match=r"start_level=-1 is for the navigation modes.*'glimpse'"):
        histojax.make("HistoJAX-Easy-v0", action_mode="glimpse", start_level=-1)
    with pytest.raises(ValueError, match=r"start_level=0.5 must be a whole level number"):
        histojax.make("HistoJAX-Easy-v0", start_level=0.5)


def test_check_params_refuses_a_start_level_a_reading_mode_would_ignore():
    from histojax.registry import check_params

    env, params = histojax.make("HistoJAX-Easy-v0", action_mode="zoom_select", read_budget=0.5)
    check_params(env, params)
    with pytest.raises(ValueError, match=r"params: start_level=-1 is for the navigation modes.*'zoom_select'"):
        check_params(env, params.replace(start_level=-1))
    nav, nav_params = histojax.make("HistoJAX-Easy-v0")
    check_params(nav, nav_params.replace(start_level=-1))
