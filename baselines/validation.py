"""A validation split of a dataset's training slides, held back from training, for choosing
hyperparameters and checkpoints without looking at the test slides.

:func:`split_train` draws a seeded share (``fraction``) of the ``"train"`` list of a ``dataset.json``,
keeping tumour and normal slides on both sides (each class is split on its own) and keeping a
tumour slide together with the normal slide that lent it its tissue (``slides[].tissue_donor``,
``python -m data_tools c16``): such a pair is one unit. :func:`write_validation_dataset` writes a
derived dataset folder (only a ``dataset.json``, bundle paths absolute) whose ``"train"`` list is
the kept training slides and whose ``"test"`` list is the validation slides; every other entry of
the original ``dataset.json`` (format, encoder, labels, slides records) is copied, so the
``HistoJAX-C16-*`` ids accept it as they accept the original. Train on it with ``split="train"``,
validate with ``split="test"``; the original dataset's ``"test"`` list stays untouched for the
final report.

    python -m baselines.validation --dataset DIR --fraction 0.2 --seed 0 --out DIR/validation-0.2-0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from baselines import outputs


def _name(path: str) -> str:
    return Path(path).name


def units(spec: dict) -> list[list[str]]:
    """The training slides (entries of ``spec["train"]``) grouped into units that stay on one side: the slides
    of one patient (``dataset.json``'s ``patients``, else a TCGA barcode's patient; grouped by
    :func:`data_tools.datasets.split.patient_groups`, the grouping of the default split and the folds) and a
    tumour slide with its tissue donor when the donor is a training slide too; else one slide."""
    from data_tools.datasets.split import patient_groups

    train = list(spec.get("train", []))
    by_name = {_name(t): t for t in train}
    donor = {
        _name(s["bundle"]): s.get("tissue_donor")
        for s in spec.get("slides", [])
        if isinstance(s, dict) and "bundle" in s
    }
    parent = {n: n for n in by_name}

    def find(n):
        while parent[n] != n:
            n = parent[n]
        return n

    def join(a, b):
        a, b = find(a), find(b)
        if a != b:
            parent[max(a, b)] = min(a, b)

    recorded = spec.get("patients") if isinstance(spec.get("patients"), dict) else None
    first: dict[str, str] = {}
    for n, g in patient_groups(sorted(by_name), recorded)[0].items():
        if g.startswith("patient:"):
            join(first.setdefault(g, n), n)
    for n in by_name:
        d = donor.get(n)
        if d and d in by_name:
            parent[find(n)] = find(d)
    groups: dict[str, list[str]] = {}
    for n, t in by_name.items():
        groups.setdefault(find(n), []).append(t)
    return [sorted(g) for _, g in sorted(groups.items())]


def slide_label(spec: dict, name: str) -> int:
    """1 (tumour) / 0 (normal) of a bundle name from ``slides[].label`` or ``labels``; 1 when unknown."""
    for s in spec.get("slides", []):
        if isinstance(s, dict) and _name(s.get("bundle", "")) == name and "label" in s:
            return int(s["label"])
    labels = spec.get("labels") or {}
    for k, v in labels.items():
        if _name(k) == name:
            return int(v)
    return 1


def split_train(spec: dict, fraction: float, seed: int = 0) -> tuple[list[str], list[str]]:
    """``(kept, validation)`` entries of ``spec["train"]``: about ``fraction`` of the training slides
    held back, drawn with ``seed``. Units (:func:`units`) are split per class (a unit with a tumour
    slide is a tumour unit): each class with at least two units gives at least one to each side, so
    both sides see tumour and normal slides whenever the training split has two of each."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"the validation fraction must be in (0, 1), got {fraction}")
    groups = units(spec)
    if len(groups) < 2:
        raise ValueError(
            f"a validation split needs at least two training slides (units); this dataset has {len(groups)}"
        )
    rng = np.random.default_rng(seed)
    kept, val = [], []
    for cls in (1, 0):
        mine = [g for g in groups if max(slide_label(spec, _name(t)) for t in g) == cls]
        if not mine:
            continue
        order = rng.permutation(len(mine))
        n_val = int(round(fraction * len(mine)))
        if len(mine) >= 2:
            n_val = min(max(n_val, 1), len(mine) - 1)
        for rank, i in enumerate(order):
            (val if rank < n_val else kept).extend(mine[i])
    if not kept or not val:
        raise ValueError(f"fraction {fraction} leaves one side empty ({len(kept)} kept, {len(val)} validation)")
    return sorted(kept), sorted(val)


