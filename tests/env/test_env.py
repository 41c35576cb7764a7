"""The environment contract on the embedded slide: spaces, observations, dynamics, jit/vmap/scan."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax
from histojax import DOWN, LEFT, RIGHT, STAY, UP, ZOOM_IN, ZOOM_OUT

KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def easy(sample_envs):
    return sample_envs["HistoJAX-Easy-v0"]


@pytest.mark.parametrize("env_id,n", [("HistoJAX-Easy-v0", 3), ("HistoJAX-Medium-v0", 5), ("HistoJAX-Hard-v0", 7)])
def test_scenarios_span_the_same_range(sample_envs, env_id, n):
    env, params = sample_envs[env_id]
    assert env.n_levels == n
    d = np.asarray(params.slide.downsample)
    assert d[0] == pytest.approx(16.0) and d[-1] == pytest.approx(1.0)
    ratios = d[:-1] / d[1:]
    np.testing.assert_allclose(ratios, 16.0 ** (1 / (n - 1)), rtol=1e-5)  # equal zoom steps
    assert int(params.slide.level_width[-1]) == 2220 and int(params.slide.level_height[-1]) == 2967


def test_spaces_use_gymnax_names(easy):
    env, params = easy
    space = env.action_space(params)
    assert space.n == 7 and space.shape == () and space.dtype == jnp.int32
    assert bool(space.contains(6)) and not bool(space.contains(7)) and not bool(space.contains(-1))
    a = space.sample(KEY)
    assert bool(space.contains(a))
    obs_space = env.observation_space(params)
    assert obs_space.shape == (128, 128, 3) and obs_space.dtype == jnp.uint8
    obs, _ = env.reset(KEY, params)
    assert bool(obs_space.contains(obs))
    assert env.default_params is params
    assert params.max_steps_in_episode == 100


def test_observation_is_the_view_of_the_level(easy):
    env, params = easy
    bundle = env.bundles[0]
    state = histojax.EnvState(
        z=jnp.int32(1), x=jnp.int32(37), y=jnp.int32(211), t=jnp.int32(0), slide_index=jnp.int32(0)
    )
    obs = env.get_obs(state, params)
    np.testing.assert_array_equal(np.asarray(obs), bundle.pixels[1][211 : 211 + 128, 37 : 37 + 128])


def test_observation_modes(sample_envs):
    env, params = histojax.make("HistoJAX-Medium-v0", obs_mode="pixels_float", with_position=True)
    obs, state = env.reset(KEY, params)
    assert set(obs) == {"pixels", "position"}
    assert obs["pixels"].dtype == jnp.float32 and float(obs["pixels"].max()) <= 1.0
    assert obs["position"].shape == (3,) and bool(jnp.all((obs["position"] >= 0) & (obs["position"] <= 1)))
    assert bool(env.observation_space(params).contains(obs))
    uint_env, uint_params = sample_envs["HistoJAX-Medium-v0"]
    uint_obs = uint_env.get_obs(state, uint_params)
    np.testing.assert_allclose(np.asarray(obs["pixels"]), np.asarray(uint_obs) / 255.0, atol=1e-6)


def test_discrete_moves_and_zoom(easy):
    env, params = easy
    step = jax.jit(histojax.HistoEnv(**{**env.__dict__, "auto_reset": False}).step)
    s = histojax.EnvState(z=jnp.int32(1), x=jnp.int32(200), y=jnp.int32(300), t=jnp.int32(0), slide_index=jnp.int32(0))
    expected = {
        UP: (1, 200, 172),
        DOWN: (1, 200, 428),
        LEFT: (1, 72, 300),
        RIGHT: (1, 328, 300),
        STAY: (1, 200, 300),
        ZOOM_IN: (2, 4 * (200 + 64) - 64, 4 * (300 + 64) - 64),
        ZOOM_OUT: (0, round((200 + 64) / 4 - 64), round((300 + 64) / 4 - 64)),
    }
    for action, (z, x, y) in expected.items():
        _, s2, *_ = step(KEY, s, action, params)
        got = (int(s2.z), int(s2.x), int(s2.y))
        clamp = (z, min(x, int(params.slide.level_width[z]) - 128), min(y, int(params.slide.level_height[z]) - 128))
        assert got == clamp, histojax.ACTION_NAMES[action]


def test_out_of_range_actions_are_stay(easy):
    env, params = easy
    _, s = env.reset(KEY, params)
    for bad in (-1, 7, 1000):
        _, s2, r, *_ = env.step(KEY, s, bad, params)
        _, s3, r3, *_ = env.step(KEY, s, STAY, params)
        assert (int(s2.x), int(s2.y), int(s2.z)) == (int(s3.x), int(s3.y), int(s3.z)) and float(r) == float(r3)


def test_continuous_actions():
    env, params = histojax.make("HistoJAX-Easy-v0", action_mode="continuous", auto_reset=False)
    space = env.action_space(params)
    assert space.shape == (3,)
    s = histojax.EnvState(
        z=jnp.int32(2), x=jnp.int32(1000), y=jnp.int32(1000), t=jnp.int32(0), slide_index=jnp.int32(0)
    )
    _, s2, *_ = env.step(KEY, s, jnp.array([0.5, -1.0, 0.0]), params)
    assert (int(s2.z), int(s2.x), int(s2.y)) == (2, 1064, 872)
    _, s3, *_ = env.step(KEY, s, jnp.array([0.0, 0.0, 0.9]), params)  # already finest: stays
    assert int(s3.z) == 2
    _, s4, *_ = env.step(KEY, s, jnp.array([0.0, 0.0, -0.9]), params)
    assert int(s4.z) == 1
    _, s5, r5, *_ = env.step(KEY, s, jnp.array([jnp.nan, jnp.inf, jnp.nan]), params)  # NaN → 0, inf → 1
    assert (int(s5.x), int(s5.y), int(s5.z)) == (1000, 1128, 2) and bool(jnp.isfinite(r5))


def test_fixed_top_left_start():
    env, params = histojax.make("HistoJAX-Easy-v0", random_start=False)
    _, s = env.reset(KEY, params)
    assert (int(s.z), int(s.x), int(s.y), int(s.t)) == (0, 0, 0, 0)


def test_random_starts_are_on_tissue(easy):
    env, params = easy
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(KEY, 256), params)
    logits = np.asarray(params.slide.start_logits)
    assert np.all(np.isfinite(logits[np.asarray(states.y), np.asarray(states.x)]))
    assert np.all(np.asarray(states.z) == 0) and len(set(zip(np.asarray(states.x), np.asarray(states.y)))) > 10


def test_success_terminates_at_finest_level_only(easy):
    env, params = easy
    bundle = env.bundles[0]
    # a finest-level view fully inside the target, and the same place one level coarser
    finest = bundle.tumour[-1]
    ys, xs = np.nonzero(finest[:-128, :-128])
    inside = [(x, y) for x, y in zip(xs[::97], ys[::97]) if finest[y : y + 128, x : x + 128].mean() == 1.0]
    x, y = inside[0]
    s = histojax.EnvState(z=jnp.int32(2), x=jnp.int32(x), y=jnp.int32(y), t=jnp.int32(0), slide_index=jnp.int32(0))
    _, _, r, term, trunc, info = env.step(KEY, s, STAY, params)
    assert bool(term) and not bool(trunc) and bool(info["success"])
    assert float(info["tumour_fraction"]) == 1.0
    assert float(r) == pytest.approx(-params.step_cost + params.success_bonus)
    s1 = s.replace(z=jnp.int32(1), x=jnp.int32(x // 4), y=jnp.int32(y // 4))
    _, _, _, term1, _, info1 = env.step(KEY, s1, STAY, params)
    assert not bool(term1) and float(info1["tumour_fraction"]) > 0


def test_histogym_preset_never_terminates_and_pays_at_finest():
    env, params = histojax.make("HistoJAX-Easy-v0", reward="histogym", auto_reset=False, max_steps_in_episode=5)
    bundle = env.bundles[0]
    finest = bundle.tumour[-1]
    ys, xs = np.nonzero(finest)
    x, y = int(xs[len(xs) // 2]) - 64, int(ys[len(ys) // 2]) - 64
    s = histojax.EnvState(z=jnp.int32(2), x=jnp.int32(x), y=jnp.int32(y), t=jnp.int32(0), slide_index=jnp.int32(0))
    _, _, r, term, trunc, info = env.step(KEY, s, STAY, params)
    frac = finest[y : y + 128, x : x + 128].mean()
    assert not bool(term) and float(r) == pytest.approx(1000 * frac - 0.01, rel=1e-5)
    _, _, r0, *_ = env.step(KEY, s.replace(z=jnp.int32(1), x=jnp.int32(x // 4), y=jnp.int32(y // 4)), STAY, params)
    assert float(r0) == pytest.approx(-0.01)


def test_scan_over_vmap_and_no_retracing(easy):
    env, params = easy

    @jax.jit
    @chex.assert_max_traces(n=1)
    def rollout(key, params):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, 8), params)

        def body(state, key):
            action = jax.random.randint(key, (8,), 0, 7)
            _, state, reward, term, trunc, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, 8), state, action, params
            )
            return state, reward

        return jax.lax.scan(body, state, jax.random.split(key, 50))

    for i in range(3):  # new keys and new parameter values: no new trace
        p = params.replace(max_steps_in_episode=10 + i, step_cost=0.01 * (i + 1))
        _, rewards = rollout(jax.random.PRNGKey(i), p)
        assert rewards.shape == (50, 8) and bool(jnp.all(jnp.isfinite(rewards)))


def test_slide_arrays_are_not_closed_over(easy):
    env, params = easy
    jaxpr = jax.make_jaxpr(env.step)(KEY, env.reset(KEY, params)[1], 0, params)
    biggest_const = max((np.size(c) for c in jaxpr.consts), default=0)
    assert biggest_const < 1000  # the pyramid arrives as an argument, not a constant


def test_make_rejects_unknown_settings_and_ids():
    with pytest.raises(ValueError, match="unknown environment id"):
        histojax.make("HistoJAX-Impossible-v0")
    with pytest.raises(TypeError, match="unknown settings"):
        histojax.make("HistoJAX-Easy-v0", colour="blue")
    with pytest.raises(ValueError, match="reward must be"):
        histojax.make("HistoJAX-Easy-v0", reward="money")


def test_render_shows_the_view(easy):
    env, params = easy
    _, s = env.reset(KEY, params)
    picture = env.render(s, params)
    assert picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3
    assert max(picture.shape[:2]) <= 640 and picture.std() > 10


def test_memory_budget_is_enforced_with_a_clear_error():
    from data_tools.errors import BundleError

    with pytest.raises(BundleError, match=r"need [\d,]+ bytes on the device.*max_device_bytes=1,000,000"):
        histojax.make("HistoJAX-Hard-v0", max_device_bytes=1_000_000)
    env, params = histojax.make("HistoJAX-Easy-v0", max_device_bytes=200_000_000)
    assert env.n_levels == 3


def test_debug_checks_pass_on_valid_steps_and_catch_a_broken_state(easy):
    from histojax.debug import checked

    env, params = easy
    reset, step = checked(env)
    err, (obs, state) = reset(KEY, params)
    err.throw()
    for a in [4, 4, 0, 3, 5, 6, 9]:
        err, (obs, state, *_rest) = step(KEY, state, a, params)
        err.throw()
    broken = state.replace(x=jnp.int32(10_000))
    err, _ = step(KEY, broken.replace(z=jnp.int32(7)), 6, params)
    with pytest.raises(Exception, match="outside"):
        err.throw()


def test_final_observation_off_gives_the_same_trajectory(easy):
    import dataclasses

    env, params = easy
    params = params.replace(max_steps_in_episode=5)  # several auto-resets in 12 steps
    lean = dataclasses.replace(env, final_observation=False)
    _, s_full = env.reset(KEY, params)
    s_lean = s_full
    for i in range(12):
        k = jax.random.fold_in(KEY, i)
        o_full, s_full, r_full, te, tr, info_full = env.step(k, s_full, i % 7, params)
        o_lean, s_lean, r_lean, te2, tr2, info_lean = lean.step(k, s_lean, i % 7, params)
        np.testing.assert_array_equal(np.asarray(o_full), np.asarray(o_lean))
        assert [int(a) for a in jax.tree.leaves(s_full)] == [int(a) for a in jax.tree.leaves(s_lean)]
        assert float(r_full) == float(r_lean) and (bool(te), bool(tr)) == (bool(te2), bool(tr2))
        # the lean env keeps gymnax's key (its wrappers read it) but as an empty array, never a wrong view
        assert info_full["final_observation"].shape == (128, 128, 3)
        assert info_lean["final_observation"].shape == (0,)
        assert set(info_full) == set(info_lean)
