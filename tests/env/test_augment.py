"""Dihedral augmentation (``make(..., augment=True)``): the agent sees a consistently turned or
mirrored slide, and the slide-frame dynamics are those of the plain environment."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_examples import examples

import histojax
from histojax.core import actions
from histojax.core import augment as A

MOVES = (actions.UP, actions.DOWN, actions.LEFT, actions.RIGHT)


@pytest.fixture(scope="module")
def envs():
    kw = dict(with_position=True, auto_reset=False, final_observation=False)
    plain, params = histojax.make("HistoJAX-Easy-v0", **kw)
    aug, _ = histojax.make("HistoJAX-Easy-v0", augment=True, **kw)
    params = params.replace(stride=0.5)  # half-view moves, so consecutive views overlap
    return plain, aug, params, jax.jit(plain.step), jax.jit(aug.step)


def _state(z, x, y, o):
    i = lambda v: jnp.int32(v)  # noqa: E731
    return histojax.EnvState(z=i(z), x=i(x), y=i(y), t=i(0), slide_index=i(0), orientation=i(o))


def test_orient_pixels_gives_the_eight_dihedral_images():
    v = np.arange(6 * 6 * 3, dtype=np.int32).reshape(6, 6, 3)
    got = [np.asarray(A.orient_pixels(jnp.asarray(v), o)) for o in range(8)]
    ref = [np.rot90(v, k, axes=(0, 1)) for k in range(4)] + [np.rot90(v[:, ::-1], k, axes=(0, 1)) for k in range(4)]
    np.testing.assert_array_equal(got[0], v)
    assert len({g.tobytes() for g in got}) == 8
    assert {g.tobytes() for g in got} == {r.tobytes() for r in ref}


def test_move_table_is_a_permutation_that_inverts_the_view_turn():
    m = A.matrices()
    for o in range(8):
        assert sorted(A._MOVES[o]) == [0, 1, 2, 3]
        assert abs(round(np.linalg.det(m[o]))) == 1
    np.testing.assert_array_equal(A._MOVES[0], [0, 1, 2, 3])
    # zoom, stay, diagnosis and junk codes are never turned
    for code in (4, 5, 6, 7, 8, -3, 99):
        assert int(A.discrete_to_slide(code, 5)) == code


@settings(deadline=None, max_examples=examples(40, 16))
@given(o=st.integers(0, 7), a=st.sampled_from(MOVES), fx=st.floats(0.3, 0.7), fy=st.floats(0.3, 0.7))
def test_a_move_in_the_agents_frame_slides_what_it_sees(envs, o, a, fx, fy):
    """After RIGHT (in the agent's frame, stride ½ view) the right half of the old view is the left
    half of the new one, whatever the orientation; likewise for the other moves."""
    _, aug, params, _, step = envs
    slide, t, z = params.slide, aug.tile_size, aug.n_levels - 1
    x = int(fx * (int(slide.level_width[z]) - 2 * t)) + t  # interior: the move is never clamped
    y = int(fy * (int(slide.level_height[z]) - 2 * t)) + t
    s = _state(z, x, y, o)
    old = np.asarray(aug.get_obs(s, params)["pixels"])
    new_obs, s2, *_ = step(jax.random.PRNGKey(0), s, a, params)
    new = np.asarray(new_obs["pixels"])
    h = t // 2
    expect = {
        actions.RIGHT: (new[:, :h], old[:, h:]),
        actions.LEFT: (new[:, h:], old[:, :h]),
        actions.DOWN: (new[:h], old[h:]),
        actions.UP: (new[h:], old[:h]),
    }[a]
    np.testing.assert_array_equal(*expect)
    # the position seen moves the same way
    p0, p1 = np.asarray(aug.get_obs(s, params)["position"]), np.asarray(new_obs["position"])
    d = {actions.RIGHT: (1, 0), actions.LEFT: (-1, 0), actions.DOWN: (0, 1), actions.UP: (0, -1)}[a]
    assert np.sign(np.round(p1[:2] - p0[:2], 6)).tolist() == list(d)


@settings(deadline=None, max_examples=examples(30, 12))
@given(o=st.integers(0, 7), a=st.integers(0, 6), seed=st.integers(0, 2**31 - 1))
def test_augmented_step_is_the_plain_step_seen_turned(envs, o, a, seed):
    plain, aug, params, step_plain, step_aug = envs
    _, s = plain.reset(jax.random.PRNGKey(seed), params)
    s = s.replace(orientation=jnp.int32(o))
    key = jax.random.PRNGKey(seed + 1)
    obs_a, s_a, r_a, te_a, tr_a, info_a = step_aug(key, s, a, params)
    obs_p, s_p, r_p, te_p, tr_p, info_p = step_plain(
        key, s.replace(orientation=jnp.int32(0)), A.discrete_to_slide(a, o), params
    )
    assert (int(s_a.z), int(s_a.x), int(s_a.y)) == (int(s_p.z), int(s_p.x), int(s_p.y))
    assert int(s_a.orientation) == o
    assert float(r_a) == float(r_p) and bool(te_a) == bool(te_p) and bool(tr_a) == bool(tr_p)
    np.testing.assert_array_equal(obs_a["pixels"], A.orient_pixels(obs_p["pixels"], o))
    np.testing.assert_allclose(obs_a["position"], A.orient_position(obs_p["position"], o), atol=1e-6)
    assert np.all((np.asarray(obs_a["position"]) >= 0) & (np.asarray(obs_a["position"]) <= 1))


def test_continuous_moves_turn_like_discrete_ones():
    for o in range(8):
        for a, vec in ((actions.RIGHT, (1, 0)), (actions.LEFT, (-1, 0)), (actions.DOWN, (0, 1)), (actions.UP, (0, -1))):
            turned = np.asarray(A.continuous_to_slide(jnp.array([*vec, 0.3], jnp.float32), o))
            code = int(A.discrete_to_slide(a, o))
            want = {actions.RIGHT: (1, 0), actions.LEFT: (-1, 0), actions.DOWN: (0, 1), actions.UP: (0, -1)}[code]
            np.testing.assert_allclose(turned, [*want, 0.3])
    # NaN acts as 0 on its own axis only, as without augmentation
    np.testing.assert_allclose(A.continuous_to_slide(jnp.array([jnp.nan, 1.0, 0.0]), 1), [1.0, 0.0, 0.0])


def test_zoom_in_then_out_returns_to_the_same_place_in_every_orientation(envs):
    _, aug, params, _, step = envs
    for o in range(8):
        s = _state(1, 40, 60, o)
        _, s1, *_ = step(jax.random.PRNGKey(0), s, actions.ZOOM_IN, params)
        _, s2, *_ = step(jax.random.PRNGKey(0), s1, actions.ZOOM_OUT, params)
        assert (int(s2.z), int(s2.x), int(s2.y)) == (1, 40, 60)


def test_reset_draws_every_orientation_and_plain_env_only_the_identity(envs):
    plain, aug, params, _, _ = envs
    keys = jax.random.split(jax.random.PRNGKey(3), 800)
    o_aug = np.asarray(jax.vmap(lambda k: aug.reset(k, params)[1].orientation)(keys))
    o_plain = np.asarray(jax.vmap(lambda k: plain.reset(k, params)[1].orientation)(keys))
    counts = np.bincount(o_aug, minlength=8)
    assert counts.min() > 60, counts  # ~100 each
    assert (o_plain == 0).all()


def test_features_cannot_be_augmented():
    with pytest.raises(ValueError, match="augment=True"):
        histojax.HistoEnv(n_levels=3, obs_mode="features", augment=True)
