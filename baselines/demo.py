"""`make demo`: the environment's random-agent table, then PPO trained on HistoJAX-Easy-v0 of the
embedded sample slide and evaluated against the random agent and the scripted policy.

    python -m baselines.demo [--total-steps 196608] [--out out] [--seed 0] [--quick] [--no-train]

1. :func:`random_agent_table`: jitted, vmapped random-agent episodes on Easy /
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

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import histojax
from baselines import outputs
from baselines.common.env import make_random_rollout
from baselines.harness.runner import run_and_save
from data_tools.cli_output import command_main
from data_tools.metrics import json_safe
from histojax.render import animate, render_trajectory

ENV_ID = "HistoJAX-Easy-v0"
# The configuration known to learn Easy on the sample slide (docs/results/benchmarks.md, "On the sample slide"); 48 updates of
# 64 envs x 64 steps. On the shared 2-core CPU training runs at ~1,500 env steps/s.
TOTAL_STEPS = 196_608
DEMO_CONFIG = dict(
    env_id=ENV_ID,
    with_position=True,
    num_envs=64,
    num_steps=64,
    num_seeds=1,
    seed=0,
    total_timesteps=TOTAL_STEPS,
    log_every=4,
)
# --quick: seconds, not a trained agent; Easy only, episodes cut at 10 steps (short GIFs)
QUICK_STEP_LIMIT = 10
QUICK_CONFIG = dict(
    num_envs=8,
    num_steps=16,
    total_timesteps=3 * 8 * 16,
    update_epochs=1,
    num_minibatches=2,
    hidden=32,
    log_every=1,
    max_steps_in_episode=QUICK_STEP_LIMIT,
)
EVAL_EPISODES, QUICK_EVAL_EPISODES = 256, 8
RANDOM_TABLE, QUICK_RANDOM_TABLE = (256, 400), (16, 50)  # (envs, steps per env)
SCENARIOS = ("HistoJAX-Easy-v0", "HistoJAX-Medium-v0", "HistoJAX-Hard-v0")


# ----------------------------------------------------------------------------- 1. the random-agent table
def first_episode(env, params, key, num_envs: int = 64):
    """``(z, x, y)`` sequences of one random-agent episode (a successful one when any of
    ``num_envs`` tries succeeds), from the start to the step that ended it."""
    env = dataclasses.replace(env, auto_reset=False)
    space = env.action_space()
    steps = int(params.max_steps_in_episode)

    @jax.jit
    def run(key):
        key, key_reset = jax.random.split(key)
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, key):
            state, done = carry
            action = jax.vmap(space.sample)(jax.random.split(key, num_envs))
            _, new, _, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, num_envs), state, action, params
            )
            new = jax.tree.map(lambda a, b: jnp.where(done, a, b), state, new)  # freeze finished envs
            return (new, done | term | trunc), (new.z, new.x, new.y, done, info["success"] & ~done)

        (_, _), out = jax.lax.scan(body, (state, jnp.zeros(num_envs, bool)), jax.random.split(key, steps))
        return state, out

    start, (z, x, y, done_before, success) = jax.device_get(run(key))
    success_any = success.any(axis=0)
    pick = int(np.argmax(success_any)) if success_any.any() else 0
    length = int((~done_before[:, pick]).sum())
    zs = np.concatenate([[start.z[pick]], z[:length, pick]])
    xs = np.concatenate([[start.x[pick]], x[:length, pick]])
    ys = np.concatenate([[start.y[pick]], y[:length, pick]])
    return zs, xs, ys, bool(success_any[pick])


def random_agent_table(
    num_envs: int = 256,
    num_steps: int = 400,
    seed: int = 0,
    out="out",
    scenarios=SCENARIOS,
    picture_max_steps: int | None = None,
) -> dict:
    """Print the random-agent table (one row per scenario: levels, steps/s, compile seconds,
    finished episodes, mean return, success rate) and write ``demo_trajectory.png`` / ``.gif``
    (one random Easy episode over the slide; ``picture_max_steps`` shortens its step limit, for
    quick runs) to ``out``. Returns ``{"rows": [...], "files": [...]}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    key = jax.random.PRNGKey(seed)
    for env_id in scenarios:
        env, params = histojax.make(env_id)
        rollout = make_random_rollout(env, num_envs, num_steps)
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(key, params))
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        info, _ = jax.device_get(rollout(jax.random.fold_in(key, 1), params))
        run_s = time.perf_counter() - t0
        done = info["returned_episode"]
        n_episodes = int(done.sum())
        mean_return = float(info["returned_episode_returns"][done].mean()) if n_episodes else float("nan")
        success = float(info["returned_episode_success"][done].mean()) if n_episodes else float("nan")
        rows.append(
            {
                "env_id": env_id,
                "levels": env.n_levels,
                "steps_per_second": num_envs * num_steps / run_s,
                "compile_seconds": compile_s,
                "episodes": n_episodes,
                "mean_return": mean_return,
                "success_rate": success,
            }
        )
    print(f"\nrandom agent, {num_envs} envs × {num_steps} steps, reward preset 'dense'")
    print(
        f"{'scenario':<20} {'levels':>6} {'steps/s':>12} {'compile s':>9} {'episodes':>8} {'mean return':>11} "
        f"{'target reached':>14}"
    )
    for r in rows:
        print(
            f"{r['env_id']:<20} {r['levels']:>6} {r['steps_per_second']:>12,.0f} {r['compile_seconds']:>9.1f} "
            f"{r['episodes']:>8} {r['mean_return']:>11.3f} {r['success_rate']:>13.1%}"
        )
    limit = {"max_steps_in_episode": picture_max_steps} if picture_max_steps else {}
    env, params = histojax.make("HistoJAX-Easy-v0", **limit)
    z, x, y, reached = first_episode(env, params, jax.random.fold_in(key, 2))
    picture = out / "demo_trajectory.png"
    title = f"Easy, random agent, {len(z) - 1} steps, target {'reached' if reached else 'not reached'}"
    render_trajectory(env, z, x, y, path=picture, title=title)
    gif = animate(env, z, x, y, out / "demo_trajectory.gif")
    print(f"\ntrajectory picture: {picture.resolve()}\nanimation:          {Path(gif).resolve()}")
    return {"rows": rows, "files": [picture, Path(gif)]}


