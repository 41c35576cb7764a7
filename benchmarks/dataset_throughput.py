"""Steps per second of the jitted, vmapped environment on a slide dataset (e.g. the true-scale
CAMELYON16 set of ``data_tools c16``), with the start positions drawn from the cumulative weights
``make`` computes once (``SlideArrays.start_cdf``) and, for comparison, recomputed from the start
logits at every reset as before (``start_cdf=None``; the auto-reset runs in every step).

    python benchmarks/dataset_throughput.py --dataset DIR [--env HistoJAX-C16-Easy-v0] [--split train]
                                            [--obs-mode features] [--batches 64 256 1024] [--env-steps 16384]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import histojax  # noqa: E402
from benchmarks.throughput import full_step_rollout  # noqa: E402
from data_tools.cli_output import command_main  # noqa: E402


def measure(env, params, batch: int, env_steps: int) -> float:
    """Env steps/s of ``env_steps`` steps (rounded to whole batched steps) after compiling."""
    steps = max(2, env_steps // batch)
    fn = full_step_rollout(env, batch, steps)
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(fn(key, params))  # compile
    t0 = time.perf_counter()
    jax.block_until_ready(fn(jax.random.fold_in(key, 1), params))
    return steps * batch / (time.perf_counter() - t0)


def add_arguments(p) -> None:
    p.add_argument("--dataset", required=True, help="dataset folder with dataset.json")
    p.add_argument("--env", default="HistoJAX-C16-Easy-v0")
    p.add_argument("--split", default="train", choices=("train", "test"))
    p.add_argument("--obs-mode", default="features")
    p.add_argument("--batches", type=int, nargs="+", default=[64, 256, 1024])
    p.add_argument("--env-steps", type=int, default=16384, help="env steps timed per measurement (default 16384)")


def run(args, parser=None) -> int:
    t0 = time.perf_counter()
    env, params = histojax.make(
        args.env, dataset=args.dataset, split=args.split, obs_mode=args.obs_mode, with_position=True
    )
    made = time.perf_counter() - t0
    s = params.slide
    device = sum(int(a.nbytes) for a in jax.tree.leaves(s))
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"JAX {jax.__version__} on {jax.devices()[0].platform}"
    )
    print(
        f"{args.env} on {args.dataset} ({args.split}: {s.num_slides} slides, obs_mode={args.obs_mode}); "
        f"make {made:.1f} s, {device / 2**30:.2f} GiB on the device; start positions per slide: "
        f"{s.start_logits.shape[-2]}×{s.start_logits.shape[-1]}"
    )
    old = params.replace(slide=s.replace(start_cdf=None))
    print(f"{'batch':>6} {'steps/s (start_cdf)':>20} {'steps/s (per reset)':>20}")
    for batch in args.batches:
        new_sps = measure(env, params, batch, args.env_steps)
        old_sps = measure(env, old, batch, args.env_steps)
        print(f"{batch:>6} {new_sps:>20,.0f} {old_sps:>20,.0f}")
    return 0


main = command_main(add_arguments, run, "python benchmarks/dataset_throughput.py", __doc__)

if __name__ == "__main__":
    raise SystemExit(main())
