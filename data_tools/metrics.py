"""Slide-level diagnosis metrics: ROC AUC and accuracy of per-slide scores in ``[0, 1]``.

Inputs no figure can be measured on are refused (:class:`MetricInputError`, one line naming the problem):
scores and labels of different lengths or not 1-D, NaN or infinite scores, labels other than 0/1. Slides of
one class (or none) are not refused: their AUC is *undefined*, returned as NaN, which every caller prints as
:data:`UNDEFINED` (or ``"AUC undefined (one class)"``, :func:`format_auc`) and writes as JSON ``null``."""

from __future__ import annotations

import numpy as np


class MetricInputError(ValueError):
    """Scores or labels that no metric can be measured on (lengths differ, NaN / infinite scores, labels
    other than 0/1); the message is one line naming the problem."""


def _first_bad(values: np.ndarray, bad: np.ndarray) -> str:
    """``"3 of 10 (first at index 7: nan)"`` for the ``bad`` entries of ``values``."""
    i = int(np.flatnonzero(bad)[0])
    return f"{int(bad.sum())} of {values.size} (first at index {i}: {values[i]!r})"


def checked_scores_labels(scores, labels) -> tuple[np.ndarray, np.ndarray]:
    """``scores`` as 1-D float64 and ``labels`` as 1-D bool, refused (:class:`MetricInputError`) when their
    lengths differ, either is not 1-D, a score is NaN or infinite, or a label is not 0/1."""
    try:
        s = np.asarray(scores, np.float64)
    except (TypeError, ValueError) as e:
        raise MetricInputError(f"scores are not numbers: {e}") from None
    y = np.asarray(labels)
    if s.ndim != 1 or y.ndim != 1:
        raise MetricInputError(f"scores and labels must be 1-D, not of shapes {s.shape} and {y.shape}")
    if s.shape != y.shape:
        raise MetricInputError(f"{s.size} scores but {y.size} labels: one label per score")
    bad = ~np.isfinite(s)
    if bad.any():
        raise MetricInputError(f"NaN or infinite scores: {_first_bad(s, bad)}")
    if y.dtype != bool:
        try:
            yf = y.astype(np.float64)
        except (TypeError, ValueError):
            raise MetricInputError(f"labels are not 0/1 numbers (dtype {y.dtype})") from None
        bad = (yf != 0) & (yf != 1)
        if bad.any():
            raise MetricInputError(f"labels other than 0/1: {_first_bad(y, bad)}")
        y = yf == 1
    return s, y


def roc_auc(scores, labels) -> float:
    """Area under the ROC curve of ``scores`` (higher = more likely tumour) for 0/1 ``labels``: the
    probability that a random positive scores above a random negative, ties counting one half
    (Mann–Whitney U / (n⁺ n⁻)). NaN (undefined) when only one class, or no slide, is present.

    Counted by sorting, not pairwise: O(n log n) time and O(n) memory (10⁶ scores in well under a
    second), and exactly equal to the pairwise count. Refuses (:class:`MetricInputError`) scores and
    labels of different lengths, NaN or infinite scores and labels other than 0/1
    (:func:`checked_scores_labels`)."""
    s, y = checked_scores_labels(scores, labels)
    pos, neg = s[y], np.sort(s[~y])
    if pos.size == 0 or neg.size == 0:
        return float("nan")
    below = np.searchsorted(neg, pos, side="left")  # negatives strictly below each positive
    upto = np.searchsorted(neg, pos, side="right")  # ... plus those tied with it
    # 2 U = 2 (greater + ties / 2) = below + upto, an exact integer; one rounding in the division
    twice_u = int(below.sum(dtype=np.int64)) + int(upto.sum(dtype=np.int64))
    return float(twice_u / (2 * pos.size * neg.size))


def accuracy(scores, labels, threshold: float = 0.5) -> float:
    """Fraction of slides whose ``score >= threshold`` equals their 0/1 label; NaN when there is no slide.
    Refuses what :func:`roc_auc` refuses (:func:`checked_scores_labels`)."""
    s, y = checked_scores_labels(scores, labels)
    if s.size == 0:
        return float("nan")
    return float(np.mean((s >= threshold) == y))


