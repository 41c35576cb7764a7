"""Experiment drivers: commands that train, evaluate or score agents, heads and encoders to produce the figures
of the results pages (the C16 reference table, held-out targets, the diagnosis ceilings, the encoders' patch
AUC, what the integration snippets learn, the cost of hostile annotation files), each ``python -m
experiments.<name>``. They import ``baselines``, ``histojax`` and ``data_tools``; nothing imports them.
Speed and memory measurements are in ``benchmarks``."""

from __future__ import annotations

from pathlib import Path


def read_dataset(folder, lists=("train", "test")) -> dict:
    """``folder``'s ``dataset.json`` with the lists an experiment reads checked (``lists``: e.g. ``"train"``,
    ``"test"``, ``"slides"``, the c16 / synth datasets' slide records): a missing, malformed or incomplete file is a
    :class:`~data_tools.errors.HistojaxDataError` naming it (one line), never a ``KeyError`` traceback."""
    import json

    from data_tools.errors import HistojaxDataError

    path = Path(folder) / "dataset.json"
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise HistojaxDataError(
            path, "missing (not a dataset folder: build one with `python -m data_tools c16`)"
        ) from None
    except (OSError, ValueError) as e:
        raise HistojaxDataError(path, f"unreadable ({e})") from None
    if not isinstance(spec, dict):
        raise HistojaxDataError(path, "not a JSON object of splits")
    for key in lists:
        value = spec.get(key)
        records = key == "slides"
        if not isinstance(value, list) or not all(isinstance(v, dict if records else str) for v in value):
            what = "slide records (a c16 or synth dataset's)" if records else "bundles"
            raise HistojaxDataError(path, f"has no {key!r} list of {what}")
    return spec
