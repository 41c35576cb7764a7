"""The reading budgets of the readers and the budget curve (a leaf module: nothing here imports back up)."""
from __future__ import annotations

BUDGETS = (0.05, 0.1, 0.2, 0.5)
"""Fractions of a slide's finest-level tissue views a reader may read (5, 10, 20, 50 %): the default budgets of
``python -m baselines.reading.readers`` and ``python -m baselines.reading.budget_curve``."""