#: The confidence level of every AUC interval histojax prints (two-sided).
INTERVAL_LEVEL = 0.95
_Z95 = 1.959963984540054


def _newcombe_variance(theta: float, n_pos: int, n_neg: int) -> float:
    """Hanley–McNeil variance of an AUC ``theta`` with Newcombe's N* = (n⁺ + n⁻)/2 − 1 for both
    classes (Newcombe 2006, method 5)."""
    n_star = (n_pos + n_neg) / 2.0 - 1.0
    tail = (1.0 - theta) / (2.0 - theta) + theta / (1.0 + theta)
    return theta * (1.0 - theta) / (n_pos * n_neg) * (1.0 + (n_star - 1.0) * tail)


def auc_interval(auc: float, n_pos: int, n_neg: int, level: float = INTERVAL_LEVEL) -> tuple[float, float]:
    """The 95 % interval over slides of an AUC measured on ``n_pos`` tumour and ``n_neg`` normal slides.

    Newcombe's score-type interval for the Mann–Whitney AUC (Newcombe 2006, *Statistics in Medicine*
    25:559, method 5): every θ in [0, 1] with |AUC − θ| ≤ z·√V(θ), V the Hanley–McNeil variance at θ
    (not at the estimate). Unlike a percentile bootstrap or DeLong's interval, it stays wide when the
    estimate is 1.0 on a few slides: AUC 1.0 on 2 tumour and 4 normal slides gives [0.556, 1.0].
    Returns ``(nan, nan)`` (undefined) when either class is empty or ``auc`` is NaN. Refuses
    (:class:`MetricInputError`) an ``auc`` outside [0, 1] or infinite and a negative or fractional count.
    Only the 95 % level is tabled.
    """
    if level != INTERVAL_LEVEL:
        raise ValueError(f"only the {INTERVAL_LEVEL:.0%} interval is supported, not {level}")
    for name, n in (("n_pos", n_pos), ("n_neg", n_neg)):
        if not float(n).is_integer() or n < 0:
            raise MetricInputError(f"{name} must be a count of slides (0, 1, 2, ...), not {n!r}")
    auc = float(auc)
    if np.isnan(auc) or n_pos == 0 or n_neg == 0:
        return float("nan"), float("nan")
    if not 0.0 <= auc <= 1.0:
        raise MetricInputError(f"an AUC lies in [0, 1], not {auc!r}")
    z2 = _Z95**2

    def inside(theta: float) -> bool:
        return (auc - theta) ** 2 <= z2 * _newcombe_variance(theta, n_pos, n_neg)

    def edge(outer: float) -> float:  # bisect between the estimate (inside) and an outer end
        if inside(outer):
            return outer
        lo, hi = auc, outer
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if inside(mid) else (lo, mid)
        return lo

    return float(edge(0.0)), float(edge(1.0))


def roc_auc_with_interval(scores, labels) -> dict:
    """AUC of ``scores`` for 0/1 ``labels`` with its 95 % interval over slides (:func:`auc_interval`).

    Returns ``{"auc", "auc_low", "auc_high", "n_tumour", "n_normal"}``; the three AUC fields are NaN
    when a class is missing (write them with :func:`json_number` so no JSON file holds ``NaN``); refuses what
    :func:`roc_auc` refuses."""
    _, y = checked_scores_labels(scores, labels)
    auc = roc_auc(scores, y)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    low, high = auc_interval(auc, n_pos, n_neg)
    return {"auc": auc, "auc_low": low, "auc_high": high, "n_tumour": n_pos, "n_normal": n_neg}


def format_auc(auc: float, low: float, high: float) -> str:
    """``"AUC 0.849 [0.741, 0.936]"`` — how every histojax command prints an AUC with its interval
    (``"AUC undefined (one class)"`` when the AUC is NaN)."""
    if not np.isfinite(auc):
        return "AUC undefined (one class)"
    return f"AUC {auc:.3f} [{low:.3f}, {high:.3f}]"


