"""The C16 results pages state their headline AUCs with the 95 % intervals experiments.results_intervals computes from
each figure and its split's class counts, and the pages' figures are the ones the script copies."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from data_tools.metrics import auc_interval
from experiments.results_intervals import HEADLINES, SPLITS, figure_mean, main, page_table

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("page", sorted(HEADLINES))
def test_each_page_carries_its_table_of_intervals(page):
    text = (ROOT / "docs" / "results" / f"{page}.md").read_text()
    rerun = f"python -m experiments.results_intervals --page {page}"
    assert page_table(page) in text, f"docs/results/{page}.md: its table differs from {rerun}'s"
    assert "How to read an interval" in text and "(../reading.md)" in text


@pytest.mark.parametrize("page", sorted(HEADLINES))
def test_every_figure_is_printed_on_its_page_as_copied(page):
    """No figure changed: each one the script holds appears on the page outside the interval table too."""
    text = (ROOT / "docs" / "results" / f"{page}.md").read_text().replace(page_table(page), "")
    for _, figure, _ in HEADLINES[page]:
        assert figure in text, f"{page}: {figure} is not on the page"


def test_a_mean_over_seeds_gets_the_interval_of_its_mean_on_the_splits_counts(capsys):
    assert figure_mean("0.793 ± 0.032") == 0.793 and SPLITS["test"] == (25, 34)
    row = next(r for r in page_table("readers").splitlines() if r.startswith("| set reader at 10 % (3 seeds)"))
    low, high = auc_interval(0.793, 25, 34)
    assert f"[{low:.3f}, {high:.3f}] (of the mean)" in row
    assert main(["0.865", "25", "34"]) == 0
    printed = capsys.readouterr().out
    assert re.fullmatch(r"AUC 0\.865 \[0\.7\d\d, 0\.9\d\d\] on 25 tumour and 34 normal slides\n", printed)
