"""How fast the slide head (:mod:`histojax.reading.heads.logit`) scores slides: jitted and vmapped over a batch of slides
padded to one grid, as the budget curve calls it, and one slide at a time, as an env step would (a
reward from the head's confidence after each read).

    python benchmarks/head_throughput.py [--grid 256 128] [--batch 64] [--ks 1 3 5] [--repeats 20]

Prints, per neighbourhood side ``k``: slides/s of the batched call and µs per single-slide call (compile
time excluded; the mask reads a random half of the views)."""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from histojax.reading.heads import score_logits

from histojax.reading.heads.logit import SlideHead


def timed(fn, *args, repeats: int = 20) -> float:
    """Median seconds of ``fn(*args)`` after one warm-up call (compilation)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--grid", type=int, nargs=2, default=[256, 128], metavar=("H", "W"),
                   help="finest views per slide (default 256 × 128, a large C16 slide)")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--ks", type=int, nargs="+", default=[1, 3, 5])
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args(argv)
    h, w = args.grid
    rng = np.random.default_rng(0)
    logits = jnp.asarray(rng.normal(-3, 1, (args.batch, h, w)).astype(np.float32))
    masks = jnp.asarray(rng.random((args.batch, h, w)) < 0.5)
    print(f"JAX {jax.__version__} on {jax.devices()[0].platform}; {args.batch} slides of {h} × {w} views")
    print("| k | batched: slides/s | one slide: µs per call |\n|---|---|---|")
    for k in args.ks:
        head = SlideHead(k=k)
        batched = jax.jit(jax.vmap(score_logits, in_axes=(None, 0, 0)))
        single = jax.jit(score_logits)
        tb = timed(batched, head, logits, masks, repeats=args.repeats)
        ts = timed(single, head, logits[0], masks[0], repeats=args.repeats)
        print(f"| {k} | {args.batch / tb:,.0f} | {ts * 1e6:,.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
