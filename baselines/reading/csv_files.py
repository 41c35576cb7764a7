"""The CSV files of the reading baselines: the readers' and lesion tables (columns as the rows give them) and the
budget curve (its fixed columns, ``fold`` first with ``--all-folds``), floats to 4 decimals."""

from __future__ import annotations

import csv
from pathlib import Path

from baselines import outputs

CURVE_COLUMNS = [
    "method",
    "budget",
    "fraction_read",
    "auc",
    "accuracy",
    "slides",
    "auc_std",
    "accuracy_std",
    "seeds",
    "fields_of_view",
    "auc_low",
    "auc_high",
    "tumour_slides",
]
"""The budget curve's columns (:func:`write_curve_csv`): ``auc_low`` / ``auc_high`` the AUC's 95 % interval over the
slides, ``tumour_slides`` how many of ``slides`` are tumour slides; ``fields_of_view`` only when a row has one."""


def write_csv(rows: list[dict], path, columns: list[str] | None = None, blank_nan: bool = False) -> Path:
    """Rows as CSV (floats to 4 decimals), written atomically: ``columns`` (default: the first row's keys, or
    ``reader`` without rows; a row's missing column is empty); ``blank_nan``: an undefined (NaN) figure is an
    empty cell instead of ``nan``."""
    path = Path(path)
    with outputs.open_text(path) as f:
        w = csv.DictWriter(f, fieldnames=columns or (list(rows[0]) if rows else ["reader"]), restval="")
        w.writeheader()
        for r in rows:
            w.writerow(
                {
                    k: (
                        ""
                        if blank_nan and isinstance(v, float) and v != v
                        else f"{v:.4f}"
                        if isinstance(v, float)
                        else v
                    )
                    for k, v in r.items()
                }
            )
    return path


def write_curve_csv(rows: list[dict], path) -> Path:
    """The budget curve's CSV: one line per method × budget (:data:`CURVE_COLUMNS`; with ``--all-folds`` a ``fold``
    column first: the fold, or ``mean``), NaN (no fields of view for a scripted reader) empty; the fields-of-view
    column only when some row has one (a trained policy's), never a column that is always empty; a
    ``scored_on_seen_slides`` column when some row was scored on slides its head saw (``--allow-fitting-slides``)."""
    folds = ["fold"] if any("fold" in r for r in rows) else []
    columns = [c for c in CURVE_COLUMNS if c != "fields_of_view" or any(_defined(r.get(c)) for r in rows)]
    if any(r.get("scored_on_seen_slides") for r in rows):  # --allow-fitting-slides scored slides the head saw
        columns.append("scored_on_seen_slides")
    return write_csv(
        [{k: v for k, v in r.items() if k in columns or k == "fold"} for r in rows],
        path,
        folds + columns,
        blank_nan=True,
    )


def _defined(value) -> bool:
    """Whether a CSV figure is there: not missing, not NaN."""
    return value is not None and not (isinstance(value, float) and value != value)
