"""Reading modes at navigation speed: env steps/s and PPO steps/s of ``glimpse:1``, ``glimpse:2`` and
``zoom_select`` against navigation (``discrete``) on the same true-scale slides, same batch, as
ratios measured in one run; peak RSS of each PPO run; the glimpse host-table time.

    python -m benchmarks.reading_speed --dataset /work/c16-sub8 [--batches 1024 256] [--json out.json]

The slides are every bundle of the dataset (train and test splits), made as ``HistoJAX-C16-Diagnosis-v2``
(pcam-cnn features; the reading modes with ``step_obs=True`` and ``read_budget=0.1``). Each figure
comes from its own process (so peak RSS is that run's), compiled first, then timed:

* **env**: ``lax.scan`` over ``vmap(step)`` with auto-reset, uniform random actions, every
  observation leaf reduced into the carry (so XLA cannot drop any of it), ``--env-steps`` steps;
* **ppo**: ``baselines.ppo`` (feed-forward; the cell-set reader for glimpse) with ``num_envs`` = the
  batch, ``--ppo-steps`` steps per update, ``--ppo-updates`` updates, 1 seed;
* **host tables**: ``Glimpse.prepare`` (the per-slide cell tables) on all the slides.

``--paired N``: each env row also times navigation in its own process, the two programs in turn ``N``
times (best of each): ``vs_navigation_paired``, a ratio that a load changing during the run moves less.

``glimpse:1-full`` is ``glimpse:1`` with the full observation of the ``-v1`` ids (``step_obs=False``) and,
for PPO, the flat network that observation needs: the reading mode as it was before ``-v2``.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

MODES = ("navigation", "glimpse:1", "glimpse:2", "zoom_select", "glimpse:1-full")
# glimpse:1-full: glimpse:1 with the full (v1) observation, every cell's features and summaries at every
# step (step_obs=False), and for PPO the flat network it needs: the reading modes as they were before v2
ENV_ID = "HistoJAX-C16-Diagnosis-v2"


def dataset_bundles(folder) -> list[str]:
    """Every bundle of a dataset folder's ``dataset.json`` (train then test)."""
    from histojax.datasets import dataset_slides

    paths = []
    for split in ("train", "test"):
        try:
            paths += [str(p) for p in dataset_slides(folder, split)]
        except ValueError:
            pass
    return paths


def _overrides(mode: str, budget: float) -> dict:
    if mode == "navigation":
        return {"action_mode": "discrete"}
    if mode.endswith("-full"):
        return {"action_mode": mode[: -len("-full")], "read_budget": budget, "step_obs": False}
    return {"action_mode": mode, "read_budget": budget}


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _env_program(env, params, batch: int, steps: int):
    """The compiled env rollout of :func:`one_env` (run once): ``fn(key)``."""
    import jax
    import jax.numpy as jnp

    n = env.num_actions

    def run(key):
        keys = jax.random.split(key, batch)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def body(carry, k):
            state, acc = carry
            ka, ks = jax.random.split(k)
            action = jax.random.randint(ka, (batch,), 0, n)
            obs, state, r, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(ks, batch), state, action, params
            )
            acc = acc + r.sum() + sum(jnp.sum(x.astype(jnp.float32)) for x in jax.tree.leaves(obs))
            return (state, acc), None

        (state, acc), _ = jax.lax.scan(body, (state, jnp.float32(0)), jax.random.split(key, steps))
        return acc

    fn = jax.jit(run).lower(jax.random.key(0)).compile()
    jax.block_until_ready(fn(jax.random.key(1)))
    return fn


def one_env(dataset, mode: str, batch: int, steps: int, budget: float, paired: int = 0) -> dict:
    """Env steps/s of ``mode``; ``paired`` > 0: navigation's too, in the same process, the two programs timed
    in turn ``paired`` times (best of each), so that a load changing during the run moves both alike."""
    import jax

    import histojax
    from histojax.reading.modes.glimpse import observation_bytes

    paths = dataset_bundles(dataset)
    t0 = time.perf_counter()
    env, params = histojax.make(ENV_ID, slides=paths, **_overrides(mode, budget))
    made = time.perf_counter() - t0
    out = {
        "kind": "env",
        "mode": mode,
        "batch": batch,
        "slides": len(paths),
        "make_s": made,
        "obs_bytes": observation_bytes(env, params),
    }
    if mode.startswith("glimpse") and not mode.endswith("-full"):
        t0 = time.perf_counter()
        env.action.prepare(env, params, env.bundles, read_budget=budget)
        out["host_tables_s"] = time.perf_counter() - t0
        out["cells"] = int(params.mode_data.valid.shape[-1])
    programs = [_env_program(env, params, batch, steps)]
    if paired and mode != "navigation":
        nav_env, nav_params = histojax.make(ENV_ID, slides=paths, **_overrides("navigation", budget))
        programs.append(_env_program(nav_env, nav_params, batch, steps))
    best = [float("inf")] * len(programs)
    for r in range(max(2, paired)):
        for j, fn in enumerate(programs):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(jax.random.key(2 + r)))
            best[j] = min(best[j], time.perf_counter() - t0)
    out.update(steps_per_s=batch * steps / best[0], peak_rss_gb=peak_rss_gb())
    if len(best) > 1:
        out.update(navigation_paired=batch * steps / best[1], vs_navigation_paired=best[1] / best[0])
    return out


