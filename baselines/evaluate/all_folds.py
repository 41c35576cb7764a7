"""``histojax evaluate --all-folds``: the one-fold evaluation (``--fold I``) on every fold I = 0 … K − 1 of a
dataset built with ``--folds K``, each in ``OUT/foldI`` as ``--fold I --out OUT/foldI`` writes it, and each
figure's mean ± std over the folds in ``OUT/eval.json`` and ``OUT/eval.csv`` (:func:`run_all_folds`)."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from baselines import outputs
from baselines.folds import SUMMARY, dataset_folds, mean_std, with_fold
from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError
from data_tools.metrics import auc_interval

FIGURES = (
    "success_rate",
    "mean_return",
    "mean_length",
    "mean_steps_to_success",
    "mean_fraction_read",
    "mean_fields_of_view",
    "diagnosis_auc",
    "diagnosis_auc_no_itc",
)
"""The figures of an evaluation row summarised over folds (each as its mean and ``<figure>_std``)."""
INTERVAL = ("diagnosis_auc_low", "diagnosis_auc_high")
"""The AUC's 95 % interval over slides: each fold's own, and for the mean that over the pooled held-out slides."""


def fold_dataset(args) -> str:
    """The dataset whose folds ``--all-folds`` scores: ``--dataset``, else the one fold 0's checkpoint trained on
    (its ``config.json``). ``HistojaxDataError`` (one line) when there is none."""
    if args.dataset is not None:
        return str(args.dataset)
    if args.checkpoint is not None:
        run = Path(with_fold(args.checkpoint, 0))
        run = run if run.is_dir() else run.parent
        try:
            recorded = (read_run_config(run / "config.json").env_kwargs or {}).get("dataset")
        except HistojaxDataError:  # unreadable or not a config: the one-fold run names it
            recorded = None
        if isinstance(recorded, str):
            return recorded
    raise HistojaxDataError(
        None,
        "--all-folds: give --dataset DIR, a dataset built with `histojax dataset ... "
        "--folds K` (the checkpoint records none)",
    )


def summarise_folds(per_fold: list[dict]) -> dict:
    """``{policy: {figure: mean, figure_std: std, "episodes": total, "folds": n}}`` over ``per_fold`` (one
    ``{policy: row}`` per fold, rows as ``eval.json`` holds them: an undefined figure is None); the mean and std
    (``ddof=0``) are over the folds that define the figure, ``folds`` the folds that scored the policy;
    ``diagnosis_auc_low`` / ``_high``: the 95 % interval of the mean AUC over the pooled held-out slides of all folds
    (each slide once), when every fold records its slide counts."""
    out: dict = {}
    for policy in dict.fromkeys(p for rows in per_fold for p in rows):
        rows = [r[policy] for r in per_fold if policy in r]
        summary = {"episodes": sum(int(r.get("episodes", 0)) for r in rows), "folds": len(rows)}
        for figure in FIGURES:
            if any(figure in r for r in rows):
                summary[figure], summary[f"{figure}_std"] = mean_std([r.get(figure) for r in rows])
        counts = [(r.get("diagnosis_tumour_slides"), r.get("diagnosis_normal_slides")) for r in rows]
        if summary.get("diagnosis_auc") is not None and counts and all(a and b for a, b in counts):
            # the interval of the mean over the held-out slides of all folds pooled, each slide once
            summary["diagnosis_tumour_slides"] = sum(a for a, _ in counts)
            summary["diagnosis_normal_slides"] = sum(b for _, b in counts)
            summary["diagnosis_auc_low"], summary["diagnosis_auc_high"] = auc_interval(
                summary["diagnosis_auc"], summary["diagnosis_tumour_slides"], summary["diagnosis_normal_slides"]
            )
        out[policy] = summary
    return out


def _number(v) -> str | float:
    return "" if v is None or v != v else v


def _finite(value):
    """``value`` with NaN floats (a figure no fold defines) as None: valid JSON (``null``)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return None if isinstance(value, float) and value != value else value


def _seen_words(seen: dict | None) -> str:
    """``eval.csv``'s ``scored_on_seen_slides`` cell of a fold: ``"policy: A B; head: C"``, or ``""``."""
    return "; ".join(f"{who}: {' '.join(names)}" for who, names in (seen or {}).items())


def trained_fold(checkpoint) -> int | None:
    """The fold whose train side ``checkpoint`` (a run folder or its ``params.msgpack``) trained on, as its
    ``config.json`` records it (``env_kwargs.fold``), or None."""
    run = Path(checkpoint)
    run = run if run.is_dir() else run.parent
    try:
        fold = (read_run_config(run / "config.json").env_kwargs or {}).get("fold")
    except HistojaxDataError:
        return None
    return fold if isinstance(fold, int) and not isinstance(fold, bool) else None