def print_banner() -> None:
    print(
        f"histojax demo on the embedded sample slide (CMU-1-Small-Region.svs, CC0; the target is an "
        f"illustrative navigation target, not a diagnosis); JAX {jax.__version__} on {jax.devices()[0].platform}"
    )


# ----------------------------------------------------------------------------- 2. and 3. PPO, evaluation


def train_ppo(config: dict, out: Path) -> tuple[dict, object, dict]:
    """Compile and run PPO for ``config`` (one program over its seeds), then write logs, curve
    and checkpoint to ``out`` (:func:`baselines.harness.runner.run_and_save`). Returns ``(config, params, summary)``."""
    from baselines import ppo

    print(
        f"\nPPO (pixels + view position, {config['num_envs']} envs, seed {config['seed']}), a line every "
        f"{config['log_every']} updates:",
        flush=True,
    )
    return run_and_save("ppo", ppo.make_train, config, out)


def evaluate_policy(config: dict, params, episodes: int, seed: int, out: Path) -> dict:
    """Rows of :func:`baselines.evaluate.scoring.evaluate` (trained policy greedy and sampled, random,
    scripted) on fresh episodes, printed as a table; trajectory PNGs and the GIF go to ``out``."""
    from baselines.evaluate import cli, scoring

    print(f"\nevaluating on {episodes} fresh episodes per policy ...", flush=True)
    rows = scoring.evaluate(config, params, num_episodes=episodes, seed=seed, out=out, label="ppo")
    cli.print_table(
        f"{config['env_id']} on the embedded sample slide, {episodes} episodes per policy "
        f"(success = target reached at the finest level)",
        rows,
    )
    return rows


