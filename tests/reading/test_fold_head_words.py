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