MIN_VALIDATION_PER_CLASS = 3
"""Fewest validation slides of each class a head fit accepts. With ``n`` tumour and ``n`` normal slides, a head that
ranks at random reaches validation AUC 1.0 with probability ``1 / C(2n, n)``: 1 in 2 with one of each, 1 in 6 with
two, 1 in 20 with three. Below three, choosing a candidate or a checkpoint by the best validation AUC picks lucky
heads about as often as good ones (a fold fit chose AUC 1.000 on 3–4 slides and scored 0.167 on its test slides)."""


def _known_label(spec: dict, name: str) -> int | None:
    """A slide's 0/1 label from ``slides[].label`` or ``labels`` of ``dataset.json``; None when neither names it."""
    for s in spec.get("slides", []):
        if isinstance(s, dict) and _name(s.get("bundle", "")) == name and "label" in s:
            return int(s["label"])
    for k, v in (spec.get("labels") or {}).items():
        if _name(k) == name:
            return int(v)
    return None


def share_counts(spec: dict, fraction: float, seed: int) -> tuple[int, int, int, int] | None:
    """``(fitting tumour, fitting normal, validation tumour, validation normal)`` slides of :func:`split_train`
    (``fraction``, ``seed``) by ``dataset.json``'s labels; None when it does not label every training slide, or
    the fraction leaves a side empty (counted as nothing on that side)."""
    labels = {_name(e): _known_label(spec, _name(e)) for e in spec.get("train", [])}
    if not labels or None in labels.values():
        return None
    try:
        kept, held = split_train(spec, fraction, seed)
    except ValueError:
        return (0, 0, 0, 0)
    k = [labels[_name(e)] for e in kept]
    h = [labels[_name(e)] for e in held]
    return sum(k), len(k) - sum(k), sum(h), len(h) - sum(h)


def share_works(counts, least: int, fitting: int) -> bool:
    """Whether :func:`share_counts` ``counts`` give ``least`` validation and ``fitting`` fitting slides a class."""
    return counts is None or (min(counts[2:]) >= least and min(counts[:2]) >= fitting)


def working_fraction(specs, seed: int, least: int = MIN_VALIDATION_PER_CLASS, fitting: int = 0) -> float | None:
    """The smallest ``--val-fraction`` (a hundredth: 0.01 … 0.99) whose share (:func:`split_train`, ``seed``) of
    every spec in ``specs`` (a dataset's train side, or each fold's) holds ``least`` validation and ``fitting``
    fitting slides of each class; None when none does."""
    for f in range(1, 100):
        if all(share_works(share_counts(spec, f / 100, seed), least, fitting) for spec in specs):
            return f / 100
    return None


def _counts_text(counts) -> str:
    ft, fn, vt, vn = counts
    return f"{vt} tumour and {vn} normal validation slides, leaving {ft} tumour and {fn} normal to fit on"


