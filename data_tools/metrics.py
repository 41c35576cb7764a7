"""Slide-level diagnosis metrics: ROC AUC and accuracy of per-slide scores in ``[0, 1]``."""
from __future__ import annotations

import numpy as np


def roc_auc(scores, labels) -> float:
    """Area under the ROC curve of ``scores`` (higher = more likely tumour) for 0/1 ``labels``: the
    probability that a random positive scores above a random negative, ties counting one half
    (Mann–Whitney U / (n⁺ n⁻)). NaN when only one class is present."""
    s = np.asarray(scores, np.float64)
    y = np.asarray(labels).astype(bool)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


def accuracy(scores, labels, threshold: float = 0.5) -> float:
    """Fraction of slides whose ``score >= threshold`` equals their 0/1 label."""
    s = np.asarray(scores, np.float64)
    return float(np.mean((s >= threshold) == np.asarray(labels).astype(bool)))
