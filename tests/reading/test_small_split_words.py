"""The small-split warning where a split is written: ``histojax dataset`` says, in one line each, when its test split
or its smallest fold holds too few slides of a class to rank heads or readers (data_tools.metrics'
``SMALL_SPLIT_PER_CLASS``), and nothing for a split large enough."""

from __future__ import annotations

from data_tools.datasets.cli import small_split_lines
from data_tools.metrics import SMALL_SPLIT_PER_CLASS


def _dataset(n_test_tumour: int, n_test_normal: int, folds=None):
    labels, test = {}, []
    for i in range(n_test_tumour + n_test_normal):
        name = f"s{i:03d}"
        labels[name] = int(i < n_test_tumour)
        test.append(f"bundles/{name}")
    ds = {"train": [], "test": test, "labels": labels}
    if folds:
        lists, k = [], 0
        for tumour, normal in folds:
            lst = []
            for j in range(tumour + normal):
                name = f"f{k:03d}"
                k += 1
                labels[name] = int(j < tumour)
                lst.append(f"bundles/{name}")
            lists.append(lst)
        ds["folds"] = {"k": len(folds), "lists": lists}
    return ds


def test_a_six_slide_test_split_is_one_warning_naming_its_counts():
    ds = _dataset(2, 4)
    (line,) = small_split_lines(ds, ds["labels"])
    assert line.startswith("warning: the test split holds 2 tumour and 4 normal slides") and "--folds" in line
    assert "\n" not in line


def test_the_smallest_fold_is_named_once_and_a_large_split_says_nothing():
    n = SMALL_SPLIT_PER_CLASS
    ds = _dataset(n, n, folds=[(4, 6), (3, 5), (4, 5)])
    (line,) = small_split_lines(ds, ds["labels"])
    assert "fold 1, the smallest of the 3 folds, holds 3 tumour and 5 normal slides" in line and "--all-folds" in line
    big = _dataset(n, 2 * n)
    assert small_split_lines(big, big["labels"]) == []
