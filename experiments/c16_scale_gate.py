"""The v3 gate: do the same CAMELYON16 slides read at PCam's own scale (downsample 4, 0.97 µm/px, ``pcam-cnn96``)
diagnose better than at the v1/v2 scale (downsample 8, 1.94 µm/px, ``pcam-cnn``)?

Give two ``data_tools c16`` datasets of the **same slides** (e.g. the 52 validation slides), each built with
``--folds K``. For each scale, every slide is scored reading everything by

* ``encoder top1`` / ``encoder top3``: the encoder's own view logit (feature entry 62 of both encoders), its largest
  value / the mean of its 3 largest over the slide's tissue views — nothing fitted;
* ``logit head``: :mod:`baselines.reading.head_fit` fitted per fold on the other ``K - 1`` folds (one fit per
  validation-split seed);
* ``learned head``: :mod:`baselines.reading.learned_head_fit` per fold (one fit per training seed),

a slide only ever by the heads of its own fold, which never fitted or validated on it (checked through
:func:`baselines.reading.provenance.check_scored`). Per method and scale: the AUC over the pooled slides (mean ± std
over seeds) with its 95 % interval over slides, and per lesion class the tumour slides above every normal slide
(mean over seeds); per method, the paired difference (downsample 4 − downsample 8) with a 95 % interval from a
bootstrap of slides (stratified by class, the same resample at both scales).

The rule it reports is on the ceiling, the best head at each scale: the native scale goes ahead if its best head's
mean AUC is ≥ 0.03 above the best head's at downsample 8, or its best head finds ≥ 2 more micrometastases above every
normal slide; otherwise v1/v2 stay the benchmark. Each head's own lift is printed beside it (a weak head catching
up with the other is not a higher ceiling). Also printed: each scale's median and highest normal-slide score and
median tumour-slide score of the encoder's top-1 view logit (how the maxima move with 4× as many views).

    python -m experiments.c16_scale_gate --coarse runs/gate/val52-d8 --native runs/gate/val52-d4 \\
        --heads runs/gate/heads --seeds 3 --json runs/gate/gate.json --plot runs/gate/gate.png

Heads already in ``--heads`` (a ``config.json``) are kept: a rerun resumes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from baselines.folds import dataset_folds
from data_tools.errors import HistojaxDataError
from data_tools.metrics import auc_over_runs, format_auc_runs, json_safe, roc_auc

AUC_LIFT = 0.03  # the gate's AUC rule
MICRO_LIFT = 2  # the gate's micrometastasis rule
CLASSES = ("ITC", "micro", "macro")


def fit_heads(dataset: Path, heads: Path, seeds: int, val_fraction: float, log) -> dict[str, list[Path]]:
    """Fit (or keep) the logit heads ``heads/logit-s{seed}/fold{i}`` and learned heads ``heads/learned-s{seed}/fold{i}``
    of every fold; returns ``{"logit head": [seed folders], "learned head": [seed folders]}``."""
    py = sys.executable
    k, _ = dataset_folds(dataset, "the scale gate")
    out = {"logit head": [], "learned head": []}
    for s in range(seeds):
        logit = heads / f"logit-s{s}"
        for i in range(k):
            if not (logit / f"fold{i}" / "config.json").exists():
                cmd = [py, "-m", "baselines.reading.head_fit", "--dataset", str(dataset), "--out",
                       str(logit / f"fold{i}"), "--fold", str(i), "--seed", str(s),
                       "--val-fraction", str(val_fraction)]  # fmt: skip
                run(cmd, log)
        out["logit head"].append(logit)
        learned = heads / f"learned-s{s}"
        if not all((learned / f"fold{i}" / "config.json").exists() for i in range(k)):
            cmd = [py, "-m", "baselines.reading.learned_head_fit", "--dataset", str(dataset), "--out", str(learned),
                   "--all-folds", "--seed", str(s), "--val-fraction", str(val_fraction), "--quiet"]  # fmt: skip
            run(cmd, log)
        out["learned head"].append(learned)
    return out


def run(cmd: list[str], log) -> None:
    """Run one fit, its output appended to ``log``; ``RuntimeError`` with its last line when it fails."""
    print("$ " + " ".join(cmd), file=log, flush=True)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, stdout=log, stderr=subprocess.PIPE, text=True)
    log.write(done.stderr[-4000:])
    print(f"# {time.perf_counter() - t0:.0f} s, rc {done.returncode}", file=log, flush=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"{' '.join(cmd[2:4])} failed: {last}")


def head_logits(dataset: Path, seed_folder: Path) -> dict[str, float]:
    """``{slide name: logit}`` of every slide of ``dataset``'s folds, each read everything (its tissue views) by the
    head of its own fold ``seed_folder/fold{i}``, refused if that head saw it."""
    from baselines.reading.provenance import check_scored
    from baselines.reading.reader_scores import head_scores, load_split
    from histojax.datasets import with_fold
    from histojax.reading import heads

    k, side = dataset_folds(dataset, "the scale gate")  # side: where fold i's held-out slides are
    spec = json.loads((dataset / "dataset.json").read_text())
    out = {}
    for i in range(k):
        folder = seed_folder / f"fold{i}"
        head = heads.load(folder)
        check_scored(head, folder, dataset, with_fold(spec, i)[side])
        head, _, slides = load_split(dataset, head, side, fold=i)
        scores = head_scores(head, slides, [s["tissue"] for s in slides])
        out.update({s["name"]: float(v) for s, v in zip(slides, scores)})
    return out


def encoder_logits(dataset: Path, tops=(1, 3)) -> tuple[dict[int, dict[str, float]], dict[str, int], dict[str, str]]:
    """``({top: {slide: mean of its ``top`` largest view logits}}, {slide: label}, {slide: lesion class})`` over
    every slide of ``dataset``'s folds, each slide read once (the encoder's own logit, nothing fitted)."""
    from baselines.reading.learned_head_fit import lesion_classes
    from baselines.reading.slides import load_slide

    spec = json.loads((dataset / "dataset.json").read_text())
    names = [n for lst in spec["folds"]["lists"] for n in lst]
    slides = [load_slide(dataset / n, spec["labels"][Path(n).name]) for n in names]
    ranked = {s["name"]: np.sort(s["logits"][s["tissue"]])[::-1] for s in slides}
    scores = {top: {n: float(v[:top].mean()) for n, v in ranked.items()} for top in tops}
    labels = {s["name"]: int(s["label"]) for s in slides}
    classes = dict(zip((s["name"] for s in slides), lesion_classes(slides)))
    return scores, labels, classes


def found(scores: np.ndarray, classes: list[str]) -> dict[str, int]:
    """Per lesion class of :data:`CLASSES` (0 where absent), the tumour slides scoring above every normal slide
    (``scores (B,)``; :func:`baselines.reading.learned_head_fit.found_counts`)."""
    from baselines.reading.learned_head_fit import found_counts

    counts = found_counts(scores, classes)
    return {c: counts.get(c, 0) for c in CLASSES}


def paired_difference(a: np.ndarray, b: np.ndarray, y: np.ndarray, reps: int = 2000, seed: int = 0) -> dict:
    """Mean over seeds of AUC(``b``) − AUC(``a``) for per-seed scores ``a, b (S, B)`` of the same ``B`` slides,
    with a 95 % interval from ``reps`` bootstrap resamples of slides (stratified by label ``y (B,)``, the same slides
    for both)."""
    rng = np.random.default_rng(seed)
    pos, neg = np.flatnonzero(y == 1), np.flatnonzero(y == 0)

    def diff(idx):
        return float(np.mean([roc_auc(b[s][idx], y[idx]) - roc_auc(a[s][idx], y[idx]) for s in range(len(a))]))

    boots = [diff(np.concatenate([rng.choice(pos, len(pos)), rng.choice(neg, len(neg))])) for _ in range(reps)]
    lo, hi = np.percentile(boots, [2.5, 97.5])
    return {"diff": diff(np.arange(len(y))), "low": float(lo), "high": float(hi)}


def ceiling_rule(methods: dict) -> tuple[dict, float, float, bool]:
    """The gate's rule on ``methods`` (``{method: {"coarse" | "native": {"auc", "found_mean": {"micro", ...}}}}``;
    the heads are the methods named ``... head``): ``(ceiling, AUC lift, micrometastasis lift, go)``, where
    ``ceiling[scale]`` is the best head's name, mean AUC and the most micrometastases a head finds at that scale,
    and ``go`` says the native scale's ceiling is ≥ :data:`AUC_LIFT` higher in AUC or finds ≥ :data:`MICRO_LIFT`
    more micrometastases."""
    heads = [m for m in methods if m.endswith("head")]
    ceiling = {
        key: {
            "head": max(heads, key=lambda m: methods[m][key]["auc"]),
            "auc": max(methods[m][key]["auc"] for m in heads),
            "micro": max(methods[m][key]["found_mean"]["micro"] for m in heads),
        }
        for key in ("coarse", "native")
    }
    lift_auc = ceiling["native"]["auc"] - ceiling["coarse"]["auc"]
    lift_micro = ceiling["native"]["micro"] - ceiling["coarse"]["micro"]
    return ceiling, lift_auc, lift_micro, bool(lift_auc >= AUC_LIFT or lift_micro >= MICRO_LIFT)


def plot_scales(result: dict, names: list[str], classes: list[str], path: Path) -> None:
    """A PNG of every slide's score at both scales, one panel per method (the mean over its fits): downsample 8 across,
    downsample 4 up, normal slides grey, micrometastases orange, macrometastases red; the dashed lines are each
    scale's highest normal slide, so a tumour slide above and right of both is found at both."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    colours = {"normal": "0.6", "ITC": "tab:purple", "micro": "tab:orange", "macro": "tab:red"}
    methods = list(result["methods"])
    fig = Figure(figsize=(3.2 * len(methods), 3.4))
    FigureCanvasAgg(fig)
    for i, m in enumerate(methods):
        ax = fig.add_subplot(1, len(methods), i + 1)
        xy = {
            k: np.asarray([np.mean(result["methods"][m][k]["scores"][n]) for n in names]) for k in ("coarse", "native")
        }
        for c in colours:
            sel = np.asarray([k == c for k in classes])
            if sel.any():
                ax.scatter(xy["coarse"][sel], xy["native"][sel], s=14, c=colours[c], label=c)
        normal = np.asarray([k == "normal" for k in classes])
        ax.axvline(xy["coarse"][normal].max(), ls="--", lw=0.8, c="0.3")
        ax.axhline(xy["native"][normal].max(), ls="--", lw=0.8, c="0.3")
        ax.set_title(m, fontsize=9)
        ax.set_xlabel("downsample 8, pcam-cnn", fontsize=8)
        if i == 0:
            ax.set_ylabel("downsample 4, pcam-cnn96", fontsize=8)
            ax.legend(fontsize=7, loc="upper left")
        ax.tick_params(labelsize=7)
    fig.suptitle(f"{len(names)} C16 validation slides read everything: each slide's score at both scales", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--coarse", type=Path, required=True, help="the slides at downsample 8 with pcam-cnn (--folds K)")
    p.add_argument("--native", type=Path, required=True, help="the same slides at downsample 4 with pcam-cnn96")
    p.add_argument("--heads", type=Path, required=True, help="folder for the fitted heads (kept; a rerun resumes)")
    p.add_argument("--seeds", type=int, default=3, help="fits per head and fold (default 3)")
    p.add_argument("--val-fraction", type=float, default=0.25, help="share of a fold's train side held to choose")
    p.add_argument("--json", type=Path, help="write every figure here")
    p.add_argument("--plot", type=Path, help="write a PNG of every slide's score at both scales here")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    scales = {"coarse": args.coarse, "native": args.native}
    per = {}
    try:
        for key, ds in scales.items():
            args.heads.mkdir(parents=True, exist_ok=True)
            with open(args.heads / f"fits-{key}.log", "a") as log:
                fitted = fit_heads(ds, args.heads / key, args.seeds, args.val_fraction, log)
            enc, labels, classes = encoder_logits(ds, (1, 3))
            methods = {"encoder top1": [enc[1]], "encoder top3": [enc[3]]}
            for name, folders in fitted.items():
                methods[name] = [head_logits(ds, f) for f in folders]
            per[key] = {
                "labels": labels,
                "classes": classes,
                "methods": methods,
                "folds": dataset_folds(ds, "the scale gate")[0],
            }
    except (HistojaxDataError, RuntimeError, OSError, ValueError, KeyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    names = sorted(per["coarse"]["labels"])
    if sorted(per["native"]["labels"]) != names:
        print("error: the two datasets do not hold the same slides", file=sys.stderr)
        return 2
    y = np.asarray([per["coarse"]["labels"][n] for n in names])
    classes = [per["coarse"]["classes"][n] for n in names]
    counts = {c: classes.count(c) for c in CLASSES}
    result = {"slides": len(names), "tumour": int(y.sum()), "normal": int(len(y) - y.sum()), "classes": counts,
              "folds": per["coarse"]["folds"], "seeds": args.seeds, "lesion_class": dict(zip(names, classes)),
              "methods": {}}  # fmt: skip
    print(f"{len(names)} slides ({int(y.sum())} tumour: {counts}; {int(len(y) - y.sum())} normal), "
          f"{per['coarse']['folds']} folds, reading everything")  # fmt: skip
    print("| method | downsample 8, pcam-cnn | downsample 4, pcam-cnn96 | difference [95 % bootstrap] | "
          "micro found (8 → 4) | macro | ITC |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for m in per["coarse"]["methods"]:
        row = {}
        arrays = {}
        for key in scales:
            runs = np.asarray([[r[n] for n in names] for r in per[key]["methods"][m]])
            arrays[key] = runs
            auc = auc_over_runs(runs, y)
            f = [found(r, classes) for r in runs]
            row[key] = {**auc, "found_mean": {c: float(np.mean([x[c] for x in f])) for c in CLASSES},
                        "found_per_run": f, "scores": {n: runs[:, j].tolist() for j, n in enumerate(names)}}  # fmt: skip
        d = paired_difference(arrays["coarse"], arrays["native"], y)
        row["difference"] = d
        result["methods"][m] = row
        fc, fn = row["coarse"]["found_mean"], row["native"]["found_mean"]
        cells = [format_auc_runs(row[k]["auc"], row[k]["auc_std"], row[k]["auc_low"], row[k]["auc_high"],
                                 len(arrays[k])) for k in scales]  # fmt: skip
        print(f"| {m} | {cells[0]} | {cells[1]} | {d['diff']:+.3f} [{d['low']:+.3f}, {d['high']:+.3f}] | "
              f"{fc['micro']:.1f} → {fn['micro']:.1f} of {counts['micro']} | {fc['macro']:.1f} → {fn['macro']:.1f} "
              f"of {counts['macro']} | {fc['ITC']:.1f} → {fn['ITC']:.1f} of {counts['ITC']} |")  # fmt: skip
    ceiling, lift_auc, lift_micro, go = ceiling_rule(result["methods"])
    result.update(ceiling=ceiling, ceiling_auc_lift=lift_auc, ceiling_micro_lift=lift_micro, go=go)
    for key, words in (("coarse", "downsample 8"), ("native", "downsample 4")):
        top1 = per[key]["methods"]["encoder top1"][0]
        normal = [top1[n] for n in names if per[key]["labels"][n] == 0]
        tumour = [top1[n] for n in names if per[key]["labels"][n] == 1]
        result[f"encoder_top1_{key}"] = {"normal_median": float(np.median(normal)), "normal_max": float(max(normal)),
                                         "tumour_median": float(np.median(tumour))}  # fmt: skip
        print(f"{words}: the best head is the {ceiling[key]['head']} (AUC {ceiling[key]['auc']:.3f}, "
              f"{ceiling[key]['micro']:.1f} of {counts['micro']} micrometastases); encoder top-1 view logit: normal "
              f"slides median {np.median(normal):.2f}, highest {max(normal):.2f}; tumour slides median "
              f"{np.median(tumour):.2f}")  # fmt: skip
    result["seconds"] = round(time.perf_counter() - t0, 1)
    print(
        f"\ngate: {'PASSED' if go else 'NOT PASSED'}: the best head's AUC {lift_auc:+.3f} (rule: >= +{AUC_LIFT}), its "
        f"micrometastases found {lift_micro:+.1f} (rule: >= +{MICRO_LIFT}); {result['seconds']:.0f} s"
    )
    if args.plot:
        plot_scales(result, names, classes, args.plot)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(result), indent=1, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
