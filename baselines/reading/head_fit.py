"""Fit the slide head (:mod:`histojax.reading.heads.logit`) of a dataset: ``python -m baselines.reading.head_fit --dataset DIR --out DIR``.

Candidates: neighbourhood sides ``--ks`` (default 1 2 3 4 5 views; 1 = the plain view logit), pooled by
the maximum or the mean of the 3 largest (``--minus-median``: also each minus the read views' median
logit; see :func:`candidates` for why that is off by default). Each is
calibrated (1-D logistic regression of the slide labels on its statistic, reading everything) on the
training split minus a validation share (:func:`baselines.validation.split_train`: per class, a tumour
slide with its tissue donor; ``--val-fraction`` 0.2, ``--seed`` 0) and scored by its AUC on that
validation share; the best one (ties: the higher training AUC, then the simplest, in the order listed) is re-calibrated on the
whole training split and saved to ``--out`` (``config.json`` records every candidate's validation AUC).
The test split is never read. ``config.json`` records what the head was fitted on
(:data:`baselines.reading.provenance.RECORD`: the dataset's seal, split, fold, fitting and validation slides).
**Refused** (one line naming ``dataset.json``, nothing saved): a validation share with fewer than
:data:`baselines.validation.MIN_VALIDATION_PER_CLASS` slides of a class (before any slide is read), fewer than
:data:`~baselines.reading.fitting.MIN_SLIDES_PER_CLASS` training slides of a class after the validation share, a
chosen head whose validation AUC is below 0.5 or whose calibration slope is not positive
(:func:`baselines.reading.fitting.check_head`).

**A rerun keeps the head** (:func:`baselines.reading.fitting.claim_head`, before any slide is read): ``--out``
holding a finished head of this command (``config.json``'s ``fit_options``: the dataset and its seal, ``--fold`` and
the fit's options) fits nothing, in one line; a head of other options is refused naming the first difference;
``--restart`` moves it aside to ``OUT.previous-N`` (never deleted) and fits again. A fit killed before its head was
written is fitted again from the start (a fit's progress within one fit is not kept).

The slides are read by the loaders every head-based tool shares (:mod:`baselines.reading.slides`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from baselines.reading.fitting import (
    CHANCE_FLAG,
    MIN_SLIDES_PER_CLASS,
    OPTIONS,
    add_restart,
    chance_warning,
    check_classes,
    check_head,
    claim_head,
    fit_options,
    logistic_fit,
)
from baselines.reading.slides import HeadDataError, load_slides, padded, read_spec, spec_label, warn_scale
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn
from data_tools.metrics import auc_interval, format_auc, json_number, json_safe, roc_auc, small_split_warning

TOPS = (1, 3)


def statistics(
    head, slides: list[dict], masks: list[np.ndarray] | None = None, shape: tuple[int, int] | None = None
) -> np.ndarray:
    """The head's pooled statistic ``(B,)`` of each slide over ``masks`` (default its tissue views)."""
    from histojax.reading.heads.logit import statistic_batch

    masks = [s["tissue"] for s in slides] if masks is None else masks
    return np.asarray(
        statistic_batch(head, padded([s["logits"] for s in slides], 0.0, shape), padded(list(masks), False, shape))
    )


def grid_shape(slides: list[dict]) -> tuple[int, int]:
    """The largest finest grid ``(H, W)`` of ``slides``."""
    return max(s["logits"].shape[0] for s in slides), max(s["logits"].shape[1] for s in slides)


def candidates(
    ks=(1, 2, 3, 4, 5), dim: int = pcam_cnn.VIEW_LOGIT, encoder: str | None = pcam_cnn.NAME, minus_median: bool = False
) -> list:
    """The candidate heads (uncalibrated), simplest first: for each ``k``, top-1 then top-3 (each also with the
    read views' median subtracted when ``minus_median``: off by default, because the median of what was read
    depends on where a reader looked — a reader that reads only hot cells has a hot median — so such a head
    scores a good reader's reads lower than a random reader's)."""
    from histojax.reading.heads.logit import LogitHead

    return [
        LogitHead(dim=dim, k=int(k), top=t, minus_median=m, encoder=encoder)
        for k in ks
        for t in TOPS
        for m in ((False, True) if minus_median else (False,))
    ]


