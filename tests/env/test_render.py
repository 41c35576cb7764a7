"""Pictures: trajectory PNG (matplotlib) and GIF from a scanned rollout, colours by level, a zoomed inset for
views too small to see; learning curves."""

from __future__ import annotations

import jax
import numpy as np
from PIL import Image

from baselines.harness.curves import curves_figure, plot_curves
from histojax.render import animate, level_colour, reading_map_figure, render_trajectory, slide_name, trajectory_figure


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
    with Image.open(png) as im:
        assert im.size == (picture.shape[1], picture.shape[0]) and 600 <= im.size[0] <= 1200
    assert picture.shape[2] == 3 and 300 <= picture.shape[0] <= 1200
    fig = trajectory_figure(env, states, title="zoom in")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[0] == "tumour" and labels[-2:] == ["start", "end (after 5 steps)"]
    assert [label.split(":")[0] for label in labels[1:-2]] == [f"level {k}" for k in range(env.n_levels)]
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x (level-0 px)" and ax.get_ylabel() == "y (level-0 px)"
    assert ax.get_title() == f"zoom in\nslide {slide_name(env, 0)}"  # the slide's name on a line of its own
    # one box per view, in its level's colour, plus the thick end box; the path has 5 steps
    boxes = [p for p in ax.patches if type(p).__name__ == "Rectangle"]
    assert len(boxes) == 7
    finest = tuple(c / 255 for c in level_colour(env.n_levels - 1, env.n_levels))
    assert np.allclose(boxes[-2].get_edgecolor()[:3], finest)
    assert len(ax.collections[0].get_segments()) == 5
    # the finest views (128 px on a 2,967 px slide) are too small to see: a zoomed inset shows them
    (inset,) = ax.child_axes
    assert inset.get_title().startswith("zoomed") and inset.get_xlim()[1] - inset.get_xlim()[0] < 2967 / 3
    assert not trajectory_figure(env, states, inset=False).axes[0].child_axes
    reading = reading_map_figure(env, params, states, score=0.5).axes[0]  # the same views as a reading map
    assert len([p for p in reading.patches if type(p).__name__ == "Rectangle"]) == 6 and len(reading.child_axes) == 1
    gif = animate(env, states, path=tmp_path / "t.gif")
    with Image.open(gif) as im:
        assert im.n_frames == 6
    same = render_trajectory(env, np.asarray(states.z), np.asarray(states.x), np.asarray(states.y), title="zoom in")
    np.testing.assert_array_equal(same, picture)


def test_learning_curves(tmp_path):
    """Seeds as a band, the mean as a line, the random agent as a reference, x in env steps; NaN are gaps."""
    steps = np.arange(1, 51) * 4096
    rng = np.random.default_rng(0)
    success = np.clip(np.linspace(0, 0.9, 50) + rng.normal(0, 0.05, (3, 50)), 0, 1)
    length = np.where(success > 0.3, 40 - 20 * success, np.nan)
    panels = {"success rate": success, "mean steps to success": length}
    fig = curves_figure(steps, panels, title="PPO, 3 seeds", reference={"success rate": 0.04})
    top, bottom = fig.axes
    assert top.get_ylabel() == "success rate" and bottom.get_xlabel() == "env steps per seed"
    assert [t.get_text() for t in top.get_legend().get_texts()] == [
        "3 seeds (min–max)",
        "mean over seeds",
        "random agent (0.04)",
    ]
    assert [t.get_text() for t in bottom.get_legend().get_texts()] == ["3 seeds (min–max)", "mean over seeds"]
    np.testing.assert_allclose(top.lines[0].get_ydata(), success.mean(axis=0))
    assert top.get_xlim() == (0, steps[-1])
    png = plot_curves(tmp_path / "curve.png", steps, panels, title="PPO, 3 seeds", reference={"success rate": 0.04})
    with Image.open(png) as im:
        assert 600 <= im.size[0] <= 1200 and 400 <= im.size[1] <= 1200
