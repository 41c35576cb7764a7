"""Evaluate a trained checkpoint against reference policies.

    python -m baselines.evaluate runs/ppo-easy [--env HistoJAX-Easy-v0] [--slides BUNDLE ... | held-out] [--episodes 256]

For every slide (default: the one the checkpoint was trained on) prints and writes
(``eval.json``, ``eval.csv`` in ``--out``, default ``<run>/eval``, or ``runs/eval-<name>`` for a run inside
the package such as ``baselines/published/NAME``) one row per policy:

* the checkpoint's policy, greedy (argmax / Gaussian mean) and sampled, pooled over its seeds;
* ``random`` — uniform random actions;
* ``scripted`` — coarse-to-fine using only the observation (see :func:`scripted_policy`); for a
  ``discrete:map`` navigator, the map follower (:func:`map_follower_policy`).

Columns: success rate (target reached at the finest level), mean return, mean episode length,
mean steps to success (over the successful episodes), mean fraction of the slide read and fields of
view, and for a diagnosis the AUC of the policy's tumour score.

**Readers trained with SASHA's reward** (``python -m baselines.reading.train_readers``; their run folder holds a
``head_reward.json`` naming the slide head; ``--head DIR`` names another, or scores any checkpoint's reading
through a head): the policy only chooses where to read, until it stops or its budget is spent, and the
**head declares** — it scores the finest views each episode read (:func:`head_env`), every row through
the same head; columns ``AUC`` over all slides and ``AUC w/o ITC`` without ITC-only tumour slides
(CAMELYON's lesion classes from the bundles' tumour polygons, when every tumour slide has them), success
= the head's diagnosis right, each slide read equally often. A cell-set reader (the ``-v2`` ids) runs on
slides of any size; a flat glimpse policy (``-v1``) on a slide wider or taller than its cell grid, a
retired published folder and a slide head folder are refused in one line saying what to use instead. Episodes run without auto-reset until
success or the step limit. Also writes, on each episode's own slide, ``trajectory_<policy>.png``
(histojax.render.render_trajectory), ``reading_<policy>_tumour.png`` / ``_normal.png`` (where it read,
histojax.render.render_reading_map) and ``trajectory.gif`` (histojax.render.animate) of one episode of
the first policy. Warns when the slides cannot be scored (no tumour slide; one class only for an AUC), when
the checkpoint is scored on its own training split or at another scale, and on config.json keys no
trainer writes. Refuses, in one line naming the run's ``slides_seen.json`` (or its ``config.json`` for an older run),
to score the policy on slides it trained or was validated on, and the head on slides it was fitted or validated on
(:mod:`baselines.reading.provenance`); ``--allow-fitting-slides`` scores them with a warning, and ``eval.json`` /
``eval.csv`` then say on which (``self_scored``, ``scored_on_seen_slides``)."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from baselines import outputs
from baselines.evaluate.all_folds import run_all_folds
from baselines.evaluate.checks import (
    check_config,
    check_params_tree,
    encoder_refusal,
    grid_refusal,
    head_reward_settings,
    provenance_warnings,
    published_dataset_refusal,
    refuse_not_an_agent,
    resolve_head,
    trained_record_warnings,
)
from baselines.evaluate.scoring import evaluate
from baselines.folds import scored_side
from baselines.harness.logs import load_checkpoint
from baselines.published_agents import published_or_path
from baselines.reading.provenance import (
    add_flag,
    check_policy,
    check_scored,
    head_config,
    head_for_fold,
    record_of,
    seen_slides,
)
from baselines.reading.slides import scale_warning
from baselines.run_config import read_record, read_run_config
from data_tools.cli_output import positive_int
from data_tools.errors import HistojaxDataError
from data_tools.metrics import UNDEFINED, format_auc


def _usage_exit(message: str) -> SystemExit:
    """A ``SystemExit`` with status 2 (a user error) whose text is ``message``, printed as one ``error:`` line."""
    print(f"error: {message}", file=sys.stderr)
    exit_ = SystemExit(message)
    exit_.code = 2
    return exit_


def resolve_slides(slides: list[str], config) -> list[str]:
    """Bundle paths to evaluate: ``slides`` as given, or for ``["held-out"]`` the ``"test"`` list of
    the ``dataset.json`` the checkpoint was trained on (``config.env_kwargs["dataset"]``; ``config`` typed or its
    record)."""
    if list(slides) != ["held-out"]:
        return list(slides)
    dataset = (read_run_config(config).env_kwargs or {}).get("dataset")
    if not dataset:
        raise _usage_exit(
            "--slides held-out: this checkpoint was not trained on a dataset (env_kwargs has no "
            "'dataset'); give bundle folders instead"
        )
    spec_path = Path(dataset) / "dataset.json"
    try:
        test = json.loads(spec_path.read_text())["test"]
    except (OSError, ValueError, KeyError) as e:
        raise _usage_exit(f"--slides held-out: cannot read the test split from {spec_path}: {e}") from None
    if not test:
        raise _usage_exit(f"--slides held-out: {spec_path} has an empty test split")
    return [str(Path(dataset) / rel) for rel in test]


def scored_words(kw: dict) -> str:
    """How ``evaluate`` names the side of a dataset it scores (``kw``: the env's keyword arguments):
    ``"fold I's held-out slides"`` with a fold (its test / validation side), else ``"the SPLIT split"``."""
    split, fold = kw.get("split", "train"), kw.get("fold")
    if fold is not None:
        return f"fold {fold}'s held-out slides" if split in ("test", "validation") else f"fold {fold}'s {split} side"
    return f"the {split} split"


def with_dataset(config, dataset=None, split: str | None = None, fold: int | None = None):
    """``config`` (a run's typed config, or its record: the same kind back) scoring ``split`` of ``dataset``
    (default split ``"test"``) in place of the slides it trained on; only ``split`` given: the same dataset, another
    split. ``fold``: that side of fold ``fold`` (default: its held-out side, ``make(..., fold=)``). Unchanged when
    none is given."""
    if dataset is None and split is None and fold is None:
        return config
    typed = read_run_config(config)
    kw = {k: v for k, v in (typed.env_kwargs or {}).items() if k not in ("slides", "slide_weights")}
    if dataset is not None:
        if not (Path(dataset) / "dataset.json").is_file():
            raise _usage_exit(f"--dataset {dataset}: no dataset.json there")
        kw["dataset"] = str(dataset)
    elif not kw.get("dataset"):  # none, or null (a published config.json names no path: published.json names it)
        raise _usage_exit(
            f"{'--split' if split is not None else '--fold'}: this checkpoint records no dataset it "
            "trained on; give --dataset DIR too"
        )
    if fold is not None:
        kw["fold"] = fold
    kw["split"] = split or scored_side(kw["dataset"], kw.get("fold"))
    if isinstance(config, dict):
        return {**config, "env_kwargs": kw, "slide": None}
    return typed.replace(env_kwargs=kw, slide=None)


MAX_EPISODES = 1 << 24
"""The most episodes per policy ``--episodes`` takes (16,777,216: the rollouts index episodes with int32)."""


def episode_count(text: str) -> int:
    """argparse type of ``--episodes``: a whole number from 1 to :data:`MAX_EPISODES`."""
    value = positive_int(text)
    if value > MAX_EPISODES:
        raise argparse.ArgumentTypeError(
            f"{text!r} is more than the {MAX_EPISODES:,} episodes per policy an evaluation runs"
        )
    return value


def json_safe(value):
    """``value`` (JSON-able dicts, lists, numbers) with every non-finite float (NaN: a mean over no episode, an
    undefined figure) replaced by None, so ``json.dumps(..., allow_nan=False)`` writes valid JSON (``null``)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def print_table(title: str, rows: dict, head: str | None = None) -> None:
    """The printed table: per policy episodes, success, mean return / length, steps to success, mean fraction
    of the slide read and fields of view; with a diagnosis score (``diagnosis_auc``), its AUC too, and
    without ITC-only slides (``diagnosis_auc_no_itc``) when known. ``head``: the slide head that declared
    (its name and folder), said under the table."""
    auc = any("diagnosis_auc" in r for r in rows.values())
    no_itc = any("diagnosis_auc_no_itc" in r for r in rows.values())
    print(f"\n{title}")
    print(
        f"{'policy':<22} {'episodes':>8} {'success':>8} {'mean return':>11} {'mean length':>11} {'steps to success':>16}"
        f" {'read':>6} {'fields':>6}"
        + (f" {'AUC [95 % interval]':>21}" if auc else "")
        + (f" {'AUC w/o ITC [95 %]':>21}" if no_itc else "")
    )

    def fig(v, width: int, spec: str) -> str:
        return f"{'undef.':>{width}}" if v is None else f"{v:>{width}{spec}}"

    def auc_cell(r: dict, key: str) -> str:  # "0.849 [0.741, 0.936]" (format_auc without its word)
        if key not in r:
            return f" {'-':>21}"
        if r[key] is None:
            return f" {'undef.':>21}"
        low, high = r.get(key + "_low"), r.get(key + "_high")
        if low is None or high is None:  # a record without its interval
            return f" {r[key]:>21.3f}"
        return f" {format_auc(r[key], low, high)[4:]:>21}"

    undefined = False
    for name, r in rows.items():
        cell, cell2 = auc_cell(r, "diagnosis_auc"), auc_cell(r, "diagnosis_auc_no_itc")
        undefined |= any(r.get(k, 0) is None for k in ("success_rate", "diagnosis_auc", "diagnosis_auc_no_itc"))
        print(
            f"{name:<22} {r['episodes']:>8} {fig(r['success_rate'], 8, '.1%')} {r['mean_return']:>11.3f} "
            f"{r['mean_length']:>11.1f} {fig(r['mean_steps_to_success'], 16, '.1f')} "
            f"{r['mean_fraction_read']:>6.1%} {r['mean_fields_of_view']:>6.1f}"
            + (cell if auc else "")
            + (cell2 if no_itc else "")
        )
    if undefined:
        print(f"undef.: {UNDEFINED} (the slides scored are all of one class; see the warning above)")
    if head:
        print(
            f"the head declares: the policy chooses where to read, then the slide head {head} scores the finest "
            "views read; success: the head's diagnosis at the episode's end (p(tumour) >= 0.5 read as tumour) "
            "matched the slide's label, i.e. its accuracy at 0.5, which a head calling every slide normal reaches "
            "on a split of mostly normal slides (the AUC is the figure that ranks); AUC: of the head's score over "
            "the episodes "
            "(each slide equally often)"
            + ("; AUC w/o ITC: ITC-only tumour slides left out" if no_itc else "")
            + " (read: mean fraction of the slide's tissue views read)"
        )
    elif auc:
        print(
            "success: the diagnosis declared was right; AUC: of the policy's tumour score over the slides "
            "(read: mean fraction of the slide's tissue views read)"
        )


def add_arguments(p) -> None:
    """The options of ``python -m baselines.evaluate`` and ``histojax evaluate``."""
    p.add_argument(
        "checkpoint",
        nargs="?",
        default=None,
        type=published_or_path,
        help="run folder or params.msgpack, or a published agent's name (histojax published lists them: "
        "c16-v2-set-reader); omit with --env for reference rows only",
    )
    p.add_argument("--env", default=None, help="env id (default: the checkpoint's)")
    p.add_argument(
        "--slide",
        "--slides",
        nargs="*",
        default=None,
        help="bundle folder(s) (default: the checkpoint's slide), or 'held-out': the test split of "
        "the dataset the checkpoint trained on",
    )
    p.add_argument(
        "--dataset",
        default=None,
        help="score on this dataset folder (dataset.json) instead of the one the checkpoint trained on, "
        "e.g. a published agent on any C16-style dataset",
    )
    p.add_argument(
        "--split",
        default=None,
        choices=("train", "test", "all"),
        help="split of the dataset to score (default: test with --dataset, else the checkpoint's)",
    )
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: score fold I's held-out side (make(..., fold=I))",
    )
    p.add_argument(
        "--all-folds",
        action="store_true",
        help="a dataset built with --folds K: evaluate every fold I = 0 ... K-1 (as --fold I, in "
        "OUT/foldI) and report each figure's mean ± std over the folds (OUT/eval.json, eval.csv); a "
        "CHECKPOINT holding {fold} (runs/ppo-fold{fold}) is the run trained on each fold",
    )
    p.add_argument(
        "--episodes",
        type=episode_count,
        default=256,
        help=f"episodes per policy (per seed for the learned one), 1 to {MAX_EPISODES:,}",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-position", action="store_true", help="(reference rows only) observation with position")
    p.add_argument("--action-mode", default="discrete", help="(reference rows only)")
    p.add_argument(
        "--out",
        default=None,
        help="output folder (default <run>/eval, or runs/eval-<run name> for a run inside the installed "
        "package such as baselines/published/NAME, or runs/eval-<env> without a checkpoint)",
    )
    p.add_argument(
        "--augment",
        action="store_true",
        help="keep the checkpoint's training-time view augmentation (default: slides as they are)",
    )
    p.add_argument(
        "--head",
        default=None,
        type=published_or_path,
        help="slide head folder (histojax.reading.heads) or a published head's name (c16-v2-head) that "
        "declares: the policy only chooses where to read, the head scores what was read (default: "
        "the head a reader trained with SASHA's reward names in its head_reward.json; none for other "
        "checkpoints); with --fold I / --all-folds, a DIR holding {fold} or the folder of "
        "learned_head_fit --all-folds is fold I's head",
    )
    add_flag(p)


def scored_names(config, slides=None) -> list[str]:
    """The names of the slides ``evaluate`` scores: the bundle folders of ``slides`` (``--slides``), else the side
    of the dataset ``config.env_kwargs`` names (``split``, ``fold``; ``"all"``: train and test); ``[]`` without a
    dataset or when it cannot be read (the env's own loading says why)."""
    return [Path(str(e)).name for e in scored_entries(config, slides)]


def scored_entries(config, slides=None) -> list[str]:
    """The slides ``evaluate`` scores as paths: the bundle folders of ``slides`` (``--slides``), else the
    ``dataset.json`` entries of the side :func:`scored_names` reads (``bundles/NAME``, relative to the dataset)."""
    kw = dict(config.env_kwargs or {})
    if slides and "held-out" not in [str(s) for s in slides]:
        return [str(s) for s in slides]
    if slides:  # held-out: the test split of the dataset it trained on
        kw["split"] = "test"
    dataset = kw.get("dataset")
    if not isinstance(dataset, str):
        return []
    from baselines.reading.slides import read_spec

    try:
        spec = read_spec(dataset, kw.get("fold"))
    except (HistojaxDataError, OSError, ValueError):
        return []
    split = kw.get("split", "train")
    entries = (spec.get("train") or []) + (spec.get("test") or []) if split == "all" else spec.get(split) or []
    return [str(e) for e in entries]


def default_out(run: Path | None, env_id: str) -> Path:
    """Where ``evaluate`` writes when ``--out`` is not given: ``<run>/eval`` for a run of the user's;
    ``runs/eval-<run name>`` (under the working folder) for a run inside the package (the published agents)
    or a run folder that is not writable; ``runs/eval-<env id>`` without a checkpoint."""
    import os

    if run is None:
        return Path("runs") / f"eval-{env_id}"
    package = [Path(__file__).resolve().parents[1], Path(__file__).resolve().parents[2] / "histojax"]
    inside = any(run.resolve().is_relative_to(p) for p in package)
    if inside or not os.access(run, os.W_OK):
        return Path("runs") / f"eval-{run.resolve().name}"
    return run / "eval"


def run(args, parser) -> int:
    """Evaluate on parsed ``args``: tables, eval.json, eval.csv, trajectory pictures and reading maps."""
    if args.checkpoint is None and args.env is None:
        parser.error("give a CHECKPOINT or --env")
    if getattr(args, "all_folds", False):  # the one-fold run below, on every fold
        return run_all_folds(args, parser, one_fold, default_out)
    warnings = []
    settings, where = None, None
    if args.checkpoint is not None:
        refuse_not_an_agent(Path(args.checkpoint))
        run = Path(args.checkpoint)
        run = run if run.is_dir() else run.parent
        try:  # a config.json that is not an object is named before loading (which would fail on it in its own words)
            raw = read_record(run / "config.json")
        except HistojaxDataError:
            raw = {}  # unreadable: load_checkpoint names the file and why
        check_config(raw, run / "config.json")
        params, record = load_checkpoint(args.checkpoint)
        config = read_run_config(record, run / "config.json", warnings)  # typed; unknown keys: warnings
        check_params_tree(params, run / "params.msgpack")
        label = config.algo
        settings, where = head_reward_settings(run, record)
    else:
        params, config, run, label = (
            None,
            read_run_config(
                {
                    "action_mode": args.action_mode,
                    "with_position": args.with_position,
                    "obs_mode": "pixels",
                    "hidden": 256,
                }
            ),
            None,
            "none",
        )
    trained = config
    if (
        run is not None
        and getattr(args, "dataset", None) is None
        and (refusal := published_dataset_refusal(run, config))
    ):
        raise HistojaxDataError(None, refusal)  # its recorded dataset is provenance, never used unasked
    if args.env:
        config = config.replace(env_id=args.env)
    config = with_dataset(
        config, getattr(args, "dataset", None), getattr(args, "split", None), getattr(args, "fold", None)
    )
    recorded = (config.env_kwargs or {}).get("dataset")
    if run is not None and (refusal := encoder_refusal(config, run / "config.json")):
        raise HistojaxDataError(None, refusal)
    if (
        run is not None
        and getattr(args, "dataset", None) is None
        and isinstance(recorded, str)
        and not (Path(recorded) / "dataset.json").is_file()
    ):
        raise HistojaxDataError(
            run / "config.json",
            f"records the dataset it trained on as {recorded}, which does not "
            "exist here (a folder of the machine it was trained on): give --dataset DIR, a "
            "dataset of the same kind (e.g. `python -m data_tools c16 ... --out DIR` for a C16 "
            "agent)",
        )
    if run is not None:
        warnings += provenance_warnings(trained, config, run / "config.json")
        warnings += trained_record_warnings(run, config, run / "config.json")  # a published agent's scale, encoder
    scored = (config.env_kwargs or {}).get("dataset")
    if isinstance(scored, str) and (line := scale_warning(scored)):
        warnings.append(line)  # the encoder-scale warning the dataset's dataset.json records, repeated
    allow = getattr(args, "allow_fitting_slides", False)
    scored_dataset = (config.env_kwargs or {}).get("dataset")
    entries = scored_entries(config, args.slide)
    seen: dict[str, list[str]] = {}  # who saw which scored slides (scored with the flag): written with the figures
    if run is not None and params is not None and entries:  # the policy's own slides: refused (or warned, the flag)
        if names := check_policy(run, scored_dataset, entries, allow):  # the same guard as every policy scorer
            seen["policy"] = names
    head, head_dir = None, None
    if getattr(args, "head", None) or settings:
        from histojax.reading import heads

        if getattr(args, "head", None):  # with --fold I (--all-folds): fold I's head of a per-fold folder / {fold}
            head_dir = Path(args.head if args.fold is None else head_for_fold(args.head, args.fold))
        else:
            head_dir = resolve_head(settings["head"], run, where)
        head = heads.load(head_dir)  # ValueError naming the file: one line
        if entries:  # a slide the head was fitted on: refused (or warned, the flag)
            check_scored(head, head_dir, scored_dataset, entries, allow)
            if names := seen_slides(record_of(head_config(head), scored_dataset)[0], scored_dataset, entries):
                seen["head"] = names
        recorded = (settings or {}).get("head_name")
        if recorded and not getattr(args, "head", None) and recorded != head.name:
            warnings.append(
                f"{where}: the reader trained with the head {recorded!r}; the head found at {head_dir} is {head.name!r}"
            )
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    out = Path(args.out) if args.out else default_out(run, config.env_id)
    slides = resolve_slides(args.slide, config) if args.slide else [config.slide]
    results = {}
    for i, slide in enumerate(slides):
        sub = out if len(slides) == 1 else out / f"slide{i}"
        dataset = (config.env_kwargs or {}).get("dataset")
        name = slide or (
            f"dataset {dataset} ({scored_words(config.env_kwargs or {})})" if dataset else "embedded sample slide"
        )
        print(
            f"evaluating {config.env_id} on {name} ({i + 1} of {len(slides)}), {args.episodes} episodes per policy ...",
            file=sys.stderr,
            flush=True,
        )
        try:
            rows = evaluate(
                config,
                params,
                slide=slide,
                num_episodes=args.episodes,
                seed=args.seed,
                out=sub,
                label=label,
                augment=args.augment,
                source=run,
                progress=True,
                warnings=warnings,
                head=head,
                head_reward=settings if not getattr(args, "head", None) else None,
            )
        except ValueError as e:
            raise grid_refusal(e, run) from None
        print_table(
            f"{config.env_id} on {name} ({args.episodes} episodes per policy"
            f"{' per seed' if params is not None else ''})",
            rows,
            head=f"{head.name!r} ({head_dir})" if head is not None else None,
        )
        results[name] = rows
    out.mkdir(parents=True, exist_ok=True)
    record = {"env_id": config.env_id, "results": results, "warnings": warnings}
    if seen:  # --allow-fitting-slides let the policy or the head score slides it saw: the figures say so
        record["self_scored"] = True
        record["scored_on_seen_slides"] = seen
    if head is not None:
        record["head"] = {"folder": str(head_dir), "name": head.name, "reward": settings}
    outputs.write_text(out / "eval.json", json.dumps(json_safe(record), indent=2, allow_nan=False))  # NaN: null
    with outputs.open_text(out / "eval.csv") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "slide",
                "policy",
                "episodes",
                "success_rate",
                "mean_return",
                "mean_length",
                "mean_steps_to_success",
                "mean_fraction_read",
                "mean_fields_of_view",
                "diagnosis_auc",
                "diagnosis_auc_no_itc",
                "diagnosis_auc_low",
                "diagnosis_auc_high",
                "diagnosis_auc_no_itc_low",
                "diagnosis_auc_no_itc_high",
                "scored_on_seen_slides",
            ]
        )
        marked = "; ".join(f"{who}: {' '.join(names)}" for who, names in seen.items())
        for slide, rows in results.items():
            for name, r in rows.items():
                w.writerow(
                    [
                        "" if v is None else v
                        for v in (
                            slide,
                            name,
                            r["episodes"],
                            r["success_rate"],
                            r["mean_return"],
                            r["mean_length"],
                            r["mean_steps_to_success"],
                            r["mean_fraction_read"],
                            r["mean_fields_of_view"],
                            r.get("diagnosis_auc", ""),
                            r.get("diagnosis_auc_no_itc", ""),
                            r.get("diagnosis_auc_low", ""),
                            r.get("diagnosis_auc_high", ""),
                            r.get("diagnosis_auc_no_itc_low", ""),
                            r.get("diagnosis_auc_no_itc_high", ""),
                            marked,
                        )
                    ]
                )
    print(f"\nwrote {out}/eval.json, eval.csv, trajectory_*.png, reading_*.png, trajectory.gif")
    return 0


def one_fold(args, parser) -> int:
    """:func:`run` on the parsed ``args`` of one fold (``--all-folds`` runs it per fold; inside :func:`run` the name
    ``run`` is the run folder)."""
    return run(args, parser)


def main(argv=None) -> int:
    """``python -m baselines.evaluate``: the same command as ``histojax evaluate`` (errors one line, exit 2)."""
    from histojax.cli import main as histojax_main

    return histojax_main(["evaluate", *(sys.argv[1:] if argv is None else argv)])
