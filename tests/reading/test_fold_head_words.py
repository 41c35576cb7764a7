"""How a fold's head and a fold's sides are named: a fold head missing from an ``--all-folds`` folder is reported as
that fold's folder (not the parent's ``config.json``), with the command that fits it."""

from __future__ import annotations

import pytest

from baselines.reading import provenance
from data_tools.errors import HistojaxDataError


def test_a_missing_fold_head_names_the_fold_folder_and_how_to_fit_it(tmp_path):
    runs = tmp_path / "heads"
    (runs / "fold0").mkdir(parents=True)
    (runs / "fold0" / "config.json").write_text("{}")
    assert provenance.head_for_fold(runs, 0) == str(runs / "fold0")
    with pytest.raises(HistojaxDataError) as err:
        provenance.head_for_fold(runs, 1)
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"{runs / 'fold1'}: missing")
    assert "learned_head_fit --all-folds" in line and "fold0" in line and "config.json: missing" not in line


def test_the_scored_side_is_named_as_what_it_holds(tmp_path):
    """A fold's held-out side is "fold I's held-out slides" / "side" (not "the test split"); the validation-set folder of
    train_readers, whose "test" list is the validation share, is named the validation share."""
    import json

    from baselines.evaluate.cli import scored_words
    from baselines.reading.pipeline import split_words

    assert scored_words({"dataset": "d", "split": "test", "fold": 0}) == "fold 0's held-out slides"
    assert scored_words({"dataset": "d", "split": "test"}) == "the test split"
    assert split_words(tmp_path, "test", 2) == "fold 2's held-out side"
    assert split_words(tmp_path, "test") == "the test split"  # no dataset.json here: named by its split
    (tmp_path / "dataset.json").write_text(
        json.dumps({"train": [], "test": [], "note_split": "test = the validation slides", "validation_split": {}})
    )
    assert split_words(tmp_path, "test") == "the validation share of the train split"
    (tmp_path / "dataset.json").write_text(
        json.dumps({"note_split": "test = the validation slides", "validation_split": {"fold": 1}})
    )
    assert split_words(tmp_path, "test") == "the validation share of fold 1's train side"


def test_a_fold_of_one_class_is_named_as_that_folds_held_out_slides():
    from baselines.reading.pipeline import one_class_problem

    assert one_class_problem("test", [1, 1], 0).startswith("fold 0's held-out side holds only tumour slides (2)")
    assert one_class_problem("train", [0], 1).startswith("split 'train' (fold 1) holds only normal")
    assert one_class_problem("test", [0, 1], 0) is None
