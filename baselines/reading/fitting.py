"""The rules the head fits share (``head_fit`` and ``head_mil_fit``): the fewest training slides of a class a fit
accepts (:func:`check_classes`), the refusal of a chosen head that ranks tumour below normal or whose calibration
slope is not positive (:func:`check_head`), and the 1-D logistic calibration they fit (:func:`logistic_fit`).

A rerun keeps a finished head (all three fits, ``learned_head_fit`` too): each records its command's options in its
``config.json`` (:data:`OPTIONS`, :func:`fit_options`), and :func:`claim_head` decides before any slide is read
whether the same command rerun has nothing to fit, fits again (a fit killed before its head was written), is refused
(a head of other options, in one line naming the first difference), or, with ``--restart``, moves the old head
aside to ``OUT.previous-N`` (never deleted)."""

from __future__ import annotations

import json
import os
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


# ----------------------------------------------------------------------------- a rerun keeps a finished head
OPTIONS = "fit_options"
"""The key of a head's ``config.json`` recording the options of the command that fitted it (:func:`fit_options`):
what a rerun of the command compares (:func:`claim_head`)."""


def fit_options(dataset, fold: int | None, **options) -> dict:
    """What a head fit's command fits (recorded in its ``config.json`` under :data:`OPTIONS`): the dataset's
    resolved folder and seal (:func:`baselines.reading.provenance.dataset_identity`: a rebuilt or edited dataset is
    another fit), ``--fold``, and the fit's own ``options`` named by their flags (``{"--seed": 0, ...}``)."""
    from baselines.reading.provenance import dataset_identity

    ident = dataset_identity(dataset)
    return {"--dataset": ident["folder"], "the dataset's seal": ident["seal"], "--fold": fold, **options}


def _value(v) -> str:
    if isinstance(v, (list, tuple)):
        return " ".join(_value(x) for x in v) or "(none)"
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "on" if v else "off"
    return str(v)


def _leftover(out: Path) -> Path | None:
    """A temporary head folder beside ``out`` (``.NAME.tmp-XXXXXXXX`` holding the head writer's marker): a save
    of ``out`` that was killed before its head was in place."""
    from histojax.reading.heads.files import TEMP_MARKER

    try:
        names = sorted(os.listdir(out.parent if str(out.parent) else "."))
    except OSError:
        return None
    for name in names:
        path = out.parent / name
        if name.startswith(f".{out.name}.tmp-") and not path.is_symlink() and (path / TEMP_MARKER).is_file():
            return path
    return None


PARTIAL = {"params.json", "params.npz", ".params.json.tmp", ".params.npz.tmp", ".config.json.tmp"}
"""What a head folder holds when its write (parameters first, ``config.json`` last) was killed before its config."""


def head_state(out, kind, options: dict) -> tuple[str, str]:
    """What the head folder ``out`` holds for a fit of ``kind`` (a head kind, or a tuple of the kinds the fit may
    save) with ``options`` (:func:`fit_options`):
    ``("new", "")`` (absent, empty, or not a folder: the fit's own checks decide), ``("again", why)`` (no finished
    head, but a save of it was killed: a marked temporary beside it, or parameters without ``config.json``), ``("done", "")`` (a finished head of these options), ``("other", what)``
    (a head of other options: ``what`` names the first entry that differs) or ``("foreign", "")`` (not a head of
    ``kind``: the fit's own refusal of foreign files names it). Reads only ``out/config.json``."""
    from data_tools.bundle_files.writes import left_run_lock
    from histojax.reading.heads.files import CONFIG, HeadFileError, read_config

    out = Path(out)
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if out.is_symlink() or (os.path.lexists(out) and not out.is_dir()):
        return "new", ""  # a link or a file: the fit's own checks refuse it
    entries = sorted(p.name for p in out.iterdir() if not left_run_lock(p)) if out.is_dir() else []
    if not entries:
        if (left := _leftover(out)) is not None:
            return "again", f"a fit killed while saving its head left {left.name}"
        return "new", ""
    if CONFIG not in entries and set(entries) <= PARTIAL:  # config.json is written last: a write killed before it
        return "again", f"a fit killed while writing its head left {', '.join(entries)} without {CONFIG}"
    try:
        saved = read_config(out / CONFIG)
    except HeadFileError:
        return "foreign", ""
    if saved.get("kind") not in kinds:
        return "foreign", ""
    recorded = saved.get(OPTIONS)
    if not isinstance(recorded, dict):
        return "other", "whose config.json records no fit options (fitted before histojax recorded them)"
    for key, value in options.items():
        if key not in recorded:
            return "other", f"whose config.json records no {key} (this command's: {_value(value)})"
        same = json.dumps(recorded[key], sort_keys=True) == json.dumps(value, sort_keys=True)  # json-not-written
        if not same:
            return "other", f"fitted with {key} {_value(recorded[key])}, not {_value(value)}"
    return "done", ""


def move_head_aside(out) -> Path:
    """Rename the head folder ``out`` (a finished head or a set of fold heads) to its next free sibling
    ``OUT.previous-N`` (N = 1, 2, ...): one rename, nothing deleted, the old head still a loadable head folder.
    Returns the new path."""
    out = Path(out)
    n = 1
    while os.path.lexists(out.with_name(f"{out.name}.previous-{n}")):
        n += 1
    dest = out.with_name(f"{out.name}.previous-{n}")
    os.rename(out, dest)
    return dest


def refusal(out, what: str) -> str:
    """The one line refusing a head folder ``out`` of another fit (``what``: :func:`head_state`'s)."""
    return f"{out} holds a head {what}; --restart moves it aside (to {out}.previous-N), or choose another --out"


def claim_head(out, kind, options: dict, restart: bool = False) -> str:
    """Decide, before any slide is read, what a head fit of ``kind`` with ``options`` does with ``out``, and say it
    in one line (none for a new folder): ``"new"``; ``"again"`` (a fit killed before its head was written: fitted
    again); ``"done"`` (a finished head of this command: nothing to fit); ``"restarted"`` (``restart``: the head
    there moved aside, :func:`move_head_aside`, never deleted). A head of other options is refused
    (:class:`HeadDataError`, one line naming ``out``: :func:`refusal`); anything that is not a head of ``kind`` is left to the
    fit's own checks (they refuse foreign files). The progress within one fit is not kept (fits take seconds to
    minutes); a finished head is."""
    out = Path(out)
    state, what = head_state(out, kind, options)
    if restart and state in ("done", "other"):
        dest = move_head_aside(out)
        print(f"{out}: moved the head there aside to {dest} (--restart); fitting it again", flush=True)
        return "restarted"
    if state == "other":
        raise HeadDataError(None, refusal(out, what))  # the line names the folder itself
    if state == "done":
        print(f"{out} holds a finished head of this command: nothing to fit (--restart fits it again)", flush=True)
    elif state == "again":
        print(f"{out} holds no finished head ({what}): fitting it again", flush=True)
    return "new" if state == "foreign" else state


def add_restart(p) -> None:
    """``--restart``: the option of every head fit that fits again over a finished head (moved aside)."""
    p.add_argument(
        "--restart",
        action="store_true",
        help="fit again even when --out holds a finished head (of this command or another): the head there is "
        "moved aside to OUT.previous-N, never deleted",
    )
