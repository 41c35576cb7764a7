"""Temporary: the metrics live in :mod:`data_tools.metrics` (the lowest floor, so ``data_tools`` can use them).
This re-export stays only until ``baselines/reading/learned_head_fit.py`` and ``tests/test_learned_head.py``
(being written) import ``data_tools.metrics``; then it is removed."""
from data_tools.metrics import accuracy, roc_auc

__all__ = ["accuracy", "roc_auc"]
