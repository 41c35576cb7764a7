"""Steps per second of the environment with feature observations (``obs_mode="features"``).

``lax.scan`` over ``vmap(step)`` with random actions and auto-reset, on the embedded sample slide
with its EfficientNet-Lite0 feature grid (computed once into a copy of the cached sample bundle,
``<cache>/…-features``, about a minute and a half on 2 CPU cores), or on ``--bundle``. Prints
steps/s per batch size and the ratio to HistoGym's 13–60 steps/s (one OpenSlide read and one
polygon overlap per step, one Python env).

    python benchmarks/features_throughput.py [--env HistoJAX-Hard-v0] [--batches 1024 4096] [--seconds 1.0]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

import histojax
from histojax.sample import sample_feature_bundle

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed: run from the clone
from benchmarks.throughput import full_step_rollout, measure  # noqa: E402

HISTOGYM_STEPS_PER_S = (13.0, 60.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="HistoJAX-Hard-v0")
    p.add_argument("--bundle", default=None, help="bundle with a feature grid (default: the sample slide's)")
    p.add_argument("--batches", type=int, nargs="+", default=[1024, 4096])
    p.add_argument("--seconds", type=float, default=1.0, help="minimum timed seconds per measurement")
    args = p.parse_args(argv)
    bundle = Path(args.bundle) if args.bundle else sample_feature_bundle()
    env, params = histojax.make(args.env, slide=bundle, obs_mode="features")
    d, dtype = params.slide.features.shape[1], params.slide.features.dtype
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"JAX {jax.__version__} on {jax.devices()[0].platform}"
    )
    print(
        f"{args.env} on {bundle.name} ({env.n_levels} levels), feature observations ({d},) "
        f"stored as {jnp.dtype(dtype).name}"
    )
    lo, hi = HISTOGYM_STEPS_PER_S
    print(f"{'batch':>6} {'features steps/s':>17} {'x HistoGym (13-60 steps/s)':>28}")
    for batch in args.batches:
        sps = measure(full_step_rollout, env, params, batch, args.seconds)
        print(f"{batch:>6} {sps:>17,.0f} {f'{sps / hi:,.0f}-{sps / lo:,.0f}x':>28}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
