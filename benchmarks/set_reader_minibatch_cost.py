"""The cost of one PPO minibatch gradient of the cell-set reader, its per-cell layers over the valid cells of the
minibatch's slides (``batch_cells=True``, the default) against over those of all training slides
(``batch_cells=False``), on a dataset's train split, without the env or the rollout (low noise on a shared CPU)::

    python -m benchmarks.set_reader_minibatch_cost --dataset DIR [--reader glimpse:1] [--repeats 15] [--json out.json]

The minibatch is made as PPO makes one at 64 envs × 64 steps with 8 minibatches (512 samples): each env's steps
run through episodes of ``--episode`` steps on slides drawn at random, and 512 of the 4,096 samples are drawn
without replacement; each sample has read 0–10 random valid cells of its slide (the other observation entries are a
reset's). The gradient of a PPO-like loss (log-probability of one action, value²) is compiled for each path and
timed ``--repeats`` times, interleaved; printed: the slides and valid cells the minibatch holds and the median and
least milliseconds of each path.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def minibatch_slides(
    rng, slides: int, envs: int = 64, steps: int = 64, minibatches: int = 8, episode: int = 11
) -> np.ndarray:
    """The slide of each of the ``envs · steps / minibatches`` samples of one shuffled PPO minibatch: each env's
    ``steps`` run through episodes of ``episode`` steps, each on a slide drawn uniformly from ``slides``."""
    slide = np.empty((steps, envs), np.int64)
    for e in range(envs):
        for t in range(0, steps, episode):
            slide[t : t + episode, e] = rng.integers(slides)
    return slide.reshape(-1)[rng.permutation(steps * envs)][: steps * envs // minibatches]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.set_reader_minibatch_cost",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--dataset", required=True, type=Path, help="a dataset folder (its train split is used)")
    p.add_argument("--reader", default="glimpse:1", help="the set reader's action mode (default glimpse:1)")
    p.add_argument("--budget", type=float, default=0.1)
    p.add_argument("--episode", type=int, default=11, help="steps of an episode (default 11)")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    from baselines.reading.slides import read_spec
    from baselines.reading.train_readers import dataset_levels
    from data_tools.errors import HistojaxDataError

    try:
        levels = dataset_levels(args.dataset, read_spec(args.dataset))
    except (HistojaxDataError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    import jax
    import jax.numpy as jnp

    import histojax
    from baselines import ppo
    from histojax.registry import READING_ID

    env, params = histojax.make(
        READING_ID,
        dataset=str(args.dataset),
        split="train",
        n_levels=levels,
        action_mode=args.reader,
        obs_mode="features",
        read_budget=args.budget,
    )
    config = {
        **ppo.DEFAULTS,
        "env_id": READING_ID,
        "action_mode": args.reader,
        "obs_mode": "features",
        "obs_norm": None,
    }
    nets = {"minibatch's slides": ppo.make_network(config, env)}
    nets["all slides"] = nets["minibatch's slides"].clone(batch_cells=False)
    obs0, _ = env.reset(jax.random.key(0), params)
    valid = np.asarray(params.mode_data.valid) > 0
    s, c = valid.shape
    k = int(np.shape(obs0["read_cells"])[0])
    rng = np.random.default_rng(0)
    slides = minibatch_slides(rng, s, episode=args.episode)
    b = len(slides)
    read = np.full((b, k), c, np.int32)
    for i, sl in enumerate(slides):
        n = rng.integers(0, min(k, 10, int(valid[sl].sum())) + 1)
        read[i, :n] = rng.choice(np.flatnonzero(valid[sl]), n, replace=False)
    obs = jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a), (b, *np.shape(a))), obs0)
    obs = {**obs, "slide": jnp.asarray(slides, jnp.int32), "read_cells": jnp.asarray(read)}
    net_params = jax.jit(nets["all slides"].init)(jax.random.key(1), obs)
    action = jnp.asarray([np.flatnonzero(valid[sl])[0] for sl in slides], jnp.int32)

    def loss(q, net, obs):
        logits, value = net.apply(q, obs)
        logp = jax.nn.log_softmax(logits)
        return -jnp.take_along_axis(logp, action[:, None], -1).sum() + (value**2).sum()

    # the observations an argument, as in PPO's update (not constants of the program)
    grads = {name: jax.jit(jax.grad(lambda q, o, n=net: loss(q, n, o))) for name, net in nets.items()}
    for g in grads.values():
        jax.block_until_ready(g(net_params, obs))
    times = {name: [] for name in grads}
    for _ in range(args.repeats):
        for name, g in grads.items():
            t0 = time.perf_counter()
            jax.block_until_ready(g(net_params, obs))
            times[name].append(time.perf_counter() - t0)
    present = np.unique(slides)
    out = {
        "dataset": str(args.dataset),
        "training_slides": s,
        "valid_cells": int(valid.sum()),
        "minibatch": b,
        "slides_in_minibatch": len(present),
        "cells_of_minibatch_slides": int(valid[present].sum()),
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "grad_ms": {
            name: {
                "median": round(1e3 * statistics.median(v), 1),
                "min": round(1e3 * min(v), 1),
                "runs": [round(1e3 * x, 1) for x in v],
            }
            for name, v in times.items()
        },
    }
    print(
        f"{s} training slides ({out['valid_cells']:,} valid cells); a minibatch of {b} holds {len(present)} slides "
        f"({out['cells_of_minibatch_slides']:,} valid cells)"
    )
    for name, r in out["grad_ms"].items():
        print(
            f"per-cell layers over {name + ' cells':28s} gradient {r['median']:8.1f} ms median, {r['min']:8.1f} least"
        )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
