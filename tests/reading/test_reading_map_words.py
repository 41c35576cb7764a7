"""The words and boxes of the reading-map pictures: the head panel's title is wrapped (no word cut at the
figure's edge), a view box larger than the head's grid (the overview at reset) is cut at the grid's edge, and
the legend says how many of the views stood on count as read (only the finest level's)."""

from __future__ import annotations

import numpy as np

from baselines.evaluate import pictures
from histojax.render import visited_words


def test_the_head_panel_title_is_wrapped_and_whole():
    name = "learned attention-MIL, 1536-d features, 2 x 256 units (imported:20x_256px/features_conch_v15)"
    title = pictures.panel_title(name, 2)
    lines = title.splitlines()
    assert all(len(line) <= 60 for line in lines), lines
    assert " ".join(lines).endswith("cyan: the 2 views the agent stood on; green: tumour")
    assert "conch_v15)" in title


def test_the_legend_says_how_many_views_count_as_read():
    views = [((0, 0, 0), 0, 0), ((1, 4, 4), 1, 1)]  # the overview at reset and one coarse view
    words = visited_words(views, 1, 5)
    assert words.startswith("2 views stood on in 1 step (levels [0, 1]")
    assert "0 of them at the finest level (4), the only views counted as read" in words


def test_a_set_readers_legend_says_its_cells_reveal_the_finest_views_it_read():
    """Was: a glimpse reader's map said "0 of them at the finest level (4), the only views counted as read" beside a
    table that said it read 9.5 %: its cells, picked at a coarser level, reveal the finest views under them."""
    views = [((0, 0, 0), 0, 0), ((2, 4, 4), 1, 1), ((2, 8, 4), 2, 1)]  # the overview and two cells of level 2
    words = visited_words(views, 2, 5, fraction_read=0.095, reveals=True)
    assert "0 of them" not in words and "the only views counted as read" not in words
    assert "each cell picked reveals the finest views (level 4) under it, which count as read: 9.5% of the" in words
    plain = visited_words(views, 2, 5, fraction_read=0.0)  # a navigator: its finest views only, and the figure
    assert "0 of them at the finest level (4), the only views counted as read (0.0% of the tissue" in plain


def test_a_view_box_larger_than_the_grid_is_cut_at_its_edge(monkeypatch, tmp_path):
    import histojax

    env, params = histojax.make("HistoJAX-Easy-v0")
    monkeypatch.setattr(pictures, "head_scores_map", lambda *a: (np.zeros((2, 3), np.float32), 10.0))
    monkeypatch.setattr(pictures, "render_reading_map", lambda *a, **k: np.zeros((40, 60, 3), np.uint8))
    figures = []
    monkeypatch.setattr(pictures.outputs, "save_figure", lambda fig, path: figures.append(fig) or path)
    head = type("Head", (), {"name": "a head"})()
    record = {"z": np.array([0]), "x": np.array([0]), "y": np.array([0]), "length": 0}  # the whole slide at reset
    pictures.reading_with_scores(env, params, head, record, 0, 0.5, tmp_path / "r.png", "t")
    right = figures[0].axes[1]
    assert right.get_xlim() == (0.0, 30.0) and right.get_ylim() == (20.0, 0.0)