def one_ppo(dataset, mode: str, batch: int, steps: int, updates: int, budget: float) -> dict:
    import jax

    from baselines import ppo
    from baselines.harness.runner import compile_seeds

    paths = dataset_bundles(dataset)
    ov = _overrides(mode, budget)
    config = {
        "env_id": ENV_ID,
        "action_mode": ov.pop("action_mode"),
        "obs_mode": "features",
        "env_kwargs": {"slides": paths, **ov},
        "num_envs": batch,
        "num_steps": steps,
        "total_timesteps": batch * steps * updates,
        "num_minibatches": 4,
        "update_epochs": 2,
        "print_progress": False,
        "num_seeds": 1,
    }
    t0 = time.perf_counter()
    train = ppo.make_train(config)
    call = compile_seeds(train, jax.random.split(jax.random.key(0), 1))
    compiled = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(call(jax.random.split(jax.random.key(0), 1)))
    took = time.perf_counter() - t0
    return {
        "kind": "ppo",
        "mode": mode,
        "batch": batch,
        "network": type(train.network).__name__,
        "compile_s": compiled,
        "steps_per_s": batch * steps * train.num_updates / took,
        "peak_rss_gb": peak_rss_gb(),
    }


def _child(args, kind: str, mode: str, batch: int) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "benchmarks.reading_speed",
        "--dataset",
        str(args.dataset),
        "--one",
        kind,
        mode,
        str(batch),
        "--env-steps",
        str(args.env_steps),
        "--ppo-steps",
        str(args.ppo_steps),
        "--ppo-updates",
        str(args.ppo_updates),
        "--budget",
        str(args.budget),
        "--paired",
        str(args.paired),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["(no output)"]
        return {"kind": kind, "mode": mode, "batch": batch, "error": tail[0]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, type=Path, help="a dataset folder with a dataset.json")
    parser.add_argument("--batches", type=int, nargs="+", default=[1024, 256])
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument("--env-steps", type=int, default=32)
    parser.add_argument("--ppo-steps", type=int, default=16)
    parser.add_argument("--ppo-updates", type=int, default=2)
    parser.add_argument("--budget", type=float, default=0.1)
    parser.add_argument("--skip-ppo", action="store_true")
    parser.add_argument(
        "--paired",
        type=int,
        default=0,
        help="env rows: also time navigation in the same process, in turn with the mode, this many "
        "times (ratio 'paired'); 0: off",
    )
    parser.add_argument("--json", type=Path, help="also write the rows here")
    parser.add_argument("--one", nargs=3, metavar=("KIND", "MODE", "BATCH"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not (args.dataset / "dataset.json").is_file():
        print(
            f"reading_speed: {args.dataset}: no dataset.json (make one with python -m data_tools c16 ...)",
            file=sys.stderr,
        )
        return 2
    if args.one:
        kind, mode, batch = args.one[0], args.one[1], int(args.one[2])
        row = (
            one_env(args.dataset, mode, batch, args.env_steps, args.budget, args.paired)
            if kind == "env"
            else one_ppo(args.dataset, mode, batch, args.ppo_steps, args.ppo_updates, args.budget)
        )
        print(json.dumps(row))
        return 0
    import jax

    t_start = time.perf_counter()
    print(
        f"# reading_speed on {args.dataset} ({len(dataset_bundles(args.dataset))} slides), jax {jax.__version__}, "
        f"{platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        flush=True,
    )
    rows = []
    kinds = ["env"] + ([] if args.skip_ppo else ["ppo"])
    for kind in kinds:
        for batch in args.batches:
            base = None
            for mode in args.modes:
                row = _child(args, kind, mode, batch)
                if mode == "navigation" and "steps_per_s" in row:
                    base = row["steps_per_s"]
                if base and "steps_per_s" in row:
                    row["vs_navigation"] = row["steps_per_s"] / base
                rows.append(row)
                extra = "".join(
                    f"  {k} {row[k]:.3g}" if isinstance(row[k], float) else f"  {k} {row[k]}"
                    for k in ("vs_navigation_paired", "obs_bytes", "cells", "host_tables_s", "network", "peak_rss_gb")
                    if k in row
                )
                if "error" in row:
                    print(f"{kind:4s} {mode:12s} batch {batch:5d}  error: {row['error']}", flush=True)
                else:
                    print(
                        f"{kind:4s} {mode:12s} batch {batch:5d}  {row['steps_per_s']:12,.0f} steps/s  "
                        f"x{row.get('vs_navigation', float('nan')):.3f} of navigation{extra}",
                        flush=True,
                    )
    print(f"# wall time {time.perf_counter() - t_start:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
