"""A reader that reads nothing on some slides says so: each row (a reader at one budget) names the slides it read
nothing on and why (its first pick larger than the budget), in the printout and in JSON, even where a smaller cell of
the slide would have fit (the feasibility line, which looks at the smallest cell only, does not name those). Host
arithmetic only: no env, no head."""

from __future__ import annotations

import numpy as np

from baselines.reading import pipeline
from baselines.reading.reader_scores import nothing_lines, rows_from_results, unreadable_line

# slide "a": two cells of 5 views: nothing fits 10 %; slide "b": cells of 1 and 9 views: 10 % reads the small one,
# but a reader that picks the 9-view cell first reads nothing; slide "c": 10 cells of 1 view
TABLES = [
    {"cell_views": np.asarray([5, 5]), "valid": np.asarray([True, True]), "total": 10},
    {"cell_views": np.asarray([1, 9]), "valid": np.asarray([True, True]), "total": 10},
    {"cell_views": np.ones(10, int), "valid": np.ones(10, bool), "total": 10},
]
BIG_FIRST = [[np.asarray([0, 1]), np.asarray([1, 0]), np.arange(10)]]  # one seed: slide b's big cell first


def read_rows(readers, budgets=(0.1,)):
    return pipeline.read_all(TABLES, readers, budgets, lambda cells: {"scores": np.zeros(len(cells))})


def test_a_first_pick_larger_than_the_budget_is_named_with_its_size():
    entry = read_rows({"score reader": BIG_FIRST})[("score reader", 0.1)]
    assert entry["fractions"][0].tolist() == [0.0, 0.0, 0.1]
    assert set(entry["nothing"]) == {0, 1}
    assert entry["nothing"][1] == (
        "its first pick (9 tissue views) is larger than the budget (1 of 10 views), though its smallest cell "
        "(1 view) fits"
    )
    assert "so is every cell of it (the smallest holds 5)" in entry["nothing"][0]


def test_the_row_names_a_slide_the_feasibility_line_does_not():
    """Was: the feasibility line named only the slides whose every cell is too big; slide b, whose first pick was too
    big, read 0 % without a word."""
    feasibility = unreadable_line([{"name": n} for n in "abc"], TABLES, [0.1])
    assert "(a, c)" not in feasibility and "(a)" in feasibility  # b has a cell that fits: not named there
    entry = read_rows({"score reader": BIG_FIRST})[("score reader", 0.1)]
    named = pipeline.nothing_entries("abc", entry["fractions"], entry["nothing"])
    assert [e["slide"] for e in named] == ["a", "b"]
    assert named[1]["reason"].startswith("its first pick (9 tissue views) is larger than the budget")
    line = pipeline.nothing_line("score reader", 0.1, named)
    assert line.startswith("score reader at budget 10 % read nothing on 2 slides") and "\n" not in line
    assert "b: its first pick (9 tissue views)" in line


def test_a_reader_that_reads_something_everywhere_prints_no_line():
    entry = read_rows({"small first": [[np.asarray([0, 1]), np.asarray([0, 1]), np.arange(10)]]}, (0.5,))
    assert pipeline.nothing_entries("abc", entry[("small first", 0.5)]["fractions"], {}) == []
    assert pipeline.nothing_line("small first", 0.5, []) is None


def test_seeds_that_read_nothing_are_counted():
    orders = [BIG_FIRST[0], [np.asarray([0, 1]), np.asarray([0, 1]), np.arange(10)]]  # seed 2 reads b's small cell
    entry = read_rows({"random reader": orders})[("random reader", 0.1)]
    named = pipeline.nothing_entries("abc", entry["fractions"], entry["nothing"])
    assert [(e["slide"], e["seeds"]) for e in named] == [("a", "2 of 2"), ("b", "1 of 2")]


