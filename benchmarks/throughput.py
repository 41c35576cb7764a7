"""Steps per second of the jitted, vmapped environment on the embedded sample slide.

Prints, for batch sizes 1, 64, 1024, 4096 (``lax.scan`` over ``vmap(step)``, random actions,
auto-reset on): the full step with pixel observations, and the reward path alone (actions,
clamping and the summed-area-table reward, no observation). The machine's numpy memory-copy
bandwidth is measured in the same run as the reference for the pixel path (which is
memory-bound: each step copies a 128×128×3 view).

    python benchmarks/throughput.py [--env HistoJAX-Hard-v0] [--batches 1 64 1024 4096] [--seconds 1.0]
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import histojax
from data_tools.cli_output import command_main, positive_float
from histojax.core import actions as act
from histojax.core.views import view_tumour_fraction


def memcpy_bandwidth(nbytes: int = 256 * 2**20, repeats: int = 5) -> float:
    """Best-of numpy copy bandwidth in bytes/s (read + write of ``nbytes``, counted once)."""
    src = np.random.default_rng(0).integers(0, 255, nbytes, dtype=np.uint8)
    dst = np.empty_like(src)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - t0)
    return nbytes / best


def full_step_rollout(env, batch: int, steps: int):
    """A jitted ``(key, params) -> (checksum, last observations)`` running ``steps`` steps of
    ``batch`` envs (any obs mode). Each step's observation batch is written into the scan carry,
    so XLA must materialise every view of every step (reading only a part of it would let XLA
    gather just that part), without adding a reduction over the pixels to the timed work."""

    def run(key, params):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, batch), params)

        def body(carry, key):
            state, _, checksum = carry
            a = jax.random.randint(key, (batch,), 0, 7)
            obs, state, reward, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, batch), state, a, params
            )
            return (state, obs, checksum + reward.sum()), None

        carry, _ = jax.lax.scan(body, (state, obs, jnp.float32(0)), jax.random.split(key, steps))
        return carry[2], carry[1]

    return jax.jit(run)


def reward_path_rollout(env, batch: int, steps: int):
    t, n = env.tile_size, env.n_levels

    def run(key, params):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, batch), params)
        s = params.slide

        def one(z, x, y, a):
            dx, dy, dz = act.discrete_deltas(a, jnp.int32(t))
            z, x, y = act.move_and_zoom(s, z, x, y, dx, dy, dz, t, n)
            return z, x, y, view_tumour_fraction(s, z, x, y, t)

        def body(carry, key):
            (z, x, y), total = carry
            a = jax.random.randint(key, (batch,), 0, 7)
            z, x, y, f = jax.vmap(one)(z, x, y, a)
            return ((z, x, y), total + f.sum()), None

        return jax.lax.scan(body, ((state.z, state.x, state.y), jnp.float32(0)), jax.random.split(key, steps))[0][1]

    return jax.jit(run)


def measure(make_fn, env, params, batch: int, seconds: float) -> float:
    """Steps/s of ``make_fn(env, batch, steps)`` after compiling, timed for at least ``seconds``."""
    steps = max(10, int(200_000 / batch))
    fn = make_fn(env, batch, steps)
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(fn(key, params))  # compile
    calls, t0 = 0, time.perf_counter()
    while True:
        jax.block_until_ready(fn(jax.random.fold_in(key, calls), params))
        calls += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return calls * steps * batch / elapsed


def add_arguments(p) -> None:
    """The options of ``python benchmarks/throughput.py`` and ``histojax bench``."""
    p.add_argument("--env", default="HistoJAX-Hard-v0")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 4096])
    p.add_argument("--seconds", type=positive_float, default=1.0, help="minimum timed seconds per measurement")


def run(args, parser=None) -> int:
    """Measure and print the throughput table for parsed ``args``."""
    env, params = histojax.make(args.env)
    view_bytes = env.tile_size**2 * 3
    bandwidth = memcpy_bandwidth()
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"JAX {jax.__version__} on {jax.devices()[0].platform}"
    )
    print(f"{args.env} on CMU-1-Small-Region ({env.n_levels} levels, {env.tile_size} px views)")
    print(f"numpy memory copy: {bandwidth / 1e9:.2f} GB/s")
    lean = dataclasses.replace(env, final_observation=False)  # one view per step instead of two
    print("pixels: full step with auto-reset (two views per step: the next and info['final_observation']);")
    print("lean: final_observation=False (one view per step); view GB/s counts the views extracted")
    print(
        f"{'batch':>6} {'pixels steps/s':>15} {'lean steps/s':>13} {'lean view GB/s':>15} {'of memcpy':>10} "
        f"{'reward-only steps/s':>20}"
    )
    for batch in args.batches:
        sps = measure(full_step_rollout, env, params, batch, args.seconds)
        lps = measure(full_step_rollout, lean, params, batch, args.seconds)
        rps = measure(reward_path_rollout, env, params, batch, args.seconds)
        gbs = lps * view_bytes
        print(f"{batch:>6} {sps:>15,.0f} {lps:>13,.0f} {gbs / 1e9:>15.2f} {gbs / bandwidth:>10.1%} {rps:>20,.0f}")
    return 0


main = command_main(add_arguments, run, "python benchmarks/throughput.py", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