UNDEFINED = "undefined: one class"
"""What a table prints (and a JSON record holds as ``null``) for a figure the slides scored cannot define: an AUC of
slides of one class (``histojax evaluate``, the learned head's fit)."""


def json_number(x):
    """``x`` as a JSON-safe value: a finite float stays, NaN / ±inf become ``None`` (JSON ``null``)."""
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


#: Fewer slides than this in either class and the 95 % interval of a typical AUC (0.85) is wider than
#: ±0.15 (:func:`auc_interval`: 13 + 13 slides give [0.643, 0.942]); such a split cannot rank readers or
#: heads, and every command that scores or fits on one says so (:func:`small_split_warning`).
SMALL_SPLIT_PER_CLASS = 13


def small_split_warning(n_tumour: int, n_normal: int, where: str) -> str | None:
    """One warning line when ``where`` (e.g. ``"the test split"``, ``"fold 2's validation share"``) holds
    fewer than :data:`SMALL_SPLIT_PER_CLASS` slides of either class, naming the counts and what to do;
    ``None`` when it is large enough."""
    if min(n_tumour, n_normal) >= SMALL_SPLIT_PER_CLASS:
        return None
    low, high = auc_interval(0.85, max(n_tumour, 1), max(n_normal, 1))
    return (
        f"warning: {where} holds {n_tumour} tumour and {n_normal} normal slides: at these counts the 95 % "
        f"interval of an AUC near 0.85 spans [{low:.2f}, {high:.2f}] (±{(high - low) / 2:.2f}; it narrows to "
        f"±0.15 at {SMALL_SPLIT_PER_CLASS} slides a class) — too few to rank heads or readers. Use k folds "
        f"(dataset --folds K, then --all-folds) or a larger --val-fraction, and report the interval beside the AUC."
    )


def auc_over_runs(scores, labels) -> dict:
    """The AUC of several runs (random reader orders, policy seeds) on the same slides, with its 95 % interval.

    ``scores (R, B)``: each run's per-slide scores of the ``B`` slides whose 0/1 ``labels (B,)`` are given (a 1-D
    ``(B,)`` is one run). Returns ``{"auc": mean over runs, "auc_std": std over runs, "auc_low", "auc_high",
    "auc_per_run": [R], "n_tumour", "n_normal"}``: the interval is :func:`auc_interval` of the mean AUC over the
    ``B`` slides, each counted once (the runs share their slides, so they add no slides; the std says how much
    the runs differ). NaN fields when a class is missing; each run refused as :func:`roc_auc` refuses."""
    s = np.atleast_2d(np.asarray(scores, np.float64))
    if s.ndim != 2:
        raise MetricInputError(f"scores of several runs must be (runs, slides), not of shape {s.shape}")
    _, y = checked_scores_labels(s[0], labels) if len(s) else (None, np.asarray(labels).astype(bool))
    aucs = np.asarray([roc_auc(row, y) for row in s])
    auc = float(aucs.mean())
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    low, high = auc_interval(auc, n_pos, n_neg)
    return {
        "auc": auc,
        "auc_std": float(aucs.std()),
        "auc_low": low,
        "auc_high": high,
        "auc_per_run": [float(a) for a in aucs],
        "n_tumour": n_pos,
        "n_normal": n_neg,
    }


def format_auc_runs(auc: float, std: float, low: float, high: float, runs: int = 2) -> str:
    """``"AUC 0.849 ± 0.035 [0.741, 0.936]"`` (mean ± std over ``runs`` seeds or folds, then the 95 % interval
    over the slides); one run: :func:`format_auc`."""
    if runs <= 1 or not np.isfinite(std):
        return format_auc(auc, low, high)
    if not np.isfinite(auc):
        return format_auc(auc, low, high)
    return f"AUC {auc:.3f} ± {std:.3f} [{low:.3f}, {high:.3f}]"


def json_safe(value):
    """``value`` (dicts, lists, tuples, numpy scalars and arrays nested) with every NaN / ±inf float replaced by
    ``None``, ready for ``json.dumps(..., allow_nan=False)``: no JSON file histojax writes holds ``NaN``."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return json_number(value)
    return value