def check_validation_share(
    spec: dict,
    held,
    where,
    fraction: float,
    fold: int | None = None,
    least: int = MIN_VALIDATION_PER_CLASS,
    seed: int | None = None,
    fitting: int = 0,
) -> None:
    """Refuse, before any slide is read or any training, a validation share (``held``: entries of ``spec["train"]``)
    with fewer than ``least`` slides of a class, or (``seed``: the share's seed, ``fitting``: the fit's
    :data:`~baselines.reading.fitting.MIN_SLIDES_PER_CLASS`) one that leaves fewer than ``fitting`` slides of a class
    to fit on: ``ValueError`` in one line naming ``where`` (the ``dataset.json``), the counts and what would work
    (the smallest ``--val-fraction`` that does, or, when none does, that no fraction works and what to do instead).
    Labels come from ``dataset.json``; a share whose labels it does not give is left to the fit's own checks."""
    labels = [_known_label(spec, _name(e)) for e in held]
    if None in labels:
        return
    n_t, n_n = sum(labels), len(labels) - sum(labels)
    counts = share_counts(spec, fraction, seed) if seed is not None else None
    if min(n_t, n_n) >= least and (counts is None or min(counts[:2]) >= fitting):
        return
    side = f"fold {fold}'s train side" if fold is not None else "the train split"
    needs = (
        f"at least {least} validation"
        + (f" and at least {fitting} fitting" if fitting else "")
        + " slides of each class"
    )
    what = _counts_text(counts) if counts is not None else f"{n_t} tumour and {n_n} normal validation slides"
    works = working_fraction([spec], seed, least, fitting) if seed is not None else None
    if works is not None:
        remedy = f"use --val-fraction {works:.2f}" + (" (the smallest that does)" if works > fraction else "")
    elif seed is not None:
        remedy = f"no --val-fraction does ({side} holds {_class_counts(spec)}); " + (
            "build the dataset with more --folds K (each fold's train side is larger), or add slides"
            if fold is not None
            else "add slides"
        )
    else:
        remedy = (
            "give a larger --val-fraction, or build the dataset with more --folds K (each fold's train side is "
            "larger), or add slides"
        )
    raise ValueError(
        f"{where}: the validation share ({fraction:g} of {side}) gives {what}; choosing a head or checkpoint and "
        f"calibrating it needs {needs} (a random head scores validation AUC 1.0 on 2 of each as often as 1 in 6): "
        f"{remedy}. Nothing was trained"
    )


def _class_counts(spec: dict) -> str:
    got = [_known_label(spec, _name(e)) for e in spec.get("train", [])]
    return f"{sum(v == 1 for v in got)} tumour and {sum(v == 0 for v in got)} normal slides"


def folds_that_work(spec: dict, k: int, seed: int, least: int, fitting: int) -> tuple[int, float] | None:
    """``(K', fraction)``: the fold count nearest ``k`` (more folds first: each train side is then larger, up to one
    patient of a class a fold) into which the dataset's folded slides (``spec``: the whole ``dataset.json``, its
    ``folds`` record) would be dealt (:func:`data_tools.datasets.split.kfold_split`, the folds' seed and patient
    grouping) with a ``--val-fraction`` (the smallest, ``seed``) that works on every fold
    (:func:`working_fraction`); None when no fold count does."""
    from data_tools.datasets.split import kfold_split, patient_groups
    from data_tools.errors import HistojaxDataError

    folds = spec.get("folds") or {}
    pool = [_name(e) for lst in folds.get("lists") or [] for e in lst]
    labels = {n: _known_label(spec, n) for n in pool}
    if not pool or None in labels.values():
        return None
    groups = patient_groups(pool, spec.get("patients") if isinstance(spec.get("patients"), dict) else None)[0]
    entry = {_name(e): e for lst in folds["lists"] for e in lst}
    most = min(len({groups[n] for n in pool if labels[n] == c}) for c in (0, 1))  # patients of the rarer class
    for kk in [*range(k + 1, most + 1), *range(k - 1, 1, -1)]:
        try:
            fold = kfold_split(pool, labels, kk, int(folds.get("seed", 0)), groups)
        except HistojaxDataError:
            continue
        sides = [{**spec, "train": [entry[n] for n in pool if fold[n] != i]} for i in range(kk)]
        if (f := working_fraction(sides, seed, least, fitting)) is not None:
            return kk, f
    return None


