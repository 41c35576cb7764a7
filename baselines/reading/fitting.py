"""The rules the head fits share (``head_fit`` and ``head_mil_fit``): the fewest training slides of a class a fit
accepts (:func:`check_classes`), the refusal of a chosen head that ranks tumour below normal or whose calibration
slope is not positive (:func:`check_head`), and the 1-D logistic calibration they fit (:func:`logistic_fit`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from baselines.reading.slides import HeadDataError

MIN_SLIDES_PER_CLASS = 5
"""Fewest training slides of each class (after the validation share is held back) a head fit accepts."""


def logistic_fit(x, y, steps: int = 3000) -> tuple[float, float]:
    """``(a, b)`` minimising the mean log loss of ``sigmoid(a · x + b)`` against 0/1 ``y`` (convex, 2 parameters;
    a small L2 penalty keeps ``a`` finite when the classes separate)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    mu, sd = x.mean(), x.std() + 1e-9
    z, w, c = (x - mu) / sd, 0.0, 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-np.clip(w * z + c, -60, 60)))
        w -= 0.5 * (float(np.mean((p - y) * z)) + 1e-3 * w)
        c -= 0.5 * float(np.mean(p - y))
    return w / sd, c - w * mu / sd


def check_classes(dataset, train: list[dict], least: int = MIN_SLIDES_PER_CLASS) -> None:
    """Refuse (:class:`HeadDataError` naming ``dataset.json``) fewer than ``least`` training slides of either
    class once the validation share is held back."""
    for cls, what in ((1, "tumour"), (0, "normal")):
        n = sum(int(s["label"] == cls) for s in train)
        if n < least:
            raise HeadDataError(
                Path(dataset) / "dataset.json",
                f"{n} {what} training slides after the validation "
                f"share is held back; a slide head needs at least {least} of each class "
                "(MIN_SLIDES_PER_CLASS)",
            )


def check_head(dataset, validation_auc: float, slope: float) -> None:
    """Refuse (:class:`HeadDataError` naming ``dataset.json``; nothing is saved) a chosen head whose validation AUC
    is below 0.5 (it ranks tumour below normal: e.g. a feature entry that is no tumour logit) or whose calibration
    slope is negative (a higher statistic would mean less tumour)."""
    where = Path(dataset) / "dataset.json"
    if not validation_auc >= 0.5:
        raise HeadDataError(
            where,
            f"the chosen head's validation AUC is {validation_auc:.3f} (< 0.5: it ranks tumour "
            "below normal; is the feature entry a tumour logit? fit a learned head on any "
            "features: python -m baselines.reading.learned_head_fit); nothing saved",
        )
    if not slope > 0:
        raise HeadDataError(
            where,
            f"the chosen head's calibration slope is {slope:.3f} (not > 0: more evidence "
            "would mean less tumour); nothing saved",
        )


CHANCE_FLAG = "validation_interval_contains_chance"
"""The ``chosen_on`` key of a head's ``config.json`` set (true) when its validation AUC's 95 % interval reaches 0.5."""


def chance_warning(auc: float, low: float, high: float, where: str) -> str | None:
    """One warning line when the chosen head's validation AUC interval (``low``, ``high``: 95 %,
    :func:`data_tools.metrics.auc_interval`) reaches 0.5: its validation slides cannot tell it from a head that ranks
    at random. ``where`` names the share (``"the validation share of fold 1"``). None otherwise (or undefined)."""
    if not (low == low and low <= 0.5):
        return None
    return (
        f"warning: {where} gives the chosen head validation AUC {auc:.3f} [{low:.3f}, {high:.3f}] (95 % interval), "
        f"which contains 0.5: these validation slides cannot tell it from a head ranking at random; saved with "
        f"{CHANCE_FLAG}: true in config.json; validate it on more slides before relying on it"
    )
