"""The CSV files of the reading baselines: the readers' and lesion tables (columns as the rows give them) and the
budget curve (its fixed columns, ``fold`` first with ``--all-folds``), floats to 4 decimals."""
from __future__ import annotations

import csv
from pathlib import Path

from baselines import outputs

CURVE_COLUMNS = ["method", "budget", "fraction_read", "auc", "accuracy", "slides", "auc_std", "accuracy_std", "seeds",
                 "fields_of_view"]
"""The budget curve's columns (:func:`write_curve_csv`)."""


def write_csv(rows: list[dict], path, columns: list[str] | None = None, blank_nan: bool = False) -> Path:
    """Rows as CSV (floats to 4 decimals), written atomically: ``columns`` (default: the first row's keys, or
    ``reader`` without rows; a row's missing column is empty); ``blank_nan``: an undefined (NaN) figure is an
    empty cell instead of ``nan``."""
    path = Path(path)
    with outputs.open_text(path) as f:
        w = csv.DictWriter(f, fieldnames=columns or (list(rows[0]) if rows else ["reader"]), restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if blank_nan and isinstance(v, float) and v != v
                            else f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    return path


def write_curve_csv(rows: list[dict], path) -> Path:
    """The budget curve's CSV: one line per method × budget (:data:`CURVE_COLUMNS`; with ``--all-folds`` a ``fold``
    column first: the fold, or ``mean``), NaN (no fields of view for a scripted reader) empty."""
    folds = ["fold"] if any("fold" in r for r in rows) else []
    return write_csv(rows, path, folds + CURVE_COLUMNS, blank_nan=True)
