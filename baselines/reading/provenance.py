"""What a slide head was fitted on, and the one guard every scorer applies with it.

Every head fit (:mod:`baselines.reading.head_fit`, :mod:`~baselines.reading.head_mil_fit`,
:mod:`~baselines.reading.learned_head_fit`) records in its ``config.json`` the entry :data:`RECORD`
(:func:`fit_record`): the dataset (folder, ``kind`` and seal, ``dataset_sha256``), the split and fold it was fitted
on, and the slide names used for **fitting** and for **validation** (choosing a candidate or a checkpoint,
calibrating). Every scorer (``histojax evaluate --head``, ``readers``, ``budget-curve``, ``learned_head_fit
--score``, ``diagnosis``) calls :func:`check_scored` with the slides it is about to score: a slide the head was
fitted or validated on is refused (one line naming the head's ``config.json``, the slides and the way out), or, with
``--allow-fitting-slides``, warned about on stderr and scored.

Slides are matched **by name** (the bundle's folder name), whatever dataset folder they are read from: a rebuilt
dataset (another encoder, another scale, the C16 small set) holds the same slides under the same names.

**Heads without the record** (published heads, heads fitted before it): a head whose ``config.json`` records a fit
(``fitted_on``) is taken to have been fitted on the scored dataset's **train split** (the whole one, without folds;
an older fold fit whose ``fitted_on`` records its ``fold``: that fold's train side, the other folds):
how every head fit worked before, and how the published C16 heads were fitted (on ``c16-full``'s train split, which
every C16 set shares). So scoring their test split works as before, and a fold's held-out side that lies in the
train split is refused like any other fitting slide. A head that records no fit at all (built in code, uncalibrated)
has seen no slide.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from data_tools.errors import HistojaxDataError

RECORD = "slides_seen"
"""Key of the fit record in a head's ``config.json`` (:func:`fit_record`)."""
FLAG = "--allow-fitting-slides"
"""The option that turns the refusal into a warning."""


class FittingSlidesError(HistojaxDataError):
    """A head asked to score slides it was fitted or validated on (one line naming its ``config.json``)."""


def _name(entry) -> str:
    return Path(str(entry)).name


def dataset_identity(dataset, spec: dict | None = None) -> dict:
    """``{"folder", "kind", "seal"}`` of a dataset: its resolved folder, ``dataset.json``'s ``kind`` and seal
    (``dataset_sha256``, None for an unsealed index; a derived validation split: its source's seal)."""
    from data_tools.bundle_files.seals import DATASET_DIGEST, read_dataset_json

    if spec is None:
        try:
            spec = read_dataset_json(dataset)
        except (OSError, ValueError):
            spec = {}
    seal = spec.get(DATASET_DIGEST) if isinstance(spec, dict) else None
    return {
        "folder": str(Path(dataset).resolve()),
        "kind": spec.get("kind") if isinstance(spec, dict) else None,
        "seal": seal,
    }


def fit_record(dataset, spec: dict, fold: int | None, fitted, validation, split: str = "train") -> dict:
    """The :data:`RECORD` entry of a head's ``config.json``: the dataset's identity (:func:`dataset_identity`, the seal
    of its ``dataset.json`` as read without a fold), ``split`` and ``fold`` fitted on, and the sorted slide names of
    ``fitted`` (the slides whose labels trained or calibrated it) and ``validation`` (the slides that chose its
    candidate or checkpoint, or calibrated it), each a list of ``dataset.json`` entries or names."""
    from data_tools.bundle_files.seals import read_dataset_json

    try:
        base = read_dataset_json(dataset)  # the index itself (spec may be a fold's sides)
    except (OSError, ValueError):
        base = spec
    return {
        "dataset": dataset_identity(dataset, base),
        "split": split,
        "fold": fold,
        "fitted": sorted({_name(e) for e in fitted}),
        "validation": sorted({_name(e) for e in validation}),
    }