def calibrated(head, slides: list[dict], shape: tuple[int, int] | None = None):
    """``head`` with its calibration ``(cal_a, cal_b)`` fitted on ``slides`` (reading everything) and the prior log odds."""
    import jax.numpy as jnp

    labels = np.asarray([s["label"] for s in slides])
    a, b = logistic_fit(statistics(head, slides, shape=shape), labels)
    p = np.clip(labels.mean(), 1e-3, 1 - 1e-3)
    return head.replace(cal_a=jnp.float32(a), cal_b=jnp.float32(b), prior_logit=jnp.float32(np.log(p / (1 - p))))


def choose(train: list[dict], val: list[dict], cands) -> tuple[object, list[dict]]:
    """Calibrate each candidate on ``train``, score it on ``val``; returns the best (highest validation AUC,
    ties to the higher training AUC, then to the earliest) and the table ``[{name, k, top, minus_median, train_auc, validation_auc}]``."""
    y_tr, y_va = [s["label"] for s in train], [s["label"] for s in val]
    shape = grid_shape(train + val)
    table, best, best_key = [], None, (-1.0, -1.0)
    for c in cands:
        h = calibrated(c, train, shape)
        auc_va = round(roc_auc(statistics(h, val, shape=shape), y_va), 4)
        auc_tr = round(roc_auc(statistics(h, train, shape=shape), y_tr), 4)
        low, high = auc_interval(auc_va, int(np.sum(y_va)), len(y_va) - int(np.sum(y_va)))
        table.append(
            {
                "name": c.name,
                "k": c.k,
                "top": c.top,
                "minus_median": c.minus_median,
                "train_auc": auc_tr,
                "validation_auc": auc_va,
                "validation_auc_low": json_number(low),
                "validation_auc_high": json_number(high),
            }
        )
        if (auc_va, auc_tr) > best_key:
            best, best_key = c, (auc_va, auc_tr)
    if best is None:
        raise ValueError(
            f"the validation share ({len(val)} slides, labels {sorted(set(y_va))}) needs tumour and "
            "normal slides to choose a head: use a larger --val-fraction or another --seed"
        )
    return best, table


