"""A warm second start: compile seconds of the demo's PPO and of a reader's PPO, each compiled twice, a fresh
process each time, first with an empty JAX persistent compilation cache (:mod:`histojax.compile_cache`), then
with the cache the first process left.

    python -m benchmarks.compile_cache [--json out.json] [--updates 2]

* ``demo PPO``: the demo's trainer settings (``HistoJAX-Easy-v0``, pixels + position, 64 envs × 64 steps,
  1 seed) for ``--updates`` updates on the sample slide;
* ``reader PPO``: the cell-set reader (``glimpse`` with ``step_obs=True``, the ``-v2`` ids, feature
  observations) on the training split of a small semi-synthetic dataset built first in a temporary folder
  (8 slides, 320 × 256 px, colour-stats features), 32 envs.

Each fresh process makes the trainer from those options exactly as ``python -m baselines.ppo`` does, with the
cache turned on as the command line turns it on, and compiles its whole training program ahead of time
(:func:`baselines.harness.runner.compile_seeds`) without running it: compile seconds are that call, whole-process seconds include the
imports and building the env. The cache lives in a temporary folder (``HISTOJAX_COMPILE_CACHE``), so the
user's cache is not touched. Prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

from baselines import ppo
from baselines.harness.runner import compile_seeds
from data_tools.datasets.synth.dataset import make_dataset
from data_tools.features.grid import compute_features
from histojax import compile_cache

STEPS_PER_UPDATE = {"demo PPO": 64 * 64, "reader PPO": 32 * 64}


def build_reader_dataset(root: Path) -> Path:
    """A small semi-synthetic dataset with colour-stats feature grids in ``root`` (seconds); returns ``root``."""
    ds = make_dataset(
        root,
        n_slides=4,
        negatives=4,
        size=(320, 256),
        seed=0,
        tile_size=32,
        level_sets=(3,),
        progress=False,
        previews=False,
    )
    for s in ds["slides"]:
        compute_features(root / s["bundle"], encoder_name="colour-stats", batch=64, progress=False, dtype="float32")
    return root


def trainer_argv(case: str, dataset: Path, updates: int) -> list[str]:
    """The ``python -m baselines.ppo`` options of ``case`` for ``updates`` updates."""
    common = ["--seeds", "1", "--total-steps", str(updates * STEPS_PER_UPDATE[case]), "--set", "print_progress=false"]
    if case == "demo PPO":
        return ["--env", "HistoJAX-Easy-v0", "--with-position", "--num-envs", "64", *common]
    return [
        "--env",
        "HistoJAX-Easy-v0",
        "--dataset",
        str(dataset),
        "--split",
        "train",
        "--action-mode",
        "glimpse:1",
        "--obs",
        "features",
        "--num-envs",
        "32",
        "--set",
        'env_kwargs={"step_obs": true, "task": "classification", "read_budget": 0.3}',
        *common,
    ]


def child(argv: list[str]) -> None:
    """In a fresh process: the cache on (as the command line turns it on), the trainer config of ``argv`` made and
    its whole training program compiled ahead of time; prints ``{"compile_seconds", "make_seconds"}`` as JSON."""
    compile_cache.setup([])
    config = ppo.PPOConfig.from_dict(ppo.config_from_args(ppo.parse_args(argv)), where="the options (--set)")
    t0 = time.perf_counter()
    train = ppo.make_train(config)
    make_s = time.perf_counter() - t0
    keys = jax.random.split(jax.random.PRNGKey(0), config.num_seeds)
    t0 = time.perf_counter()
    compile_seeds(train, keys)
    print(json.dumps({"compile_seconds": time.perf_counter() - t0, "make_seconds": make_s}))


def run_once(argv: list[str], cache: Path) -> dict:
    """:func:`child` on trainer options ``argv`` in a fresh process with the cache in ``cache``: compile seconds,
    whole-process seconds, cache entries after."""
    env = {k: v for k, v in os.environ.items() if k != compile_cache.OFF_ENV}
    env[compile_cache.DIR_ENV] = str(cache)
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks.compile_cache", "--child", *argv], env=env, capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"compiling {' '.join(argv)} failed:\n{r.stderr[-3000:]}")
    row = json.loads(r.stdout.strip().splitlines()[-1])
    return {**row, "wall_seconds": wall, "cache_entries": sum(1 for _ in cache.iterdir()) if cache.is_dir() else 0}


def main(argv=None) -> int:
    """Measure both cases (empty, then warm cache), print the table, write ``--json`` if given."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--child"]:
        child(argv[1:])
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--updates", type=int, default=2, help="PPO updates per run (default 2)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="histojax-compile-cache-") as tmp:
        tmp = Path(tmp)
        dataset = build_reader_dataset(tmp / "dataset")
        for case in ("demo PPO", "reader PPO"):
            cache = tmp / f"cache-{case.split()[0]}"
            for start in ("empty cache", "warm cache"):
                row = {"case": case, "start": start, **run_once(trainer_argv(case, dataset, args.updates), cache)}
                rows.append(row)
                print(
                    f"{case:<11} {start:<12} compile {row['compile_seconds']:6.1f} s   whole process "
                    f"{row['wall_seconds']:6.1f} s   cache entries {row['cache_entries']}",
                    flush=True,
                )
    result = {
        "rows": rows,
        "updates": args.updates,
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
