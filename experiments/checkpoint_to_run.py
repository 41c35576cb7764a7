"""A PPO run stopped before its end, as a run folder: its last checkpoint's parameters and learning curve.

    python -m experiments.checkpoint_to_run RUN [--out DIR]

``RUN/checkpoint/`` (``runner.msgpack``, ``config.json``: what ``--checkpoint-every`` writes) holds every
seed's whole training state after the last finished chunk. This writes ``OUT/params.msgpack`` and
``OUT/config.json`` (the run's config, ``total_timesteps`` set to the steps actually trained), ``log.csv``,
``log.json`` and ``curve.png`` (the updates done so far; no random-agent reference), so that
``baselines.reading.diagnosis``, ``baselines.evaluate`` and ``histojax evaluate`` read it as a finished run.
``OUT`` defaults to ``RUN``. The parameters are found in the runner state by their shapes: the network the
config makes (built on one slide of the run's dataset), every leaf with the seeds on axis 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError


def params_from_leaves(template, leaves: list[np.ndarray], n_seeds: int):
    """The parameters in a runner state's flat ``leaves``: the first run of consecutive leaves whose shapes
    are ``template``'s leaves with a leading ``n_seeds`` axis; the pytree of ``template`` with seeds on axis 0."""
    import jax

    want, treedef = jax.tree.flatten(template)
    shapes = [(n_seeds, *np.shape(w)) for w in want]
    for i in range(len(leaves) - len(want) + 1):
        if all(tuple(np.shape(leaves[i + j])) == s for j, s in enumerate(shapes)):
            return jax.tree.unflatten(treedef, [np.asarray(leaves[i + j]) for j in range(len(want))])
    raise ValueError("no run of leaves in the checkpoint has the network's parameter shapes")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m experiments.checkpoint_to_run",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    import jax
    from flax import serialization

    from baselines.common.env import make_env
    from baselines.harness.curves import plot_curves
    from baselines.harness.logs import finite_mean, save_checkpoint, smooth, write_logs
    from baselines.harness.runner import CHECKPOINT_DIR
    from baselines.networks import preprocess_obs
    from baselines.ppo import make_network

    folder = args.run / CHECKPOINT_DIR
    try:
        config = read_run_config(folder / "config.json")
        state = serialization.msgpack_restore((folder / "runner.msgpack").read_bytes())
    except (OSError, ValueError, HistojaxDataError) as e:
        print(f"error: {folder}: no readable checkpoint ({e})", file=sys.stderr)
        return 2
    if config.algo != "ppo":
        print(f"error: {folder}: a {config.algo} run; this reads PPO runs", file=sys.stderr)
        return 2
    leaves = [state["leaves"][str(i)] for i in range(len(state["leaves"]))]
    n_seeds, update = int(config.num_seeds), int(state["update"])
    kw = dict(config.env_kwargs or {})
    with tempfile.TemporaryDirectory() as tmp:
        if kw.get("dataset"):  # the network's shapes from one slide of the run's dataset
            spec = json.loads((Path(kw["dataset"]) / "dataset.json").read_text())
            root = Path(kw["dataset"])
            first = next(iter(spec[kw.get("split", "train")]))
            first = str(first if Path(first).is_absolute() else (root / first).resolve())
            (Path(tmp) / "dataset.json").write_text(
                json.dumps({**spec, "train": [first], "test": [first]}, allow_nan=False)
            )
            kw = {**kw, "dataset": tmp, "split": "train"}
        small = config.replace(env_kwargs=kw)
        env, env_params = make_env(small)
        network = make_network(small, env)
        obs, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 2), env_params)
        template = network.init(jax.random.key(0), preprocess_obs(obs))
    try:
        params = params_from_leaves(template, leaves, n_seeds)
    except ValueError as e:
        print(f"error: {folder}: {e}", file=sys.stderr)
        return 2
    metrics = {k: np.asarray(v) for k, v in state["metrics"].items()}
    steps_per_update = int(config.num_envs) * int(config.num_steps)
    steps = (np.arange(update) + 1) * steps_per_update
    out = args.out or args.run
    out.mkdir(parents=True, exist_ok=True)
    config = config.replace(total_timesteps=int(steps[-1]))
    record = {
        **config.as_dict(),
        "stopped_at_update": update,  # the run's notes (RECORD_NOTES) beside it
        "checkpoint_train_seconds": float(state["train_seconds"]),
    }
    k = max(1, update // 40)
    tail = slice(max(0, update - k), None)
    summary = {
        "algo": "ppo",
        "env_id": config.env_id,
        "env_steps_per_seed": int(steps[-1]),
        "seeds": n_seeds,
        "train_seconds": float(state["train_seconds"]),
        "stopped_at_update": update,
        "planned_updates": int(state["num_updates"]),
        "env_steps_per_second_all_seeds": float(steps[-1] * n_seeds / max(1e-9, float(state["train_seconds"]))),
        "final": {n: finite_mean(metrics[n][:, tail]) for n in ("return", "success", "length")},
    }
    write_logs(out, steps, metrics, summary)
    plot_curves(
        out / "curve.png",
        steps,
        {
            "mean return": smooth(metrics["return"], k),
            "success rate": smooth(metrics["success"], k),
            "mean length": smooth(metrics["length"], k),
        },
        title=f"PPO on {config.env_id} ({config.action_mode}), {n_seeds} seeds, "
        f"stopped at update {update}/{state['num_updates']}",
    )
    save_checkpoint(out, params, record)
    print(
        f"{out}: update {update}/{state['num_updates']}, {steps[-1]:,} env steps/seed x {n_seeds} seeds in "
        f"{state['train_seconds']:.0f} s ({summary['env_steps_per_second_all_seeds']:,.0f} env steps/s); "
        f"final return {summary['final']['return']:.4f}; wrote params.msgpack, config.json, log.csv, curve.png"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
