"""The reading modes' auto-reset without clearing the whole memory (``ActionMode.auto_reset_memory``):
``zoom_select`` stamps its seen-bits and visited-map blocks with the episode, ``glimpse`` with
``step_obs`` leaves the cells-read list's stale slots in place. What a user sees must equal, bit for bit,
the plain select over a fresh memory (the base class's ``auto_reset_memory``), in vmapped rollouts that
auto-reset many times; an episode that auto-resets starts from a clean memory; vmap equals a loop.

One small synthetic slide with the cheap ``colour-stats`` feature grid, 32-px views, 3 levels.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax
from histojax.core.modes.base import ActionMode
from histojax.core.seen_views import seen_flags
from histojax.reading.modes.glimpse import Glimpse
from histojax.reading.modes.zoom_select import ZoomSelect

TILE, STEPS, ENVS, EPISODE = 32, 30, 6, 7


@dataclasses.dataclass(frozen=True)
class PlainZoom(ZoomSelect):
    """``zoom_select`` whose auto-reset selects a fresh memory over the whole memory (the reference)."""

    auto_reset_memory = ActionMode.auto_reset_memory


@dataclasses.dataclass(frozen=True)
class PlainGlimpse(Glimpse):
    """``glimpse`` whose auto-reset selects a fresh memory over the whole memory (the reference)."""

    auto_reset_memory = ActionMode.auto_reset_memory


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    from slide_helpers import tiny_feature_bundle

    return tiny_feature_bundle(tmp_path_factory.mktemp("autoreset"), seed=3, tile=TILE)


def _make(bundle, mode, **kw):
    return histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        obs_mode="features",
        action_mode=mode,
        task="classification",
        max_steps_in_episode=EPISODE,
        **kw,
    )


def _rollout(env, params, actions, key):
    """``ENVS`` vmapped auto-resetting envs: per step (obs, reward, terminated, truncated, reading info, state)."""

    def run(key, actions):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, ENVS), params)

        def body(carry, a):
            state, key = carry
            key, sub = jax.random.split(key)
            obs, state, r, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(sub, ENVS), state, a, params
            )
            return (state, key), (obs, r, term, trunc, info["fraction_read"], info["fields_of_view"], state)

        return jax.lax.scan(body, (state, key), actions)[1]

    return jax.jit(run)(key, actions)


def _actions(n, seed=0):
    return jnp.asarray(np.random.default_rng(seed).integers(0, n, (STEPS, ENVS)), jnp.int32)


def _assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.fixture(scope="module")
def zoom_runs(bundle):
    env, params = _make(bundle, "zoom_select", read_budget=0.5)
    ref_env, ref_params = _make(bundle, PlainZoom(), read_budget=0.5)
    actions = _actions(env.num_actions)
    return (
        env,
        params,
        _rollout(env, params, actions, jax.random.key(1)),
        _rollout(ref_env, ref_params, actions, jax.random.key(1)),
        actions,
    )


@pytest.fixture(scope="module")
def glimpse_runs(bundle):
    env, params = _make(bundle, Glimpse(level=1), read_budget=0.4, step_obs=True)
    ref_env, ref_params = _make(bundle, PlainGlimpse(level=1), read_budget=0.4, step_obs=True)
    actions = _actions(env.num_actions, seed=1)
    return (
        env,
        params,
        _rollout(env, params, actions, jax.random.key(2)),
        _rollout(ref_env, ref_params, actions, jax.random.key(2)),
        actions,
    )


def test_zoom_select_equals_plain_select(zoom_runs):
    env, _, fast, ref, _ = zoom_runs
    *out, state = fast
    *ref_out, ref_state = ref
    ends = np.asarray(out[2] | out[3])
    assert ends.sum() >= 2 * ENVS, "the rollout must auto-reset many times to test the stamps"
    _assert_same(out, ref_out)  # observations (visited map, view, position), rewards, dones, reading info
    m, r = state.memory, ref_state.memory
    _assert_same(
        (m.seen, m.block_read, m.views_read, m.fields, m.path_x, m.path_y),
        (r.seen, r.block_read, r.views_read, r.fields, r.path_x, r.path_y),
    )
    assert int(np.asarray(m.episode).max()) >= 2  # the stamped memory did start episodes by stamp


def test_zoom_select_auto_reset_sees_a_clean_memory(zoom_runs):
    """Right after an auto-reset the seen set is the start view alone, the visited map empty, the raw words
    still holding the ended episode's bits (nothing was cleared)."""
    env, params, fast, _, _ = zoom_runs
    obs, *_, state = fast
    term, trunc = fast[2], fast[3]
    tables = params.mode_data
    fresh = jax.jit(lambda one: env.action.init_memory(env, one.replace(memory=None), params))
    stale = 0
    for t, e in zip(*np.nonzero(np.asarray(term | trunc))):
        mem = jax.tree.map(lambda a: a[t, e], state.memory)
        start = fresh(jax.tree.map(lambda a: a[t, e], state))
        _assert_same(
            (mem.seen, mem.block_read, mem.views_read, mem.fields),
            (start.seen, start.block_read, start.views_read, start.fields),
        )
        assert int(np.unpackbits(np.asarray(mem.seen).view(np.uint8)).sum()) == 1
        assert np.asarray(obs["visited"][t, e]).sum() == 0
        stale += int(np.unpackbits(np.asarray(mem.words).view(np.uint8)).sum()) > 1
        f = env.n_levels - 1
        size = int(tables.grid_width[0, f] * tables.grid_height[0, f])
        assert not seen_flags(mem.seen, int(tables.grid_offset[0, f]), size).any()  # no finest view read yet
    assert stale > 0  # the stamps, not a clear, made the memory clean