def run_demo(
    out="out",
    total_steps: int | None = None,
    seed: int = 0,
    quick: bool = False,
    train: bool = True,
    envs: int | None = None,
    steps: int | None = None,
) -> dict:
    """The whole demo; returns the summary written to ``<out>/demo_summary.json``."""
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    print_banner()
    table_envs, table_steps = QUICK_RANDOM_TABLE if quick else RANDOM_TABLE
    table = random_agent_table(
        envs or table_envs,
        steps or table_steps,
        seed,
        out,
        **(dict(scenarios=(ENV_ID,), picture_max_steps=QUICK_STEP_LIMIT) if quick else {}),
    )
    files = {
        str(table["files"][0]): "random agent, one Easy episode over the slide",
        str(table["files"][1]): "the same episode, animated",
    }
    summary = {"random_agent_table": table["rows"], "ppo": None, "evaluation": None}
    if train:
        config = {**DEMO_CONFIG, **(QUICK_CONFIG if quick else {}), "seed": seed}
        if total_steps is not None:
            config["total_timesteps"] = total_steps
        run = out / "ppo-easy"
        config, params, train_summary = train_ppo(config, run)
        eval_dir = run / "eval"
        rows = evaluate_policy(config, params, QUICK_EVAL_EPISODES if quick else EVAL_EPISODES, seed, eval_dir)
        summary["ppo"] = {
            k: train_summary[k]
            for k in (
                "env_steps_per_seed",
                "seeds",
                "train_seconds",
                "compile_seconds",
                "env_steps_per_second_all_seeds",
                "final",
            )
        }
        summary["ppo"]["seed"] = config["seed"]
        summary["evaluation"] = rows
        files.update(
            {
                str(
                    run / "curve.png"
                ): "PPO learning curve (return, success rate, steps to success; random agent dashed)",
                str(run / "params.msgpack"): "trained parameters (flax msgpack) + config.json beside it",
                str(run / "log.csv"): "per-update training log (also log.json)",
                str(eval_dir / "trajectory_ppo_greedy.png"): "trained agent (greedy), one episode over the slide",
                str(eval_dir / "trajectory.gif"): "the same episode, animated",
                str(eval_dir / "trajectory_ppo_sampled.png"): "trained agent (sampled actions)",
                str(eval_dir / "trajectory_random.png"): "random agent, for comparison (also trajectory_scripted.png)",
            }
        )
    summary["wall_seconds"] = time.perf_counter() - t_start
    summary["files"] = files
    path = out / "demo_summary.json"
    outputs.write_text(path, json.dumps(json_safe(summary), indent=2, default=_json_default, allow_nan=False))
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
        print(
            f"PPO trained for {ppo['env_steps_per_seed']:,} env steps in {ppo['train_seconds']:.0f} s "
            f"(+{ppo['compile_seconds']:.0f} s compile, {ppo['env_steps_per_second_all_seeds']:,.0f} env steps/s)"
        )
        for name, r in rows.items():
            print(
                f"  {name:<14} success {_pct(r['success_rate']):>6}  mean return {r['mean_return']:6.2f}  "
                f"steps to success {r['mean_steps_to_success']:5.1f}"
            )
    print("files written:")
    width = max(map(len, summary["files"]))
    for f, what in summary["files"].items():
        print(f"  {f:<{width}}  {what}")


def add_arguments(p) -> None:
    """The options of ``python -m baselines.demo`` and ``histojax demo``."""
    p.add_argument(
        "--total-steps",
        type=int,
        default=None,
        help=f"PPO env steps (default {TOTAL_STEPS:,}; a few minutes on 2 CPU cores)",
    )
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random table, PPO and the evaluation")
    p.add_argument("--quick", action="store_true", help="tiny budgets (seconds; for tests, not a trained agent)")
    p.add_argument("--no-train", action="store_true", help="only the random-agent table and its picture")
    p.add_argument("--envs", type=int, default=None, help="random table: parallel environments (default 256)")
    p.add_argument("--steps", type=int, default=None, help="random table: steps per environment (default 400)")


def run(args, parser) -> int:
    """The demo on parsed ``args``."""
    if args.total_steps is not None and args.total_steps <= 0:
        parser.error("--total-steps must be positive")
    run_demo(args.out, args.total_steps, args.seed, args.quick, not args.no_train, args.envs, args.steps)
    return 0


main = command_main(add_arguments, run, "python -m baselines.demo", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