def head_config(head) -> dict:
    """The fit information a loaded head carries (its ``info``: ``config.json`` beyond its structure); ``{}`` when
    none."""
    try:
        info = json.loads(getattr(head, "info", "{}") or "{}")
    except (TypeError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def slides_seen(head, dataset) -> tuple[set[str], set[str], str]:
    """``(fitted, validation, source)``: the slide names ``head`` was fitted and validated on and where that comes
    from: its :data:`RECORD` (``"recorded"``), else, for a head recording a fit but no slides (published or older
    heads), the train split of ``dataset``'s ``dataset.json`` read without a fold (``"assumed"``), else nothing
    (``"none"``: a head built in code)."""
    info = head_config(head)
    rec = info.get(RECORD)
    if isinstance(rec, dict):
        return set(map(str, rec.get("fitted") or [])), set(map(str, rec.get("validation") or [])), "recorded"
    if "fitted_on" not in info or dataset is None:  # no dataset named (bundle folders given): nothing to assume
        return set(), set(), "none"
    from data_tools.bundle_files.seals import read_dataset_json

    try:
        spec = read_dataset_json(dataset)
    except (OSError, ValueError):
        return set(), set(), "none"
    fold = (info.get("fitted_on") or {}).get("fold") if isinstance(info.get("fitted_on"), dict) else None
    if isinstance(fold, int) and not isinstance(fold, bool):  # an older fold fit: the other folds' slides
        from histojax.datasets import with_fold

        try:
            spec = with_fold(spec, fold)
        except (HistojaxDataError, ValueError):
            pass  # the dataset has no such fold: its train split, as for any older head
    return {_name(e) for e in spec.get("train") or []}, set(), "assumed"


def overlap(head, dataset, scored) -> tuple[list[str], list[str], str]:
    """``(fitted, validated, source)``: the names among ``scored`` (``dataset.json`` entries, paths or names) the head
    was fitted on, those it was validated on only, and :func:`slides_seen`'s source."""
    fitted, validation, source = slides_seen(head, dataset)
    names = sorted({_name(e) for e in scored})
    return [n for n in names if n in fitted], [n for n in names if n in validation and n not in fitted], source


def check_scored(head, head_dir, dataset, scored, allow: bool = False, what: str = "scores") -> str | None:
    """Refuse (:class:`FittingSlidesError`, one line naming ``HEAD_DIR/config.json``) scoring ``scored`` slides with a
    head fitted or validated on some of them; with ``allow``, print the same as one ``warning:`` line on stderr and
    return it. ``None`` when no scored slide was seen in fitting."""
    fitted, validated, source = overlap(head, dataset, scored)
    if not fitted and not validated:
        return None
    seen = fitted + validated
    n = len({_name(e) for e in scored})
    parts = ([f"fitted on {len(fitted)}"] if fitted else []) + ([f"validated on {len(validated)}"] if validated else [])
    rec = head_config(head).get(RECORD) or {}
    fold = rec.get("fold") if isinstance(rec, dict) else None
    how = (
        ""
        if source == "recorded"
        else " (it records no slides: taken as fitted on this dataset's train split, as published and older heads were)"
    )
    on_fold = f"; it was fitted on fold {fold}'s train side" if fold is not None else ""
    problem = (
        f"the head was {' and '.join(parts)} of the {n} slides it {what} (e.g. {', '.join(seen[:3])})"
        f"{how}{on_fold}: figures on them are not held out"
    )
    where = Path(head_dir) / "config.json" if head_dir is not None else None
    if not allow:
        raise FittingSlidesError(
            where,
            f"{problem}; score slides it has not seen (the test split, or the held-out "
            f"fold of the head fitted on that fold), or pass {FLAG} to score them with a "
            "warning",
        )
    line = f"{where}: {problem} ({FLAG} given)" if where else f"{problem} ({FLAG} given)"
    print(f"warning: {line}", file=sys.stderr, flush=True)
    return line


def add_flag(p) -> None:
    """Add :data:`FLAG` to a scorer's argument parser."""
    p.add_argument(
        FLAG,
        dest="allow_fitting_slides",
        action="store_true",
        help="score slides the head was fitted or validated on, with a warning (refused by default: "
        "figures on them are not held out)",
    )


def head_for_fold(head, fold: int) -> str:
    """The head folder of fold ``fold``: ``head`` with ``{fold}`` replaced, or ``HEAD/foldI`` when ``head`` is the
    folder ``learned_head_fit --all-folds`` wrote (``fold0``, ``fold1``, ... and no ``config.json``); else ``head``
    itself (one head for every fold: :func:`check_scored` refuses it where it saw a fold's slides)."""
    text = str(head)
    if "{fold}" in text:
        return text.replace("{fold}", str(fold))
    folder = Path(text)
    if not (folder / "config.json").exists():
        if (folder / f"fold{fold}" / "config.json").exists():
            return str(folder / f"fold{fold}")
        present = sorted(p.name for p in folder.glob("fold*") if (p / "config.json").is_file())
        if present:  # an --all-folds folder without this fold's head (e.g. a run that stopped early)
            raise HistojaxDataError(
                folder / f"fold{fold}",
                f"missing: {folder} holds the heads of {', '.join(present)} only; fit fold {fold}'s with "
                f"python -m baselines.reading.learned_head_fit --all-folds --out {folder} (or --fold {fold} --out "
                f"{folder / f'fold{fold}'})",
            )
    return text


__all__ = [
    "FLAG",
    "RECORD",
    "FittingSlidesError",
    "add_flag",
    "check_scored",
    "dataset_identity",
    "fit_record",
    "head_config",
    "head_for_fold",
    "overlap",
    "slides_seen",
]
