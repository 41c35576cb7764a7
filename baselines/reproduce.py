"""Reproduce HistoGym's tables with the pure-JAX baselines and write them as markdown.

* Table 1 — Easy / Medium / Hard × discrete / continuous actions × PPO / DQN (DQN needs discrete
  actions, so its continuous cells are marked n/a), pixel observations with the view position.
* Table 2 — observations: pixels vs EfficientNet-Lite0 features (the sample slide's feature grid,
  computed once) vs imported features (``--imported BUNDLE``: a bundle whose grid came from
  ``python -m data_tools import-features``), PPO and DQN, Easy, discrete.

Each cell trains with ``baselines.ppo`` / ``baselines.dqn`` (one run folder per cell under
``--out``), then evaluates the trained policy on fresh episodes with ``baselines.evaluate``
(PPO: sampled actions; DQN: greedy). Rows report success rate (target reached at the finest
level), mean return, mean steps to success, and wall time (training + compile).

    python -m baselines.reproduce [--quick] [--tables 1 2] [--steps N] [--seeds N] [--out runs/reproduce]

``--quick`` uses tiny budgets (a smoke run of the whole grid in minutes, far from converged);
the default budgets take hours on 2 CPU cores.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import jax

from baselines import dqn, outputs, ppo
from baselines.evaluate.scoring import evaluate
from baselines.harness.logs import load_checkpoint
from data_tools.cli_output import command_main

BUDGETS = {  # env steps per seed, seeds, evaluation episodes
    "quick": dict(steps=16_384, seeds=1, episodes=32),
    "full": dict(steps=245_760, seeds=2, episodes=256),
}
SCENARIOS = ("HistoJAX-Easy-v0", "HistoJAX-Medium-v0", "HistoJAX-Hard-v0")


def run_cell(algo: str, env_id: str, action_mode: str, obs: str, slide, budget: dict, out: Path) -> dict:
    """Train one cell and evaluate it; returns the row (success, return, steps, seconds)."""
    argv = [
        "--env",
        env_id,
        "--action-mode",
        action_mode,
        "--obs-mode",
        obs,
        "--with-position",
        "--seeds",
        str(budget["seeds"]),
        "--total-steps",
        str(budget["steps"]),
        "--out",
        str(out),
        "--set",
        "print_progress=false",
    ]
    if slide is not None:
        argv += ["--slide", str(slide)]
    t0 = time.perf_counter()
    (ppo if algo == "ppo" else dqn).main(argv)
    wall = time.perf_counter() - t0
    params, config = load_checkpoint(out)
    rows = evaluate(config, params, num_episodes=budget["episodes"], out=out / "eval", label=algo)
    name = f"{algo} (sampled)" if f"{algo} (sampled)" in rows else f"{algo} (greedy)"
    row = rows[name]
    summary = json.loads((out / "log.json").read_text()).get("summary", {})
    return {
        "policy": name,
        "success": row["success_rate"],
        "return": row["mean_return"],
        "steps_to_success": row["mean_steps_to_success"],
        "wall_s": wall,
        "train_steps_per_s": summary.get("env_steps_per_second_all_seeds"),
        "random_success": rows["random"]["success_rate"],
    }


def _fmt_row(label: str, r: dict | None, note: str = "") -> str:
    if r is None:
        return f"| {label} | n/a | | | | {note} |"
    steps = "–" if r["steps_to_success"] != r["steps_to_success"] else f"{r['steps_to_success']:.1f}"
    return (
        f"| {label} | {r['success']:.0%} | {r['return']:.2f} | {steps} | {r['wall_s']:.0f} s | "
        f"random agent {r['random_success']:.0%}{'; ' + note if note else ''} |"
    )


HEADER = "| cell | success | mean return | steps to success | wall time | notes |\n|---|---|---|---|---|---|"


def table1(budget: dict, out: Path) -> list[str]:
    lines = ["### Table 1: scenarios × action modes × algorithms (pixels + position, sample slide)", "", HEADER]
    for env_id in SCENARIOS:
        for mode in ("discrete", "continuous"):
            for algo in ("ppo", "dqn"):
                label = f"{env_id} / {mode} / {algo.upper()}"
                if algo == "dqn" and mode == "continuous":
                    lines.append(_fmt_row(label, None, "DQN needs discrete actions"))
                    continue
                row = run_cell(algo, env_id, mode, "pixels", None, budget, out / f"t1-{env_id}-{mode}-{algo}")
                lines.append(_fmt_row(label, row))
    return lines


def table2(budget: dict, out: Path, imported=None) -> list[str]:
    from histojax.sample import sample_feature_bundle

    lines = ["### Table 2: observations (Easy, discrete, with position, sample slide)", "", HEADER]
    cells = [("pixels", "pixels", None), ("EfficientNet-Lite0 features", "features", sample_feature_bundle())]
    if imported is not None:
        cells.append(("imported features", "features", Path(imported)))
    for label, obs, slide in cells:
        for algo in ("ppo", "dqn"):
            tag = label.split()[0].lower()
            row = run_cell(algo, "HistoJAX-Easy-v0", "discrete", obs, slide, budget, out / f"t2-{tag}-{algo}")
            lines.append(_fmt_row(f"{label} / {algo.upper()}", row))
    if imported is None:
        lines.append("| imported features | not run | | | | pass --imported BUNDLE with an imported grid |")
    return lines


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reproduce`` and ``histojax reproduce``."""
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke run of the grid, not converged")
    p.add_argument("--tables", type=int, nargs="+", default=[1, 2], choices=(1, 2))
    p.add_argument("--steps", type=int, default=None, help="env steps per seed per cell (overrides the budget)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per cell (overrides the budget)")
    p.add_argument("--episodes", type=int, default=None, help="evaluation episodes per seed (overrides the budget)")
    p.add_argument("--imported", default=None, help="bundle with an imported feature grid (Table 2 column)")
    p.add_argument("--out", default="runs/reproduce", help="folder for run folders and the markdown table")


def run(args, parser=None) -> int:
    """Train, evaluate and tabulate on parsed ``args``; writes ``<out>/tables.md``."""
    mode = "quick" if args.quick else "full"
    budget = dict(BUDGETS[mode])
    for k in ("steps", "seeds", "episodes"):
        if getattr(args, k) is not None:
            budget[k] = getattr(args, k)
            mode = "custom"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    lines = [
        f"## Reproduced tables ({mode}: {budget['steps']:,} env steps × {budget['seeds']} seed(s) per cell, "
        f"{budget['episodes']} evaluation episodes per seed)",
        "",
        f"Machine: {platform.machine()}, {jax.device_count()} {jax.devices()[0].platform} device(s), "
        f"JAX {jax.__version__}. Success = target reached at the finest level on fresh episodes.",
        "",
    ]
    if 1 in args.tables:
        lines += table1(budget, out) + [""]
    if 2 in args.tables:
        lines += table2(budget, out, args.imported) + [""]
    lines.append(f"Total wall time {time.perf_counter() - t0:.0f} s.")
    table = out / "tables.md"
    outputs.write_text(table, "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"\nwrote {table}")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reproduce", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
