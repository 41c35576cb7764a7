"""Every fold of a dataset built with ``--folds K``: which folds there are, which side of each is scored, and each
figure as its mean ± std over folds. The budget curve's and ``histojax evaluate``'s ``--all-folds`` run their one-fold
path (``--fold I``) for I = 0 … K − 1 and summarise it here (a leaf module: it imports no other command)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from data_tools.datasets.index import read_dataset_json
from data_tools.errors import HistojaxDataError

SUMMARY = "mean"
"""The ``fold`` cell of a summary row (the mean over folds; the std over folds in its ``*_std`` cells or row)."""


def dataset_folds(dataset, option: str = "--all-folds") -> tuple[int, str]:
    """``(K, side)`` of ``DATASET/dataset.json``: its number of folds and the split that holds fold I's held-out
    slides (``"test"`` where the folds cover every slide, ``"validation"`` where they cut the train side of a fixed
    test set, as ``make(..., fold=I)`` reads them). ``HistojaxDataError`` in one line naming the file and ``option``
    for a dataset without folds or one that cannot be read."""
    path = Path(dataset) / "dataset.json"
    try:
        spec = read_dataset_json(dataset)
    except FileNotFoundError:
        raise HistojaxDataError(
            None, f"{option}: {path}: no such file (give a dataset folder built by `histojax dataset`)"
        ) from None
    except (OSError, ValueError) as e:
        raise HistojaxDataError(None, f"{option}: {path}: cannot be read ({e})") from None
    folds = spec.get("folds") if isinstance(spec, dict) else None
    if not isinstance(folds, dict) or not isinstance(folds.get("lists"), list) or len(folds["lists"]) < 2:
        raise HistojaxDataError(
            None,
            f"{option}: {path} has no folds; build the dataset with `histojax dataset "
            "... --folds K` (or `c16 --folds K`), or drop " + option,
        )
    return len(folds["lists"]), ("test" if folds.get("pool") == "all" else "validation")


def scored_side(dataset, fold: int | None) -> str:
    """The split a command scores: ``"test"`` without a fold, else fold ``fold``'s held-out side
    (:func:`dataset_folds`)."""
    return "test" if fold is None else dataset_folds(dataset, f"--fold {fold}")[1]


def mean_std(values) -> tuple[float, float]:
    """Mean and standard deviation (numpy's, over the folds: ``ddof=0``) of the defined (finite) ``values``; both
    NaN when no fold defines the figure (e.g. an AUC on folds of one class)."""
    a = np.asarray([v for v in values if v is not None and v == v and v not in ("", "nan")], np.float64)
    return (float(a.mean()), float(a.std())) if a.size else (float("nan"), float("nan"))


def with_fold(path: str, fold: int) -> str:
    """``path`` with ``{fold}`` replaced by ``fold`` (one run folder per fold: ``runs/ppo-fold{fold}``); unchanged
    without ``{fold}`` (one run scored on every fold)."""
    return path.replace("{fold}", str(fold))