def test_the_readers_rows_hold_the_slides_read_nothing_on_for_readers_json():
    slides = [{"name": n, "label": y, "tumour": None, "mpp": 1.0} for n, y in zip("abc", (0, 1, 0))]
    results = {
        ("overview only", 0.0): {
            "kind": "overview",
            "scores": np.asarray([[0.0, 1.0, 0.5]]),
            "fractions": np.zeros((1, 3)),
            "tumour_read": np.zeros((1, 3), bool),
        },
        ("my reader", 0.05): {
            "kind": "learned",
            "scores": np.asarray([[0.0, 1.0, 0.5]]),
            "fractions": np.asarray([[0.04, 0.0, 0.05]]),
            "tumour_read": np.zeros((1, 3), bool),
            "nothing": {1: "its first pick (9 tissue views) is larger than the budget (0 of 10 views)"},
        },
    }
    rows = rows_from_results(results, slides)
    assert rows[0]["read_nothing"] == []  # the overview reads nothing by design: no line
    assert rows[1]["read_nothing"] == [
        {"slide": "b", "reason": "its first pick (9 tissue views) is larger than the budget (0 of 10 views)"}
    ]
    (line,) = nothing_lines(rows)
    assert line.startswith("my reader at budget 5 % read nothing on 1 slide (scored there on nothing read): b:")


def test_the_budget_curves_rows_hold_them_too():
    from baselines.reading.budget_curve import rows_from_scores

    entry = read_rows({"score reader": BIG_FIRST})[("score reader", 0.1)]
    rows = rows_from_scores(
        {("score reader", 0.1): (np.asarray([[0.1, 0.9, 0.2]]), entry["fractions"], entry["nothing"])},
        np.asarray([0, 1, 0]),
        names=list("abc"),
    )
    assert [e["slide"] for e in rows[0]["read_nothing"]] == ["a", "b"]


def test_evaluates_episodes_that_read_nothing_name_their_slides():
    """A set reader's episodes in ``histojax evaluate``: the slides some episode read nothing on, and why."""
    from types import SimpleNamespace

    from baselines.evaluate.scoring import read_nothing_episodes

    params = SimpleNamespace(
        mode_data=SimpleNamespace(
            cell_views=np.asarray([[5, 5], [1, 9], [1, 1]]),
            valid=np.ones((3, 2), bool),
            total_views=np.asarray([10, 10, 2]),
            read_budget=np.float32(0.1),
        )
    )
    ep = {"slide": np.asarray([0, 1, 2, 0, 1, 2]), "fraction_read": np.asarray([0.0, 0.0, 0.5, 0.0, 0.1, 0.5])}
    named = read_nothing_episodes(ep, params, ["Tumor_072", "Normal_001", "c"])
    assert [(e["slide"], e["episodes"]) for e in named] == [("Tumor_072", "2 of 2"), ("Normal_001", "1 of 2")]
    assert "so is every cell of it (the smallest holds 5)" in named[0]["reason"]
    assert named[1]["reason"].startswith("its first pick is larger than the budget (1 of 10 views), or it stopped")
    assert read_nothing_episodes(ep, SimpleNamespace(mode_data=None), ["a", "b", "c"]) == []  # not a set reader


def test_a_trained_readers_refused_pick_is_found_where_its_view_stands():
    """A glimpse policy's episode that read nothing: the cell its refused pick moved the view to, and its size."""
    from types import SimpleNamespace

    table = {
        "cell_views": np.asarray([[1, 9]]),
        "valid": np.ones((1, 2), bool),
        "cell_x": np.asarray([[0, 4]]),
        "cell_y": np.zeros((1, 2), int),
        "total": 10,
    }
    refused = SimpleNamespace(memory=SimpleNamespace(over_budget=np.asarray([True])), x=np.asarray([4]), y=[0])
    said = pipeline._nothing_episode(refused, 0, 0, [table], 0.1)
    assert said == (
        "its first pick (9 tissue views) is larger than the budget (1 of 10 views), though its smallest cell (1 view) "
        "fits"
    )
    declared = SimpleNamespace(memory=SimpleNamespace(over_budget=np.asarray([False])), x=np.asarray([0]), y=[0])
    assert pipeline._nothing_episode(declared, 0, 0, [table], 0.1) == "it declared before reading a cell"
    assert pipeline._nothing_episode(declared, 0, 0, None, 0.1) == "it read no finest view"  # zoom_select
