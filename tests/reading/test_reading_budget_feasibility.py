"""A reading budget below the smallest cell of a slide reads nothing there: one line per run names those slides and
the nearest budget that reads a cell on every slide (histojax.reading.modes.glimpse.unreadable_warning), said by
``histojax evaluate`` (a glimpse env's budget), the readers and the budget curve. Host arithmetic only: no env."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from baselines.evaluate.scoring import unreadable_at_budget
from baselines.reading.reader_scores import unreadable_line
from histojax.reading.modes.glimpse import budget_views, smallest_budgets, unreadable_warning

# slide "a": two cells of 5 views (10 in all): a cell needs 50 %; slide "b": cells of 1 and 9 views: 10 % reads one;
# slide "c": 40 tissue views, its smallest cell 5 views (12.5 %); padding cells (valid False) never count
VIEWS = np.asarray([[5, 5, 0], [1, 9, 0], [5, 35, 99]], np.int32)
VALID = np.asarray([[True, True, False], [True, True, False], [True, True, False]])
TOTAL = np.asarray([10, 10, 40], np.int32)


def test_smallest_budget_is_the_smallest_cell_over_the_slide():
    np.testing.assert_allclose(smallest_budgets(VIEWS, VALID, TOTAL), [0.5, 0.1, 0.125])
    assert np.isinf(smallest_budgets([np.zeros(2, int)], [np.zeros(2, bool)], [5])[0])  # no cell: never readable


def test_one_line_names_the_slides_and_the_nearest_budget_that_reads():
    line = unreadable_warning(["a", "b", "c"], VIEWS, VALID, TOTAL, [0.05, 0.2, 0.6], where="runs/x")
    assert line.startswith(
        "runs/x: nothing can be read at read budgets 5 %, 20 % on 3, 1 of 3 slides (at 5 %: a, b, c)"
    )
    assert "the overview alone" in line and "the nearest budget that reads a cell on every slide is 50.0 %" in line
    assert "\n" not in line
    one = unreadable_warning(["a", "b", "c"], VIEWS, VALID, TOTAL, [0.1])
    assert one.startswith("nothing can be read at read budget 10 % on 2 of 3 slides (a, c)")
    assert unreadable_warning(["a", "b", "c"], VIEWS, VALID, TOTAL, [0.5, 1.0]) is None  # every slide reads a cell


def test_the_line_agrees_with_the_envs_budget_rule():
    """Was: a budget of 10 % on the small C16 set read 0 % and printed AUC 0.500 without a word. The rule the line
    uses is the env's own: the views a budget allows (budget_views) against the smallest cell."""
    tables = SimpleNamespace(total_views=np.asarray(TOTAL), read_budget=np.float32(0.1))
    allowed = [int(budget_views(tables, i)) for i in range(3)]
    readable = [a >= v[ok].min() for a, v, ok in zip(allowed, VIEWS, VALID)]
    assert readable == [False, True, False]
    line = unreadable_warning(["a", "b", "c"], VIEWS, VALID, TOTAL, [0.1])
    assert "(a, c)" in line


def test_many_slides_are_named_five_then_a_count():
    views = np.full((8, 1), 4)
    line = unreadable_warning([f"s{i}" for i in range(8)], views, views > 0, np.full(8, 10), [0.2])
    assert "(s0, s1, s2, s3, s4 and 3 more)" in line and "is 40.0 %" in line


def test_evaluate_says_it_for_a_glimpse_envs_budget_and_not_for_other_modes():
    params = SimpleNamespace(
        mode_data=SimpleNamespace(cell_views=VIEWS, valid=VALID, total_views=TOTAL, read_budget=np.float32(0.1))
    )
    assert unreadable_at_budget(params, ["a", "b", "c"]).startswith("nothing can be read at read budget 10 %")
    assert unreadable_at_budget(SimpleNamespace(mode_data=None), ["a"]) is None  # a navigator: no cells, no line


def test_the_readers_say_it_from_their_cell_tables():
    slides = [{"name": n} for n in "abc"]
    tables = [{"cell_views": v, "valid": ok, "total": int(t)} for v, ok, t in zip(VIEWS, VALID, TOTAL)]
    assert unreadable_line(slides, tables, [0.1, 0.5]).startswith("nothing can be read at read budget 10 % on 2 of 3")