def check_all_folds(
    dataset, fraction: float, seed: int, least: int = MIN_VALIDATION_PER_CLASS, fitting: int = 0
) -> None:
    """Refuse, before any fold is trained, an ``--all-folds`` fit one of whose folds the validation share
    (``fraction``, ``seed``) leaves with fewer than ``least`` validation or ``fitting`` fitting slides of a class:
    ``ValueError`` in one line naming ``DATASET/dataset.json``, the first fold that fails and its counts, and the
    smallest ``--val-fraction`` that works on every fold, or (none does) the most ``--folds K`` that would work,
    or that none does. A dataset whose labels ``dataset.json`` does not give is left to each fold's checks."""
    from data_tools.datasets.index import read_dataset_json
    from histojax.datasets import with_fold

    where = Path(dataset) / "dataset.json"
    spec = read_dataset_json(dataset)
    k = len(spec["folds"]["lists"])
    sides = [with_fold(spec, i, where) for i in range(k)]
    bad = [
        (i, c)
        for i, side in enumerate(sides)
        if not share_works(c := share_counts(side, fraction, seed), least, fitting)
    ]
    if not bad:
        return
    i, counts = bad[0]
    others = f"; fold(s) {', '.join(str(j) for j, _ in bad[1:])} too" if bad[1:] else ""
    needs = f"{least} validation" + (f" and {fitting} fitting" if fitting else "") + " slides of each class"
    if (works := working_fraction(sides, seed, least, fitting)) is not None:
        remedy = f"--val-fraction {works:.2f} works on every fold"
    else:
        never = next((j for j, side in enumerate(sides) if working_fraction([side], seed, least, fitting) is None), i)
        remedy = (
            f"no --val-fraction works on every fold (fold {never}'s train side holds {_class_counts(sides[never])}, "
            f"and a fit needs {least + fitting} of each class there); "
            + (
                f"build the dataset with --folds {kf[0]} (--val-fraction {kf[1]:.2f} then works on every fold: "
                f"each fold's train side holds {kf[0] - 1}/{kf[0]} of the slides, its held-out side 1/{kf[0]})"
                if (kf := folds_that_work(spec, k, seed, least, fitting)) is not None
                else "no fold count works either: "
                + (
                    f"fit one head on the train split (drop --all-folds; --val-fraction {tf:.2f} works there)"
                    if (tf := working_fraction([spec], seed, least, fitting)) is not None
                    else "nor does the train split: add slides"
                )
            )
        )
    raise ValueError(
        f"{where}: --all-folds: the validation share ({fraction:g} of fold {i}'s train side{others}) gives "
        f"{_counts_text(counts)}; a fit needs {needs}: {remedy}. Nothing was trained"
    )


def write_validation_dataset(dataset, fraction: float, seed: int, out) -> Path:
    """Write ``OUT/dataset.json``: the original's entries with ``"train"`` = the kept training slides,
    ``"test"`` = the validation slides (absolute bundle paths) and a ``"validation"`` record (source
    dataset, fraction, seed, the two lists). Returns ``OUT``; rewriting the same split is a no-op."""
    dataset, out = Path(dataset).resolve(), Path(out)
    spec = json.loads((dataset / "dataset.json").read_text())
    kept, val = split_train(spec, fraction, seed)
    derived = {
        **spec,
        "train": [str(dataset / t) for t in kept],
        "test": [str(dataset / t) for t in val],
        "validation": {"source": str(dataset), "fraction": fraction, "seed": seed, "train": kept, "validation": val},
    }
    if isinstance(spec.get("labels"), dict):  # keyed by bundle path or name: keep the names working
        derived["labels"] = {_name(k): v for k, v in spec["labels"].items()}
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(derived, indent=1, allow_nan=False)
    index = out / "dataset.json"
    if not index.is_file() or index.read_text() != text:
        outputs.write_text(index, text)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--fraction", type=float, default=0.2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    try:
        out = write_validation_dataset(args.dataset, args.fraction, args.seed, args.out)
    except (OSError, ValueError) as e:
        raise SystemExit(f"validation split: {e}") from None
    v = json.loads((out / "dataset.json").read_text())["validation"]
    print(f"wrote {out}/dataset.json: {len(v['train'])} training slides, {len(v['validation'])} validation slides")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