def run_all_folds(args, parser, run_one, default_out) -> int:
    """Run ``run_one`` (the one-fold ``evaluate`` command: ``run(args, parser)``) with ``--fold I`` and ``--out
    OUT/foldI`` for every fold I of the dataset (a ``CHECKPOINT`` holding ``{fold}`` is one run per fold, as the
    trainers' ``--fold I`` wrote them), then write ``OUT/eval.json`` (``per_fold``: each fold's results;
    ``summary``: :func:`summarise_folds`) and ``OUT/eval.csv`` (each fold's rows, then a ``mean`` and a ``std`` row
    per policy) and print the means ± std. ``default_out(run, env_id)``: where ``OUT`` goes without ``--out``
    (``-all-folds`` added). A dataset without folds: one line, nothing written."""
    if getattr(args, "fold", None) is not None or args.slide:
        given = f"--fold {args.fold}" if getattr(args, "fold", None) is not None else "--slides"
        raise HistojaxDataError(None, f"--all-folds scores every fold the dataset records; not with {given}")
    dataset = fold_dataset(args)
    k, side = dataset_folds(dataset)
    split = args.split or side
    first = Path(with_fold(args.checkpoint, 0)) if args.checkpoint is not None else None
    if args.out:
        out = Path(args.out)
    else:
        base = default_out(None if first is None else (first if first.is_dir() else first.parent), args.env or "folds")
        out = base.parent / f"{base.name}-all-folds"
    per_fold, records, warnings = [], [], []
    for i in range(k):
        checkpoint = None if args.checkpoint is None else with_fold(args.checkpoint, i)
        trained = None if checkpoint is None else trained_fold(checkpoint)
        if trained is not None and trained != i:
            warnings.append(
                f"{checkpoint} trained on fold {trained}'s train side, which holds fold {i}'s slides: "
                f"its fold {i} figures are not held-out; give one run per fold (CHECKPOINT with {{fold}})"
            )
            print(f"warning: {warnings[-1]}", file=sys.stderr)
        print(
            f"fold {i} of {k} (0 to {k - 1}): {checkpoint or 'reference policies'} on its {split} side",
            file=sys.stderr,
            flush=True,
        )
        one = argparse.Namespace(
            **{
                **vars(args),
                "checkpoint": checkpoint,
                "dataset": dataset,
                "split": split,
                "fold": i,
                "all_folds": False,
                "out": str(out / f"fold{i}"),
            }
        )
        code = run_one(one, parser)
        if code:
            return code
        record = json.loads((out / f"fold{i}" / "eval.json").read_text())
        rows = {policy: row for results in record["results"].values() for policy, row in results.items()}
        per_fold.append(rows)
        records.append({"fold": i, "checkpoint": checkpoint, "out": str(out / f"fold{i}"), **record})
    summary = summarise_folds(per_fold)
    # folds whose policy or head scored slides it saw (--allow-fitting-slides): the summary says so too
    seen = {str(r["fold"]): r["scored_on_seen_slides"] for r in records if r.get("scored_on_seen_slides")}
    outputs.write_text(
        out / "eval.json",
        json.dumps(
            _finite(
                {
                    "env_id": records[0]["env_id"],
                    "dataset": dataset,
                    "split": split,
                    "folds": k,
                    "summary": summary,
                    "warnings": warnings,
                    **({"self_scored": True, "scored_on_seen_slides": seen} if seen else {}),
                    "per_fold": records,
                }
            ),
            indent=2,
            allow_nan=False,
        ),
    )
    with outputs.open_text(out / "eval.csv") as f:
        w = csv.writer(f)
        w.writerow(["fold", "policy", "episodes", *FIGURES, *INTERVAL, "scored_on_seen_slides"])
        marks = {i: _seen_words(seen.get(str(i))) for i in range(k)}
        for i, rows in enumerate(per_fold):
            for policy, r in rows.items():
                w.writerow(
                    [i, policy, r.get("episodes", ""), *(_number(r.get(x)) for x in FIGURES + INTERVAL), marks[i]]
                )
        every = "; ".join(f"fold {i}: {m}" for i, m in marks.items() if m)
        for policy, s in summary.items():
            w.writerow([SUMMARY, policy, s["episodes"], *(_number(s.get(x)) for x in FIGURES + INTERVAL), every])
            w.writerow(
                ["std", policy, "", *(_number(s.get(f"{x}_std")) for x in FIGURES), *([""] * len(INTERVAL)), every]
            )
    print(f"\nmean ± std over {k} folds ({split} side of each fold of {dataset}):")
    for policy, s in summary.items():
        shown = [
            f"{x} {s[x]:.3f} ± {s[x + '_std']:.3f}"
            + (
                f" [{s['diagnosis_auc_low']:.3f}, {s['diagnosis_auc_high']:.3f}]"
                if x == "diagnosis_auc" and s.get("diagnosis_auc_low") is not None
                else ""
            )
            for x in FIGURES
            if x in s and s[x] is not None and s[x] == s[x]
        ]
        print(f"{policy:<22} " + ", ".join(shown))
    print(f"\nwrote {out}/eval.json and eval.csv (mean ± std over folds; each fold's own files in {out}/fold0 ...)")
    return 0