def fit(
    dataset,
    out=None,
    val_fraction: float = 0.2,
    seed: int = 0,
    ks=(1, 2, 3, 4, 5),
    dim: int = pcam_cnn.VIEW_LOGIT,
    progress: bool = False,
    minus_median: bool = False,
    fold: int | None = None,
    options: dict | None = None,
):
    """Choose and fit the head of ``dataset`` (see the module doc); saved to ``out`` when given. ``fold=i``: on
    fold i's train side (the other folds) of a dataset built with ``--folds K``. ``options``: the command's
    (:func:`command_options`), recorded in ``config.json`` so that its rerun keeps the head.
    Returns ``(head, table of candidates)``."""
    import datetime

    import jax

    from baselines.reading.provenance import RECORD, fit_record
    from baselines.validation import check_validation_share, split_train
    from histojax.reading.heads.files import check_writable

    if out is not None:
        check_writable(out)  # a folder that cannot be written: refused before any slide is read
    spec = read_spec(dataset, fold)
    warn_scale(dataset, spec)  # the encoder-scale warning dataset.json records, repeated
    classes = {spec_label(spec, Path(e).name) for e in spec["train"]}
    if len(classes) == 1 and None not in classes:  # labels from dataset.json: one class, refused before loading
        kind = "tumour" if classes.pop() else "normal"
        where = f"fold {fold}'s train side" if fold is not None else "the train split"
        raise HeadDataError(
            Path(dataset) / "dataset.json",
            f"{where} holds only {kind} slides ({len(spec['train'])}): "
            "a head is fitted on tumour and normal slides; give a "
            "dataset whose training slides hold both",
        )
    kept, held = split_train(spec, val_fraction, seed)
    check_validation_share(
        spec, held, Path(dataset) / "dataset.json", val_fraction, fold, seed=seed, fitting=MIN_SLIDES_PER_CLASS
    )  # before any slide is read
    train = load_slides(dataset, spec["train"], spec, dim, progress=progress)
    by_name = {s["name"]: s for s in train}
    tr = [by_name[Path(n).name] for n in kept]
    va = [by_name[Path(n).name] for n in held]
    check_classes(dataset, tr)
    encoders = {s["encoder"] for s in train}
    encoder = encoders.pop() if len(encoders) == 1 else None
    best, table = choose(tr, va, candidates(ks, dim, encoder, minus_median))
    head = calibrated(best, train, grid_shape(train))
    chosen = next(r for r in table if r["name"] == best.name)
    check_head(dataset, chosen["validation_auc"], float(head.cal_a))
    n_tumour = int(sum(s["label"] for s in va))
    if (
        warning := small_split_warning(
            n_tumour, len(va) - n_tumour, "the validation share" + (f" of fold {fold}" if fold is not None else "")
        )
    ) is not None:
        print(warning, file=sys.stderr)  # the candidate was chosen on it (after the refusals: those stay one line)
    low, high = auc_interval(chosen["validation_auc"], n_tumour, len(va) - n_tumour)
    share = "the validation share" + (f" of fold {fold}" if fold is not None else "")
    if (chance := chance_warning(chosen["validation_auc"], low, high, share)) is not None:
        print(chance, file=sys.stderr)
    info = {
        "fitted_on": {
            "dataset": str(Path(dataset).resolve()),
            "split": "train",
            "slides": len(train),
            "tumour_slides": int(sum(s["label"] for s in train)),
            **({"fold": fold} if fold is not None else {}),
        },
        "chosen_on": {
            "validation_fraction": val_fraction,
            "seed": seed,
            "train_slides": len(tr),
            "validation_slides": len(va),
            "validation_auc": chosen["validation_auc"],
            **({CHANCE_FLAG: True} if chance is not None else {}),
        },
        # re-calibrated on the whole train side: every train slide is a fitting slide, the share validated too
        RECORD: fit_record(dataset, spec, fold, spec["train"], held),
        "candidates": table,
        **({OPTIONS: options} if options is not None else {}),
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
    }
    head = head.replace(info=json.dumps(json_safe(info), allow_nan=False))
    if out is not None:
        head.save(out)
    return head, table


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.head_fit``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json with a train split; feature grids)")
    p.add_argument("--out", required=True, help="folder to save the head in (config.json, params.json)")
    p.add_argument(
        "--val-fraction",
        type=float,
        default=0.2,
        help="share of training slides held back to choose among the candidates (default 0.2)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the validation split (default 0)")
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: fit on fold I's train side (the other K - 1 folds)",
    )
    p.add_argument("--ks", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="neighbourhood sides to try (views)")
    p.add_argument(
        "--minus-median",
        action="store_true",
        help="also try each candidate minus the read views' median logit (off by default: it depends on "
        "where a reader looked)",
    )
    p.add_argument(
        "--dim",
        type=int,
        default=pcam_cnn.VIEW_LOGIT,
        help=f"feature entry holding the view tumour logit (default {pcam_cnn.VIEW_LOGIT}: pcam-cnn's)",
    )
    add_restart(p)


def command_options(args) -> dict:
    """What the command fits (:func:`baselines.reading.fitting.fit_options`): compared with a finished head's."""
    return fit_options(
        args.dataset,
        args.fold,
        **{
            "--val-fraction": args.val_fraction,
            "--seed": args.seed,
            "--ks": list(args.ks),
            "--minus-median": bool(args.minus_median),
            "--dim": args.dim,
        },
    )


def run(args, parser=None) -> int:
    """Fit, save and print the candidates' table; a finished head of this command in ``--out``: nothing to fit
    (:func:`baselines.reading.fitting.claim_head`)."""
    if any(k < 1 for k in args.ks):
        return print_error(f"--ks: neighbourhood sides must be ≥ 1, got {args.ks}")
    from histojax.reading.heads.logit import KIND as LOGIT_KIND

    t0 = time.perf_counter()
    try:
        options = command_options(args)
        if claim_head(args.out, LOGIT_KIND, options, getattr(args, "restart", False)) == "done":
            return 0
        head, table = fit(
            args.dataset,
            args.out,
            args.val_fraction,
            args.seed,
            args.ks,
            args.dim,
            progress=True,
            minus_median=args.minus_median,
            fold=args.fold,
            options=options,
        )
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    print("| candidate | train AUC | validation AUC [95 % interval over the validation slides] |\n|---|---|---|")
    for r in table:
        low, high = (
            float("nan") if v is None else v for v in (r.get("validation_auc_low"), r.get("validation_auc_high"))
        )
        print(f"| {r['name']} | {r['train_auc']:.3f} | {format_auc(r['validation_auc'], low, high)} |")
    print(
        f"chosen: {head.name} (slide logit = {float(head.cal_a):.3f} · s + {float(head.cal_b):.3f}); saved to {args.out} "
        f"in {time.perf_counter() - t0:.0f} s"
    )
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.head_fit", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
