"""``env.state_space(params)``: a Dict of the
EnvState fields with their bounds, containing every state reset and step produce."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax
from histojax.core import spaces


def _states(env, params, n_envs: int = 16, n_steps: int = 120, seed: int = 0):
    """Every state of ``n_envs`` envs over ``n_steps`` random steps, stacked (steps, envs)."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n_envs)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    space = env.action_space(params)

    def body(state, key):
        k_act, k_step = jax.random.split(key)
        actions = jax.vmap(space.sample)(jax.random.split(k_act, n_envs))
        _, state, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(k_step, n_envs), state, actions, params
        )
        return state, state

    _, states = jax.jit(lambda s: jax.lax.scan(body, s, jax.random.split(jax.random.PRNGKey(seed + 1), n_steps)))(state)
    first = jax.tree.map(lambda a: a[None], state)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), first, states)


def _all_contained(space, states) -> bool:
    flat = jax.tree.map(lambda a: a.reshape(-1), states)
    return bool(jax.vmap(space.contains)(flat).all())


# Hard (continuous moves, augmentation) and Medium (no auto-reset) in `make test`; Easy's plain discrete case,
# the path the other two extend, under `make test-all`
@pytest.mark.parametrize(
    "env_id, overrides",
    [
        pytest.param("HistoJAX-Easy-v0", {}, marks=pytest.mark.slow),
        ("HistoJAX-Hard-v0", {"action_mode": "continuous", "augment": True}),
        ("HistoJAX-Medium-v0", {"auto_reset": False, "max_steps_in_episode": 20}),
    ],
)
def test_states_of_reset_and_step_are_contained(env_id, overrides):
    env, params = histojax.make(env_id, **overrides)
    space = env.state_space(params)
    assert isinstance(space, spaces.Dict)
    assert set(space.spaces) == {"z", "x", "y", "t", "slide_index", "orientation"}
    assert space.spaces["z"].n == env.n_levels and space.spaces["orientation"].n == 8
    assert space.spaces["t"].n == int(params.max_steps_in_episode) + 1
    _, state = env.reset(jax.random.PRNGKey(0), params)
    assert bool(space.contains(state))
    # without auto-reset the caller resets at the time limit: step exactly up to it
    n_steps = int(params.max_steps_in_episode) if overrides.get("auto_reset") is False else 120
    states = _states(env, params, n_steps=n_steps)
    assert _all_contained(space, states)
    # the states reached every level and, without auto-reset, the time limit
    assert set(np.unique(states.z)) == set(range(env.n_levels))
    if overrides.get("auto_reset") is False:
        assert int(states.t.max()) == int(params.max_steps_in_episode)
    if overrides.get("augment"):
        assert len(np.unique(states.orientation)) > 1
    assert env.state_space() is not None  # default params


def test_bounds_are_tight_and_the_check_can_fail():
    env, params = histojax.make("HistoJAX-Easy-v0")
    space = env.state_space(params)
    s = params.slide
    assert space.spaces["x"].high == int(np.max(s.level_width)) - env.tile_size
    assert space.spaces["y"].high == int(np.max(s.level_height)) - env.tile_size
    _, state = env.reset(jax.random.PRNGKey(0), params)
    for bad in (
        state.replace(z=jnp.int32(env.n_levels)),
        state.replace(x=jnp.int32(-1)),
        state.replace(y=jnp.int32(space.spaces["y"].high + 1)),
        state.replace(t=jnp.int32(params.max_steps_in_episode + 1)),
        state.replace(slide_index=jnp.int32(1)),
        state.replace(orientation=jnp.int32(8)),
    ):
        assert not bool(space.contains(bad))
    assert not bool(space.contains({"z": 0}))  # a mapping with other keys
    assert not bool(space.contains(object()))


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_dataset_states(small_slides):
    env, params = histojax.make("HistoJAX-Easy-v0", slides=small_slides)
    space = env.state_space(params)
    assert space.spaces["slide_index"].n == len(small_slides)
    states = _states(env, params, n_envs=32, n_steps=40)
    assert _all_contained(space, states)
    assert len(np.unique(states.slide_index)) > 1