def test_glimpse_step_obs_equals_plain_select(glimpse_runs):
    env, _, fast, ref, _ = glimpse_runs
    *out, state = fast
    *ref_out, ref_state = ref
    ends = np.asarray(out[2] | out[3])
    assert ends.sum() >= 2 * ENVS
    _assert_same(out, ref_out)  # read_cells / read_summaries show stale slots empty, as a cleared list would
    m, r = state.memory, ref_state.memory
    _assert_same(
        (m.revealed, m.views_read, m.fields, m.over_budget), (r.revealed, r.views_read, r.fields, r.over_budget)
    )
    k = np.arange(m.slots.shape[-1])
    used = k[None, None] < np.asarray(m.fields)[..., None]
    np.testing.assert_array_equal(np.asarray(m.slots)[used], np.asarray(r.slots)[used])
    assert (np.asarray(m.slots)[~used] != np.asarray(r.slots)[~used]).any()  # stale slots were left in place


def test_glimpse_auto_reset_observes_an_empty_reading(glimpse_runs):
    env, params, fast, _, _ = glimpse_runs
    obs, term, trunc = fast[0], fast[2], fast[3]
    c = int(params.mode_data.valid.shape[-1])
    for t, e in zip(*np.nonzero(np.asarray(term | trunc))):
        assert (np.asarray(obs["read_cells"][t, e]) == c).all()
        assert (np.asarray(obs["read_summaries"][t, e]) == 0).all()
        assert (np.asarray(obs["read_bits"][t, e]) == 0).all()


@pytest.mark.parametrize("runs", ["zoom_runs", "glimpse_runs"])
def test_vmap_equals_loop(runs, request):
    """Each env of the vmapped rollout equals that env stepped alone (same keys, same actions)."""
    env, params, fast, _, actions = request.getfixturevalue(runs)

    def one(key, actions, e):
        _, state = env.reset(jax.random.split(key, ENVS)[e], params)

        def body(carry, a):
            state, key = carry
            key, sub = jax.random.split(key)
            obs, state, r, term, trunc, info = env.step(jax.random.split(sub, ENVS)[e], state, a[e], params)
            return (state, key), (obs, r, term, trunc, info["fraction_read"], info["fields_of_view"])

        return jax.lax.scan(body, (state, key), actions)[1]

    key = jax.random.key(1 if runs == "zoom_runs" else 2)
    loop = jax.jit(one)  # e traced: one program for every env
    for e in (0, ENVS - 1):
        _assert_same(loop(key, actions, e), jax.tree.map(lambda a: a[:, e], fast[:-1]))
