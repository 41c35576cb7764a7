"""Steps per second of the numpy-facing bridges, batched against one-env-at-a-time.

Prints env steps per second (random actions, pixel observations, host numpy arrays out) of
Gymnasium's ``SyncVectorEnv`` over ``GymnasiumEnv``\\ s against ``GymnasiumVectorEnv`` (one jitted
``vmap``), and, with the ``sb3`` extra, SB3's ``DummyVecEnv`` over ``GymnasiumEnv``\\ s against
``SB3VecEnv``. Both pairs give the same arrays for the same seeds and actions (tests/adapters/test_gymnasium.py,
tests/adapters/test_sb3.py); only the speed differs.

    python benchmarks/integrations.py [--env HistoJAX-Easy-v0] [--num-envs 16] [--seconds 2.0]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import gymnasium
import numpy as np

import histojax
from histojax.adapters.gymnasium import GymnasiumEnv, GymnasiumVectorEnv


def steps_per_second(venv, n: int, seconds: float, sb3: bool) -> float:
    """Env steps per second over at least ``seconds`` after two warm-up steps (compilation)."""
    if sb3:
        venv.seed(0)
        venv.reset()
    else:
        venv.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(2):
        venv.step(rng.integers(0, 7, n))
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        venv.step(rng.integers(0, 7, n))
        steps += n
    return steps / (time.perf_counter() - start)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="HistoJAX-Easy-v0")
    p.add_argument("--num-envs", type=int, default=16)
    p.add_argument("--seconds", type=float, default=2.0)
    args = p.parse_args()
    env, params = histojax.make(args.env)
    n = args.num_envs
    print(f"{args.env}, {n} envs, pixels; {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    rows = [
        (
            "gymnasium SyncVectorEnv(GymnasiumEnv x n)",
            lambda: gymnasium.vector.SyncVectorEnv([lambda: GymnasiumEnv(env, params) for _ in range(n)]),
            False,
        ),
        ("histojax GymnasiumVectorEnv", lambda: GymnasiumVectorEnv(env, n, params), False),
    ]
    try:
        from stable_baselines3.common.vec_env import DummyVecEnv

        from histojax.adapters.sb3 import SB3VecEnv

        rows += [
            (
                "sb3 DummyVecEnv(GymnasiumEnv x n)",
                lambda: DummyVecEnv([lambda: GymnasiumEnv(env, params) for _ in range(n)]),
                True,
            ),
            ("histojax SB3VecEnv", lambda: SB3VecEnv(env, n, params), True),
        ]
    except ImportError:
        print("(stable-baselines3 not installed: pip install -e '.[sb3]' for the SB3 rows)")
    for name, build, sb3 in rows:
        print(f"{name:45s} {steps_per_second(build(), n, args.seconds, sb3):10.0f} steps/s")


if __name__ == "__main__":
    main()
