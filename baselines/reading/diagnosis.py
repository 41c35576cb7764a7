"""A navigator's diagnosis through the slide head: the navigator chooses where to look, the head declares.

    python -m baselines.reading.diagnosis --dataset DIR --head HEAD --navigator NAME RUN [--split test] [--out DIR]

A trained navigator (a run folder of ``python -m baselines.ppo`` / ``ppo_rnn`` in ``discrete`` or
``continuous`` mode, e.g. ``baselines/published/c16-v1-diagnosis``) is rolled greedily once per slide
of the split (each of its first ``--policy-seeds`` seeds; ``--sampled``: its sampled policy) by
:func:`baselines.episodes.rollout.run_episodes`,
with reading tracked; the **finest-level tissue views it stood on** make its read mask, and the slide
head scores them: the slide's diagnosis no longer comes from the navigator's own declaring action (which can
memorise overviews), only from what it read. ``--head`` is any head folder :func:`histojax.reading.heads.load`
reads: a pcam-cnn logit head (``c16-v2-head``, ``c16-v2-head-mil``) or a head learned from any encoder's features
(``learned-attention-mil``, :mod:`baselines.reading.learned_head_fit`; its scripted row is the *score reader*:
cells by the head's per-view score). The rows join the one-head budget curve (:mod:`baselines.reading.readers`:
overview only, random and scripted readers, read everything, at the fraction the navigator actually read) in
``OUT/readers.csv``, ``readers.json``, ``readers.png``. A split of one class is refused in one line (its AUC is
undefined: one class), nothing written.

:func:`score_split` and :func:`write_results` are the scoring loop this command and
``experiments.navigator_ceiling`` share: the split loaded through the head, the one-class refusal, the scripted
readers' rows, and the CSV and JSON written.

In an env, :class:`histojax.reading.head_reward.HeadReward` gives the same score step by step
(``info["head_score"]``: at the episode's end, the navigator's diagnosis by the head).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from baselines import outputs
from baselines.reading import reader_scores
from baselines.reading.csv_files import write_csv
from baselines.reading.pipeline import BUDGETS, check_two_classes, run_seeds, split_words
from baselines.reading.plots import plot_readers
from baselines.reading.provenance import add_flag, check_policy, check_scored, mark_words, seen_mark, with_seen
from baselines.run_config import read_run_config
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe, small_split_warning
from histojax.reading.heads import encoder_mismatch


def score_split(
    dataset, head_path, split: str = "test", budgets=BUDGETS, seeds: int = 5, fold: int | None = None
) -> tuple:
    """The scoring every head diagnosis starts from: ``(head, cell level, slides, results)`` with ``head`` any
    head folder (:func:`histojax.reading.heads.load`), ``slides`` the split's slides read for it
    (:func:`baselines.reading.reader_scores.load_split`) and ``results`` the scripted readers' rows at ``budgets``
    (fractions of a slide's finest tissue views; ``seeds`` random orders): :func:`baselines.reading.reader_scores.scripted_results`.
    A split without slides of both classes is a ``HistojaxDataError`` naming ``dataset.json``, one line: its AUC is
    undefined: one class (:func:`baselines.reading.pipeline.check_two_classes`, as the readers refuse it); so is a
    head of another encoder's features (:func:`histojax.reading.heads.encoder_mismatch`), naming its ``config.json``."""
    head, level, slides = reader_scores.load_split(dataset, head_path, split, fold=fold)
    if (problem := encoder_mismatch(head, [s.get("encoder") for s in slides])) is not None:  # as the readers refuse it
        raise HistojaxDataError(
            Path(str(head_path)) / "config.json",
            f"{problem} ({dataset}): fit a head on them (python -m baselines.reading.learned_head_fit)",
        )
    check_two_classes(dataset, split, [int(s["label"]) for s in slides], fold)  # the readers' own refusal
    return head, level, slides, reader_scores.scripted_results(head, slides, budgets, seeds, level)


def write_results(
    out, results: dict, slides: list[dict], record: dict, json_name: str = "readers.json", mark: dict | None = None
) -> list[dict]:
    """The rows of ``results`` (:func:`baselines.reading.reader_scores.rows_from_results`) written to ``OUT/readers.csv``
    and, with ``record`` (the run's settings), to ``OUT/<json_name>``; returns the rows. ``mark``
    (:func:`baselines.reading.provenance.seen_mark`, :func:`~baselines.reading.provenance.with_seen`): slides the head
    or a navigator saw, scored with ``--allow-fitting-slides``, said in both files."""
    rows = reader_scores.rows_from_results(results, slides)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seen = {"scored_on_seen_slides": mark_words(mark)} if mark else {}
    write_csv([{**r, **seen} for r in reader_scores.csv_rows(rows)], out / "readers.csv")
    record = {**record, **(mark or {})}
    outputs.write_text(out / json_name, json.dumps(json_safe({**record, "rows": rows}), indent=1, allow_nan=False))
    return rows


def navigator_reads(
    run, dataset, split: str = "test", seed: int = 0, greedy: bool = True, fold: int | None = None
) -> list[np.ndarray]:
    """Per slide of ``dataset``'s ``split`` (in its order): the indices of the finest tissue views (in the
    slide's raster order of tissue views, as :func:`baselines.reading.reader_scores.masks_from_instances` takes them)
    that one greedy (``greedy=False``: sampled, key ``seed``) episode of ``run``'s seed ``seed`` stood on."""
    import jax

    from baselines.episodes import policies, rollout
    from baselines.harness.logs import load_checkpoint
    from histojax.core.seen_views import SeenMemory, seen_flags

    params, record = load_checkpoint(run)
    config = read_run_config(record, (Path(run) if Path(run).is_dir() else Path(run).parent) / "config.json")
    n_seeds = jax.tree.leaves(params)[0].shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"{run} has {n_seeds} seed(s), not a seed {seed}")
    if config.action_mode.partition(":")[0] not in ("discrete", "continuous"):  # ":memory", ":map" too
        raise ValueError(
            f"{run}: a policy of action mode {config.action_mode!r}; a navigator moves in "
            "discrete or continuous mode, :memory and :map included (readers: python -m baselines.reading.readers "
            "--reader)"
        )
    params = jax.tree.map(lambda a: a[seed], params)
    kw = {k: v for k, v in (config.env_kwargs or {}).items() if k not in ("dataset", "split", "slides", "fold")}
    config = config.replace(
        env_kwargs={**kw, "dataset": str(dataset), "split": split, **({"fold": fold} if fold is not None else {})}
    )  # fold: the slides scored
    config, (env, env_params) = rollout.eval_env(config)
    policy = policies.learned_policy(
        policies.network_for(config, env),
        params,
        config.action_mode,
        greedy=greedy,
        declare=policies.diagnosis_actions(env, policies.network_for(config, env), config.action_mode),
    )
    n_slides = max(1, len(env.bundles))
    slides = np.arange(n_slides)
    per_episode, axes = rollout.per_episode_params(env_params, slides)
    ep = rollout.run_episodes(env, per_episode, policy, jax.random.key(seed), n_slides, params_axes=axes, final=True)
    memory, tables = ep["final_state"].memory, env_params.mode_data
    if not isinstance(memory, SeenMemory):
        raise ValueError(f"{run}: its env does not track the views read")
    f = env.n_levels - 1
    out = []
    for e, i in enumerate(np.asarray(ep["slide"])):
        start = int(tables.grid_offset[i, f])
        size = int(tables.grid_width[i, f] * tables.grid_height[i, f])
        seen = seen_flags(memory.seen[e], start, size)
        out.append(np.flatnonzero(seen[np.asarray(tables.tissue[i])[:size]]))
    return out


