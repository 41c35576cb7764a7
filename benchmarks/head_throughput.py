"""How fast the slide head (:mod:`histojax.reading.heads.logit`) scores slides: jitted and vmapped over a batch of slides
padded to one grid, as the budget curve calls it, and one slide at a time, as an env step would (a
reward from the head's confidence after each read).

    python benchmarks/head_throughput.py [--grid 256 128] [--batch 64] [--ks 1 3 5] [--repeats 20] [--dim 64]

Prints, per neighbourhood side ``k``: slides/s of the batched call and µs per single-slide call (compile
time excluded; the mask reads a random half of the views). Then the same for the learned attention-MIL head
(:mod:`histojax.reading.heads.learned`, ``--dim`` features, 64 units) three ways: from the feature grid
``(H, W, D)``; from its cached view terms ``(H, W, 2)`` (attention and instance logit, computed once per
slide); and one incremental step that adds 16 newly read views to each slide's running sums."""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from histojax.reading.heads import score_logits
from histojax.reading.heads.learned import LearnedHead, init_params
from histojax.reading.heads.logit import LogitHead


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
    p.add_argument(
        "--grid",
        type=int,
        nargs=2,
        default=[256, 128],
        metavar=("H", "W"),
        help="finest views per slide (default 256 × 128, a large C16 slide)",
    )
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--ks", type=int, nargs="+", default=[1, 3, 5])
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--dim", type=int, default=64, help="feature entries of the learned head's rows (default 64)")
    p.add_argument(
        "--feature-batch",
        type=int,
        default=8,
        help="slides per batched call of the learned head on feature grids (default 8: 64 of them "
        "are 0.5 GB of float32 at 256 x 128 x 64)",
    )
    args = p.parse_args(argv)
    h, w = args.grid
    rng = np.random.default_rng(0)
    logits = jnp.asarray(rng.normal(-3, 1, (args.batch, h, w)).astype(np.float32))
    masks = jnp.asarray(rng.random((args.batch, h, w)) < 0.5)
    print(f"JAX {jax.__version__} on {jax.devices()[0].platform}; {args.batch} slides of {h} × {w} views")
    print("| k | batched: slides/s | one slide: µs per call |\n|---|---|---|")
    for k in args.ks:
        head = LogitHead(k=k)
        batched = jax.jit(jax.vmap(score_logits, in_axes=(None, 0, 0)))
        single = jax.jit(score_logits)
        tb = timed(batched, head, logits, masks, repeats=args.repeats)
        ts = timed(single, head, logits[0], masks[0], repeats=args.repeats)
        print(f"| {k} | {args.batch / tb:,.0f} | {ts * 1e6:,.0f} |")
    learned_rows(args, masks, rng)
    return 0


def learned_rows(args, masks, rng) -> None:
    """The learned head's rows: batched slides/s and µs per single-slide call (see the module doc)."""
    h, w = args.grid
    head = LearnedHead(params=init_params(jax.random.PRNGKey(0), args.dim, 64, 32), features_dim=args.dim)
    fb = min(args.feature_batch, args.batch)
    grids = jnp.asarray(rng.normal(size=(fb, h, w, args.dim)).astype(np.float32))
    terms = jax.jit(jax.vmap(head.view_terms))(grids)
    terms = jnp.concatenate([terms] * -(-args.batch // fb))[: args.batch]
    print(
        f"\nlearned head ({args.dim}-d features, 64 units): {h} × {w} views per slide\n"
        "| input | batch | batched: slides/s | one slide: µs per call |\n|---|---|---|---|"
    )
    by_features = jax.jit(jax.vmap(head.score))
    tb = timed(by_features, grids, masks[:fb], repeats=args.repeats)
    ts = timed(jax.jit(head.score), grids[0], masks[0], repeats=args.repeats)
    print(f"| feature grid (H, W, {args.dim}) | {fb} | {fb / tb:,.0f} | {ts * 1e6:,.0f} |")
    by_terms = jax.jit(jax.vmap(head.score_terms))
    tb = timed(by_terms, terms, masks, repeats=args.repeats)
    ts = timed(jax.jit(head.score_terms), terms[0], masks[0], repeats=args.repeats)
    print(f"| cached view terms (H, W, 2) | {args.batch} | {args.batch / tb:,.0f} | {ts * 1e6:,.0f} |")
    states = jax.vmap(lambda _: head.init_terms_state())(jnp.arange(args.batch))
    new = terms[:, :4, :4].reshape(args.batch, 16, 2)
    step = jax.jit(jax.vmap(lambda s, t, m: head.logit_terms(head.add_terms(s, t, m))))
    tb = timed(step, states, new, jnp.ones((args.batch, 16), bool), repeats=args.repeats)
    print(
        f"| incremental: 16 new views per slide | {args.batch} | {args.batch / tb:,.0f} (steps/s) | "
        f"{tb / args.batch * 1e6:,.1f} (per slide) |"
    )


if __name__ == "__main__":
    raise SystemExit(main())
