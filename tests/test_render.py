"""Pictures: trajectory PNG and GIF from a scanned rollout, colours by level."""
from __future__ import annotations

import jax
import numpy as np
from PIL import Image

from histojax.render import animate, level_colour, render_trajectory


def test_trajectory_png_and_gif_from_a_scan(sample_envs, tmp_path):
    env, params = sample_envs["HistoJAX-Medium-v0"]
    key = jax.random.PRNGKey(0)
    _, state = env.reset(key, params)

    def body(state, inp):
        k, a = inp
        _, state, *_ = env.step(k, state, a, params)
        return state, state

    actions = jax.numpy.array([4, 4, 4, 4, 3, 1])  # zoom in to the finest level, then move: 6 distinct views
    _, states = jax.lax.scan(body, state, (jax.random.split(key, 6), actions))
    png = tmp_path / "t.png"
    picture = render_trajectory(env, states, path=png, title="zoom in")
    assert png.is_file() and picture.shape[2] == 3
    # the finest level's colour (red end of the scale) is drawn somewhere
    red = np.array(level_colour(env.n_levels - 1, env.n_levels))
    assert np.any(np.all(picture == red, axis=-1))
    gif = animate(env, states, path=tmp_path / "t.gif")
    with Image.open(gif) as im:
        assert im.n_frames == 6
    same = render_trajectory(env, np.asarray(states.z), np.asarray(states.x), np.asarray(states.y))
    np.testing.assert_array_equal(same[20:], picture[20:])  # below the title line
