"""Set-reader PPO through a head against a navigator's PPO through the same head, on the same slides, back to back
in one process: env steps/s of each (and their ratio), the env wrapped in
:class:`~histojax.reading.head_reward.HeadReward` as ``baselines.reading.train_readers`` wraps it, under
``HistoJAX-Reading-v0`` (any dataset, any encoder's features; the levels the bundles were built for)::

    python -m benchmarks.learned_reader_speed --dataset DIR --head HEAD [--reader glimpse:1] [--num-envs 32]
        [--updates 3] [--repeats 3] [--all-cells] [--by-env] [--json out.json]

With the learned attention-MIL head the reward is running sums (a step adds the views it newly read). Each
setting is compiled once, then ``--updates`` PPO updates of 1 seed are timed ``--repeats`` times, the two
settings interleaved; the median of each is printed with the ratio reader / navigator (the target is ≥ 0.5).
``--all-cells`` adds a third row, the set reader with its per-cell layers over the valid cells of all training
slides in every minibatch (``batch_cells=False``: how it trained before they ran over the minibatch's slides only;
the same parameters and outputs), so the two are compared in one process. ``--by-env`` adds the set reader
with PPO's minibatches drawn by env (``minibatch_by="env"``: each minibatch whole env sequences, so it holds only
those envs' episodes and slides; how PPO samples changes, see docs/results/readers.md for its training check).
``benchmarks.synthetic_reading_set``
builds a set of any number of slides to run it on.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path


def compiled_row(
    dataset: Path,
    head,
    action_mode: str,
    num_envs: int,
    updates: int,
    budget: float,
    levels: int,
    all_cells: bool = False,
    minibatch_by: str = "sample",
):
    """``(run, steps, compile_s)``: a compiled PPO program (1 seed, ``updates`` updates of ``num_envs`` × 64 steps)
    of ``action_mode`` on ``dataset``'s train split through ``head``'s reward, the env steps one run takes and the
    compile time. ``all_cells``: a set reader's per-cell layers over all slides' cells (``batch_cells=False``);
    ``minibatch_by``: PPO's ``minibatch_by`` ("sample": shuffled samples, its default; "env": whole env sequences)."""
    import jax

    from baselines import ppo
    from baselines.harness.runner import compile_seeds
    from baselines.reading.train_readers import is_navigator
    from histojax.reading.head_reward import HeadReward
    from histojax.registry import READING_ID

    original, original_network = ppo.make_env, ppo.make_network

    def make_env(config, auto_reset=True, mesh=None):
        env, params = original(config, auto_reset=auto_reset, mesh=mesh)
        return HeadReward(env, head, gain="fidelity", final=0.0, params=params), params

    def make_network(config, env, network_cls=None):
        net = original_network(config, env) if network_cls is None else original_network(config, env, network_cls)
        return net.clone(batch_cells=False) if all_cells and hasattr(net, "batch_cells") else net

    ppo.make_env, ppo.make_network = make_env, make_network
    try:
        kw = {"dataset": str(dataset), "split": "train", "n_levels": levels}
        if not is_navigator(action_mode):
            kw["read_budget"] = budget
        config = {
            **ppo.DEFAULTS,
            "env_id": READING_ID,
            "action_mode": action_mode,
            "obs_mode": "features",
            "num_envs": num_envs,
            "num_steps": 64,
            "total_timesteps": num_envs * 64 * updates,
            "print_progress": False,
            "num_seeds": 1,
            "minibatch_by": minibatch_by,
            "env_kwargs": kw,
        }
        train = ppo.make_train(config)
        keys = jax.random.split(jax.random.key(0), 1)
        t0 = time.perf_counter()
        compiled = compile_seeds(train, keys)
        compile_s = time.perf_counter() - t0
    finally:
        ppo.make_env, ppo.make_network = original, original_network

    def run() -> tuple[float, float]:
        """One timed run: ``(wall s, CPU s of this process)``."""
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(keys))
        return time.perf_counter() - t0, time.process_time() - c0

    return run, num_envs * 64 * train.num_updates, compile_s


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.learned_reader_speed",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--dataset", required=True, type=Path, help="a dataset folder (its train split is used)")
    p.add_argument("--head", required=True, help="a slide head folder (e.g. a learned head)")
    p.add_argument("--reader", default="glimpse:1", help="the set reader's action mode (default glimpse:1)")
    p.add_argument("--navigator", default="discrete", help="the navigator's action mode (default discrete)")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--updates", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--budget", type=float, default=0.1)
    p.add_argument(
        "--all-cells",
        action="store_true",
        help="also time the set reader with its per-cell layers over all slides' cells in every minibatch",
    )
    p.add_argument(
        "--by-env",
        action="store_true",
        help="also time the set reader with PPO's minibatches drawn by env (minibatch_by='env')",
    )
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    from baselines.reading.slides import read_spec
    from baselines.reading.train_readers import dataset_levels
    from data_tools.errors import HistojaxDataError
    from histojax.reading import heads

    try:
        head = heads.load(args.head)
        levels = dataset_levels(args.dataset, read_spec(args.dataset))
    except (HistojaxDataError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    import jax

    rows = {}
    settings = [("navigator", args.navigator, False, "sample"), ("set reader", args.reader, False, "sample")]
    if args.all_cells:
        settings.append(("set reader, all cells", args.reader, True, "sample"))
    if args.by_env:
        settings.append(("set reader, by env", args.reader, False, "env"))
    for name, mode, all_cells, by in settings:
        run, steps, compile_s = compiled_row(
            args.dataset, head, mode, args.num_envs, args.updates, args.budget, levels, all_cells, by
        )
        rows[name] = {
            "action_mode": mode,
            "run": run,
            "steps": steps,
            "compile_s": round(compile_s, 1),
            "walls": [],
            "cells": ("all slides'" if all_cells else "the minibatch's slides'") if name != "navigator" else None,
            "minibatch_by": by,
        }
    for _ in range(args.repeats):  # interleaved: all see the same machine load
        for r in rows.values():
            wall, cpu = r["run"]()
            r["walls"].append(wall)
            r.setdefault("cpus", []).append(cpu)
    out = []
    print(
        f"{'policy':22s} {'mode':12s} {'envs':>5s} {'median steps/s':>15s} {'runs steps/s':>36s} "
        f"{'steps/CPU-s':>12s} {'compile s':>9s}"
    )
    for name, r in rows.items():
        rates = [r["steps"] / w for w in r["walls"]]
        cpu_rates = [r["steps"] / max(c, 1e-9) for c in r["cpus"]]  # steps per CPU-second: less hurt by other load
        row = {
            "policy": name,
            "action_mode": r["action_mode"],
            "num_envs": args.num_envs,
            "env_steps": r["steps"],
            **({"per_cell_layers_over": r["cells"] + " cells"} if r["cells"] else {}),
            "minibatch_by": r["minibatch_by"],
            "median_steps_per_s": round(statistics.median(rates)),
            "steps_per_s": [round(x) for x in rates],
            "compile_s": r["compile_s"],
            "median_steps_per_cpu_s": round(statistics.median(cpu_rates)),
            "steps_per_cpu_s": [round(x) for x in cpu_rates],
        }
        out.append(row)
        print(
            f"{name:22s} {r['action_mode']:12s} {args.num_envs:5d} {row['median_steps_per_s']:15d} "
            f"{', '.join(str(x) for x in row['steps_per_s']):>36s} {row['median_steps_per_cpu_s']:12d} "
            f"{r['compile_s']:9.1f}"
        )
    ratio = out[1]["median_steps_per_s"] / max(1, out[0]["median_steps_per_s"])
    meta = {
        "dataset": str(args.dataset),
        "head": args.head,
        "head_kind": head.kind,
        "levels": levels,
        "training_slides": len(read_spec(args.dataset)["train"]),
        "machine": f"{platform.machine()}, {jax.device_count()} × {jax.devices()[0].platform}",
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "load_average_1min_at_end": os.getloadavg()[0],
        "reader_over_navigator": round(ratio, 3),
        "reader_over_navigator_cpu": round(
            out[1]["median_steps_per_cpu_s"] / max(1, out[0]["median_steps_per_cpu_s"]), 3
        ),
    }
    print(f"set reader / navigator: {ratio:.2f} (target >= 0.5)")
    extra = {  # the optional rows: their meta prefix and their words
        "set reader, all cells": ("all_cells_", "set reader over all slides' cells"),
        "set reader, by env": ("by_env_", "set reader, minibatches by env"),
    }
    for row in out[2:]:
        prefix, words = extra[row["policy"]]
        for suffix, rate in (("", "median_steps_per_s"), ("_cpu", "median_steps_per_cpu_s")):
            meta[f"{prefix}reader_over_navigator{suffix}"] = round(row[rate] / max(1, out[0][rate]), 3)
        print(f"{words} / navigator: {meta[prefix + 'reader_over_navigator']:.2f}")
    print(json.dumps(meta))
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "rows": out}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
