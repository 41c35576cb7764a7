"""How fast the set reader trains with SASHA's reward: PPO env steps/s of the cell-set reader
(``glimpse`` with ``step_obs=True``, :class:`~baselines.cell_set_networks.CellSetActorCritic`) on a dataset's
training slides, the env wrapped in :class:`~histojax.reading.head_reward.HeadReward` exactly as
``baselines.reading.train_readers`` wraps it, under four settings measured in one run:

* ``whole grid, keys every step``: the head re-scores the whole finest grid at every step
  (``incremental_score=False``) and the rollout recomputes every slide's cell keys at every step (as
  ``baselines.ppo`` did before :func:`baselines.networks.rollout_apply`; the network computes the keys of the
  valid cells only, as it does now);
* ``windowed head``: the head re-scores only the window around the revealed cell;
* ``windowed head + keys once``: also the cell keys once per update (what ``baselines.ppo`` does now);
* the same at a larger batch (``--big-envs`` envs, ``--big-minibatches`` minibatches).

    python -m benchmarks.reader_training_speed --dataset DIR --head HEAD [--action-mode glimpse:2]
        [--num-envs 32] [--updates 3] [--json out.json]

Each row is compiled first (compile time printed), then ``--updates`` PPO updates of 1 seed are timed.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path


def one_row(
    dataset: Path,
    head_dir: str,
    action_mode: str,
    num_envs: int,
    minibatches: int,
    updates: int,
    budget: float,
    windowed: bool,
    keys_once: bool,
) -> dict:
    """PPO env steps/s of one setting (1 seed, ``updates`` updates of ``num_envs`` × 64 steps)."""
    import jax

    from baselines import ppo
    from baselines.harness.runner import compile_seeds
    from histojax.reading import heads
    from histojax.reading.head_reward import HeadReward

    head = heads.load(head_dir)
    original_make, original_apply = ppo.make_env, ppo.rollout_apply

    def make_env(config, auto_reset=True, mesh=None):
        env, params = original_make(config, auto_reset=auto_reset, mesh=mesh)
        return HeadReward(
            env, head, gain="fidelity", final=0.0, params=params, incremental_score=None if windowed else False
        ), params

    ppo.make_env = make_env
    if not keys_once:  # the rollout as before: every step recomputes every slide's cell keys
        ppo.rollout_apply = lambda network, params: lambda obs: network.apply(params, obs)
    try:
        config = {
            **ppo.DEFAULTS,
            "env_id": "HistoJAX-C16-Diagnosis-v2",
            "action_mode": action_mode,
            "obs_mode": "features",
            "num_envs": num_envs,
            "num_steps": 64,
            "num_minibatches": minibatches,
            "total_timesteps": num_envs * 64 * updates,
            "print_progress": False,
            "num_seeds": 1,
            "env_kwargs": {"dataset": str(dataset), "split": "train", "read_budget": budget},
        }
        t0 = time.perf_counter()
        train = ppo.make_train(config)
        t_make = time.perf_counter() - t0
        keys = jax.random.split(jax.random.key(0), 1)
        t0 = time.perf_counter()
        compiled = compile_seeds(train, keys)
        t_compile = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(keys))
        wall = time.perf_counter() - t0
    finally:
        ppo.make_env, ppo.rollout_apply = original_make, original_apply
    steps = num_envs * 64 * train.num_updates
    return {
        "num_envs": num_envs,
        "num_minibatches": minibatches,
        "windowed_head": windowed,
        "keys_once": keys_once,
        "env_steps": steps,
        "wall_s": round(wall, 2),
        "steps_per_s": round(steps / wall),
        "compile_s": round(t_compile, 1),
        "make_s": round(t_make, 1),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.reader_training_speed",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--dataset", required=True, type=Path, help="a dataset folder (its train split is used)")
    p.add_argument("--head", required=True, help="a slide head folder (e.g. baselines/published/c16-v2-head)")
    p.add_argument("--action-mode", default="glimpse:2")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--minibatches", type=int, default=8)
    p.add_argument("--big-envs", type=int, default=128)
    p.add_argument("--big-minibatches", type=int, default=4)
    p.add_argument("--updates", type=int, default=3)
    p.add_argument("--budget", type=float, default=0.1)
    p.add_argument("--skip-before", action="store_true", help="skip the slow first row (whole grid, keys every step)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    if not (args.dataset / "dataset.json").is_file():
        print(f"error: {args.dataset}: no dataset.json (a dataset folder from data_tools)", file=sys.stderr)
        return 2
    import jax

    settings = [
        ("whole grid, keys every step", args.num_envs, args.minibatches, False, False),
        ("windowed head", args.num_envs, args.minibatches, True, False),
        ("windowed head + keys once", args.num_envs, args.minibatches, True, True),
        ("windowed head + keys once, larger batch", args.big_envs, args.big_minibatches, True, True),
    ]
    if args.skip_before:
        settings = settings[1:]
    rows = []
    print(f"{'setting':42s} {'envs':>5s} {'mb':>3s} {'steps/s':>9s} {'compile s':>9s}")
    for name, envs, mbs, windowed, once in settings:
        row = {
            "setting": name,
            **one_row(args.dataset, args.head, args.action_mode, envs, mbs, args.updates, args.budget, windowed, once),
        }
        rows.append(row)
        print(f"{name:42s} {envs:5d} {mbs:3d} {row['steps_per_s']:9d} {row['compile_s']:9.1f}", flush=True)
    meta = {
        "dataset": str(args.dataset),
        "head": args.head,
        "action_mode": args.action_mode,
        "machine": f"{platform.machine()}, {jax.device_count()} × {jax.devices()[0].platform}",
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
    }
    print(json.dumps(meta))
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
