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
    """The training slides (entries of ``spec["train"]``) grouped into units that stay on one side:
    a tumour slide with its tissue donor when the donor is a training slide too, else one slide."""
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


def check_validation_share(
    spec: dict, held, where, fraction: float, fold: int | None = None, least: int = MIN_VALIDATION_PER_CLASS
) -> None:
    """Refuse, before any slide is read or any training, a validation share (``held``: entries of ``spec["train"]``)
    with fewer than ``least`` slides of a class: ``ValueError`` in one line naming ``where`` (the ``dataset.json``),
    the counts and the options (``--val-fraction``, more slides, ``--folds`` with fewer folds). Labels come from
    ``dataset.json``; a share whose labels it does not give is left to the fit's own checks."""
    labels = [_known_label(spec, _name(e)) for e in held]
    if None in labels:
        return
    n_t, n_n = sum(labels), len(labels) - sum(labels)
    if min(n_t, n_n) >= least:
        return
    side = f"fold {fold}'s train side" if fold is not None else "the train split"
    raise ValueError(
        f"{where}: the validation share ({fraction:g} of {side}) holds {n_t} tumour and {n_n} normal "
        f"slides; choosing a head or checkpoint and calibrating it needs at least {least} of each (a "
        f"random head scores validation AUC 1.0 on fewer as often as 1 in 6): give a larger --val-fraction, "
        "or build the dataset with fewer --folds K (each fold's train side is larger), or add slides. "
        "Nothing was trained"
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
