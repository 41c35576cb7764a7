"""A navigator's diagnosis through the slide head: the navigator chooses where to look, the head declares.

    python -m baselines.reading.diagnosis --dataset DIR --head HEAD --navigator NAME RUN [--split test] [--out DIR]

A trained navigator (a run folder of ``python -m baselines.ppo`` / ``ppo_rnn`` in ``discrete`` or
``continuous`` mode, e.g. ``baselines/published/c16-v1-diagnosis``) is rolled greedily once per slide
of the split (each of its first ``--policy-seeds`` seeds; ``--sampled``: its sampled policy) by
:func:`baselines.evaluate.run_episodes`,
with reading tracked; the **finest-level tissue views it stood on** make its read mask, and the slide
head (:mod:`histojax.reading.heads.logit`) scores them: the slide's diagnosis no longer comes from the navigator's
own declaring action (which can memorise overviews), only from what it read. The rows join the
one-head budget curve (:mod:`baselines.reading.readers`: overview only, random and scripted readers, read
everything, at the fraction the navigator actually read) in ``OUT/readers.csv``, ``readers.json``,
``readers.png``.

In an env, :class:`histojax.adapters.head_reward.HeadReward` gives the same score step by step
(``info["head_score"]``: at the episode's end, the navigator's diagnosis by the head).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from baselines.reading.csv_files import write_csv
from baselines.reading.plots import plot_readers
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError


def navigator_reads(run, dataset, split: str = "test", seed: int = 0, greedy: bool = True,
                    fold: int | None = None) -> list[np.ndarray]:
    """Per slide of ``dataset``'s ``split`` (in its order): the indices of the finest tissue views (in the
    slide's raster order of tissue views, as :func:`baselines.reading.readers.masks_from_instances` takes them)
    that one greedy (``greedy=False``: sampled, key ``seed``) episode of ``run``'s seed ``seed`` stood on."""
    import jax

    from baselines import common, evaluate
    from histojax.reading.tables import SeenMemory, seen_flags

    params, config = common.load_checkpoint(run)
    n_seeds = jax.tree.leaves(params)[0].shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"{run} has {n_seeds} seed(s), not a seed {seed}")
    if str(config.get("action_mode")).partition(":")[0] not in ("discrete", "continuous"):  # ":memory", ":map" too
        raise ValueError(f"{run}: a policy of action mode {config.get('action_mode')!r}; a navigator moves in "
                         "discrete or continuous mode, :memory and :map included (readers: python -m baselines.reading.readers "
                         "--reader)")
    params = jax.tree.map(lambda a: a[seed], params)
    kw = {k: v for k, v in (config.get("env_kwargs") or {}).items() if k not in ("dataset", "split", "slides", "fold")}
    config = {**config, "env_kwargs": {**kw, "dataset": str(dataset), "split": split,
                                       **({"fold": fold} if fold is not None else {})}}  # fold: the slides scored
    config, (env, env_params) = evaluate.eval_env(config)
    policy = evaluate.learned_policy(evaluate.network_for(config, env), params, config["action_mode"], greedy=greedy,
                                     declare=evaluate.diagnosis_actions(env, evaluate.network_for(config, env),
                                                                        config["action_mode"]))
    n_slides = max(1, len(env.bundles))
    slides = np.arange(n_slides)
    per_episode, axes = evaluate.per_episode_params(env_params, slides)
    ep = evaluate.run_episodes(env, per_episode, policy, jax.random.key(seed), n_slides, params_axes=axes, final=True)
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


def navigator_masks(run, dataset, slides: list[dict], split: str = "test", seeds: int = 1,
                    greedy: bool = True, fold: int | None = None) -> dict:
    """``{1.0: [[read mask (H, W) per slide] per seed]}`` of a navigator (no budget: key 1.0), ready for
    :func:`baselines.reading.readers.add_reader`; ``slides`` are :func:`baselines.reading.head_fit.load_slides` of the split;
    ``greedy=False``: sampled episodes (key = the seed)."""
    from baselines.reading.budget_curve import run_seeds
    from baselines.reading.readers import masks_from_instances

    per_seed = []
    for seed in range(max(1, min(seeds, run_seeds(run)))):
        reads = navigator_reads(run, dataset, split, seed, greedy=greedy, fold=fold)
        if len(reads) != len(slides):
            raise ValueError(f"{run}: {len(reads)} episodes for {len(slides)} slides of split {split!r}")
        per_seed.append([masks_from_instances(s, r) for s, r in zip(slides, reads)])
    return {1.0: per_seed}


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.diagnosis``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json; pcam-cnn feature grids)")
    p.add_argument("--head", required=True, help="slide head folder (python -m baselines.reading.head_fit)")
    p.add_argument("--navigator", nargs=2, action="append", required=True, metavar=("NAME", "RUN"),
                   help="a trained navigator's run folder (discrete / continuous mode); repeatable")
    p.add_argument("--split", default="test", help="split scored (default test)")
    p.add_argument("--fold", type=int, default=None, metavar="I",
                   help="a dataset built with --folds K: score fold I's side of --split (test / validation = fold I)")
    p.add_argument("--policy-seeds", type=int, default=1, help="seeds of each run (default 1)")
    p.add_argument("--seeds", type=int, default=5, help="random reader orders (default 5)")
    p.add_argument("--sampled", action="store_true",
                   help="roll the navigators' sampled policies (key = the seed) instead of their greedy ones")
    p.add_argument("--out", default="runs/head-diagnosis", help="output folder (default runs/head-diagnosis)")


def run(args, parser=None) -> int:
    """Score each navigator through the head beside the readers; CSV, JSON, PNG in ``args.out``."""
    from baselines import outputs
    from baselines.reading import readers

    t0 = time.perf_counter()
    try:
        head, level, slides = readers.load_split(args.dataset, args.head, args.split, fold=args.fold)
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    if not slides or len({s["label"] for s in slides}) < 2:
        return print_error(f"{args.dataset}: split {args.split!r} needs tumour and normal slides to score an AUC")
    results = readers.scripted_results(head, slides, seeds=args.seeds, level=level)
    for name, run_dir in args.navigator:
        try:
            masks = navigator_masks(run_dir, args.dataset, slides, args.split, args.policy_seeds,
                                    greedy=not args.sampled, fold=args.fold)
        except (OSError, ValueError, HistojaxDataError) as e:
            return print_error(f"--navigator {name}: {e}")
        how = ", sampled" if args.sampled else ""
        readers.add_reader(results, head, slides, f"{name} (head declares{how})", masks, "learned")
    rows = readers.rows_from_results(results, slides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out / "readers.csv")
    wall = time.perf_counter() - t0
    outputs.write_text(out / "readers.json", json.dumps(
        {"dataset": str(args.dataset), "split": args.split, "head": str(args.head), "head_name": head.name,
         "navigators": args.navigator, "sampled": bool(args.sampled), "wall_s": round(wall, 1), "rows": rows}, indent=1, default=float))
    png = plot_readers(rows, out / "readers.png", f"{Path(args.dataset).name}, {args.split} split: navigators "
                                                   f"through head {head.name}")
    readers.print_tables(rows, [])
    print(f"wrote {out}/readers.csv, readers.json and {png} in {wall:.0f} s")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.diagnosis", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
