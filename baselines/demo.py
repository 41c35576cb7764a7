"""`make demo`: the environment's random-agent table, then PPO trained on HistoJAX-Easy-v0 of the
embedded sample slide and evaluated against the random agent and the scripted policy.

    python -m baselines.demo [--total-steps 196608] [--out out] [--seed 0] [--quick] [--no-train]

1. :func:`histojax.demo.random_agent_table`: jitted, vmapped random-agent episodes on Easy /
   Medium / Hard (steps/s, return, success rate) and ``demo_trajectory.png`` / ``.gif``.
2. PPO (``baselines.ppo``, pixels + view position, 64 envs × 64 steps per update, one fixed seed)
   on Easy, one jitted program, with a progress line every 4 updates; learning curve, logs and
   checkpoint go to ``<out>/ppo-easy/`` (``python -m baselines.evaluate <out>/ppo-easy`` re-evaluates it).
3. ``baselines.evaluate`` on fresh episodes: success rate, mean return, steps to success of the
   trained policy (greedy and sampled) against the random agent and the scripted coarse-to-fine
   policy; trajectory pictures and a GIF of the trained agent go to ``<out>/ppo-easy/eval/``.

Ends with a summary and the list of files written (also in ``<out>/demo_summary.json``).
``--quick`` is a tiny budget (seconds of training, not a trained agent) used by the tests.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from histojax.demo import print_banner, random_agent_table

ENV_ID = "HistoJAX-Easy-v0"
# The configuration known to learn Easy on the sample slide (docs/benchmarks.md, "On the sample slide"); 48 updates of
# 64 envs x 64 steps. On the shared 2-core CPU training runs at ~1,500 env steps/s.
TOTAL_STEPS = 196_608
DEMO_CONFIG = dict(env_id=ENV_ID, with_position=True, num_envs=64, num_steps=64, num_seeds=1, seed=0,
                   total_timesteps=TOTAL_STEPS, log_every=4)
# --quick: seconds, not a trained agent; Easy only, episodes cut at 10 steps (short GIFs)
QUICK_STEP_LIMIT = 10
QUICK_CONFIG = dict(num_envs=8, num_steps=16, total_timesteps=3 * 8 * 16, update_epochs=1, num_minibatches=2,
                    hidden=32, log_every=1, max_steps_in_episode=QUICK_STEP_LIMIT)
EVAL_EPISODES, QUICK_EVAL_EPISODES = 256, 8
RANDOM_TABLE, QUICK_RANDOM_TABLE = (256, 400), (16, 50)  # (envs, steps per env)


def train_ppo(config: dict, out: Path) -> tuple[dict, object, dict]:
    """Compile and run PPO for ``config`` (one program over its seeds), then write logs, curve
    and checkpoint to ``out`` (:func:`baselines.ppo.run_and_save`). Returns ``(config, params, summary)``."""
    from baselines import ppo

    print(f"\nPPO (pixels + view position, {config['num_envs']} envs, seed {config['seed']}), a line every "
          f"{config['log_every']} updates:", flush=True)
    return ppo.run_and_save("ppo", ppo.make_train, config, out)


def evaluate_policy(config: dict, params, episodes: int, seed: int, out: Path) -> dict:
    """Rows of :func:`baselines.evaluate.evaluate` (trained policy greedy and sampled, random,
    scripted) on fresh episodes, printed as a table; trajectory PNGs and the GIF go to ``out``."""
    from baselines import evaluate

    print(f"\nevaluating on {episodes} fresh episodes per policy ...", flush=True)
    rows = evaluate.evaluate(config, params, num_episodes=episodes, seed=seed, out=out, label="ppo")
    evaluate.print_table(f"{config['env_id']} on the embedded sample slide, {episodes} episodes per policy "
                         f"(success = target reached at the finest level)", rows)
    return rows


def run_demo(out="out", total_steps: int | None = None, seed: int = 0, quick: bool = False,
             train: bool = True, envs: int | None = None, steps: int | None = None) -> dict:
    """The whole demo; returns the summary written to ``<out>/demo_summary.json``."""
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    print_banner()
    table_envs, table_steps = QUICK_RANDOM_TABLE if quick else RANDOM_TABLE
    table = random_agent_table(envs or table_envs, steps or table_steps, seed, out,
                               **(dict(scenarios=(ENV_ID,), picture_max_steps=QUICK_STEP_LIMIT) if quick else {}))
    files = {str(table["files"][0]): "random agent, one Easy episode over the slide",
             str(table["files"][1]): "the same episode, animated"}
    summary = {"random_agent_table": table["rows"], "ppo": None, "evaluation": None}
    if train:
        config = {**DEMO_CONFIG, **(QUICK_CONFIG if quick else {}), "seed": seed}
        if total_steps is not None:
            config["total_timesteps"] = total_steps
        run = out / "ppo-easy"
        config, params, train_summary = train_ppo(config, run)
        eval_dir = run / "eval"
        rows = evaluate_policy(config, params, QUICK_EVAL_EPISODES if quick else EVAL_EPISODES, seed, eval_dir)
        summary["ppo"] = {k: train_summary[k] for k in ("env_steps_per_seed", "seeds", "train_seconds",
                                                         "compile_seconds", "env_steps_per_second_all_seeds",
                                                         "final")}
        summary["ppo"]["seed"] = config["seed"]
        summary["evaluation"] = rows
        files.update({
            str(run / "curve.png"): "PPO learning curve (return, success rate, steps to success; random agent dashed)",
            str(run / "params.msgpack"): "trained parameters (flax msgpack) + config.json beside it",
            str(run / "log.csv"): "per-update training log (also log.json)",
            str(eval_dir / "trajectory_ppo_greedy.png"): "trained agent (greedy), one episode over the slide",
            str(eval_dir / "trajectory.gif"): "the same episode, animated",
            str(eval_dir / "trajectory_ppo_sampled.png"): "trained agent (sampled actions)",
            str(eval_dir / "trajectory_random.png"): "random agent, for comparison (also trajectory_scripted.png)",
        })
    summary["wall_seconds"] = time.perf_counter() - t_start
    summary["files"] = files
    path = out / "demo_summary.json"
    path.write_text(json.dumps(summary, indent=2, default=_json_default))
    files[str(path)] = "this summary as JSON"
    print_summary(summary)
    return summary


def _json_default(o):
    return o.item() if hasattr(o, "item") else str(o)


def _pct(v) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.1%}"


def print_summary(summary: dict) -> None:
    minutes, seconds = divmod(summary["wall_seconds"], 60)
    print(f"\n=== demo summary ({int(minutes)} min {seconds:.0f} s wall time, compilation included) ===")
    easy = next((r for r in summary["random_agent_table"] if r["env_id"] == ENV_ID), None)
    if easy is not None:
        print(f"environment: random agent on Easy at {easy['steps_per_second']:,.0f} env steps/s")
    if summary["evaluation"]:
        ppo, rows = summary["ppo"], summary["evaluation"]
        print(f"PPO trained for {ppo['env_steps_per_seed']:,} env steps in {ppo['train_seconds']:.0f} s "
              f"(+{ppo['compile_seconds']:.0f} s compile, {ppo['env_steps_per_second_all_seeds']:,.0f} env steps/s)")
        for name, r in rows.items():
            print(f"  {name:<14} success {_pct(r['success_rate']):>6}  mean return {r['mean_return']:6.2f}  "
                  f"steps to success {r['mean_steps_to_success']:5.1f}")
    print("files written:")
    width = max(map(len, summary["files"]))
    for f, what in summary["files"].items():
        print(f"  {f:<{width}}  {what}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--total-steps", type=int, default=None,
                   help=f"PPO env steps (default {TOTAL_STEPS:,}; a few minutes on 2 CPU cores)")
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random table, PPO and the evaluation")
    p.add_argument("--quick", action="store_true", help="tiny budgets (seconds; for tests, not a trained agent)")
    p.add_argument("--no-train", action="store_true", help="only the random-agent table and its picture")
    p.add_argument("--envs", type=int, default=None, help="random table: parallel environments (default 256)")
    p.add_argument("--steps", type=int, default=None, help="random table: steps per environment (default 400)")
    args = p.parse_args(argv)
    if args.total_steps is not None and args.total_steps <= 0:
        p.error("--total-steps must be positive")
    run_demo(args.out, args.total_steps, args.seed, args.quick, not args.no_train, args.envs, args.steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