def navigator_masks(
    run, dataset, slides: list[dict], split: str = "test", seeds: int = 1, greedy: bool = True, fold: int | None = None
) -> dict:
    """``{1.0: [[read mask (H, W) per slide] per seed]}`` of a navigator (no budget: key 1.0), ready for
    :func:`baselines.reading.reader_scores.add_reader`; ``slides`` are :func:`baselines.reading.slides.load_slides` of the split;
    ``greedy=False``: sampled episodes (key = the seed)."""
    per_seed = []
    for seed in range(max(1, min(seeds, run_seeds(run)))):
        reads = navigator_reads(run, dataset, split, seed, greedy=greedy, fold=fold)
        if len(reads) != len(slides):
            raise ValueError(f"{run}: {len(reads)} episodes for {len(slides)} slides of split {split!r}")
        per_seed.append([reader_scores.masks_from_instances(s, r) for s, r in zip(slides, reads)])
    return {1.0: per_seed}


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.diagnosis``."""
    from baselines.published_agents import published_or_path

    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json; feature grids the head reads)")
    p.add_argument(
        "--head",
        required=True,
        type=published_or_path,
        help="slide head folder, any kind histojax.reading.heads.load reads (baselines.reading.head_fit or "
        "learned_head_fit), or a published head's name",
    )
    p.add_argument(
        "--navigator",
        nargs=2,
        action="append",
        required=True,
        metavar=("NAME", "RUN"),
        help="a trained navigator's run folder (discrete / continuous mode); repeatable",
    )
    p.add_argument("--split", default="test", help="split scored (default test)")
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: score fold I's side of --split (test / validation = fold I)",
    )
    p.add_argument("--policy-seeds", type=int, default=1, help="seeds of each run (default 1)")
    p.add_argument("--seeds", type=int, default=5, help="random reader orders (default 5)")
    p.add_argument(
        "--sampled",
        action="store_true",
        help="roll the navigators' sampled policies (key = the seed) instead of their greedy ones",
    )
    p.add_argument("--out", default="runs/head-diagnosis", help="output folder (default runs/head-diagnosis)")
    add_flag(p)


def run(args, parser=None) -> int:
    """Score each navigator through the head beside the readers; CSV, JSON, PNG in ``args.out``."""
    t0 = time.perf_counter()
    try:
        from baselines.reading.provenance import head_for_fold
        from baselines.reading.slides import read_spec
        from histojax.reading import heads

        if args.fold is not None:  # the folder of learned_head_fit --all-folds (or DIR{fold}): fold I's head
            args.head = head_for_fold(args.head, args.fold)
        scored = read_spec(args.dataset, args.fold).get(args.split) or []
        allow = getattr(args, "allow_fitting_slides", False)
        check_scored(heads.load(args.head), args.head, args.dataset, scored, allow)  # fitted on them: refused
        mark = seen_mark(heads.load(args.head), args.dataset, scored)
        for name, run_dir in args.navigator:  # a navigator trained on them: refused too, before any is read
            names = check_policy(run_dir, args.dataset, scored, allow, option=f"--navigator {name}")
            mark = with_seen(mark, f"policy {name}", names)
        head, level, slides, results = score_split(
            args.dataset, args.head, args.split, seeds=args.seeds, fold=args.fold
        )
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    for name, run_dir in args.navigator:
        try:
            masks = navigator_masks(
                run_dir, args.dataset, slides, args.split, args.policy_seeds, greedy=not args.sampled, fold=args.fold
            )
        except (OSError, ValueError, HistojaxDataError) as e:
            return print_error(f"--navigator {name}: {e}")
        how = ", sampled" if args.sampled else ""
        reader_scores.add_reader(results, head, slides, f"{name} (head declares{how})", masks, "learned")
    out = Path(args.out)
    wall = time.perf_counter() - t0
    rows = write_results(
        out,
        results,
        slides,
        {
            "dataset": str(args.dataset),
            "split": args.split,
            "head": str(args.head),
            "head_name": head.name,
            "head_kind": head.kind,
            "navigators": args.navigator,
            "sampled": bool(args.sampled),
            "wall_s": round(wall, 1),
        },
        mark=mark,
    )
    png = plot_readers(
        rows,
        out / "readers.png",
        f"{Path(args.dataset).name}, {split_words(args.dataset, args.split, args.fold)}: navigators through head "
        f"{head.name}",
    )
    print(f"cells: {reader_scores.cells_words(slides, level)}")
    reader_scores.print_tables(rows, [])
    labels = [int(s["label"]) for s in slides]
    warning = small_split_warning(
        sum(labels),
        len(labels) - sum(labels),
        split_words(args.dataset, args.split, args.fold),
    )
    if warning:
        print(warning, file=sys.stderr)
    print(f"wrote {out}/readers.csv, readers.json and {png} in {wall:.0f} s")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.diagnosis", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
