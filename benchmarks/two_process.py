"""The same PPO run as several processes on this machine (``jax.distributed`` over 127.0.0.1, gloo
CPU collectives), the slides split between them (``--shard-slides``): starts the processes,
waits (killing all of them on the first failure or after ``--timeout`` seconds), checks that
every process ends with the same parameters, and prints the figures.

    python benchmarks/two_process.py --compare-single

Each process gets ``--local-devices`` CPU devices (default 1), so the mesh has
``processes × local-devices`` devices and each process holds its devices' share of the slides.
``--compare-single`` also runs the same command as one process with all those devices (fake CPU
devices) and checks the parameters agree (``rtol=1e-5, atol=1e-7``).
Without ``--dataset`` a dataset of 8 small semi-synthetic slides is built in a temporary folder.
Exit status 0 when all checks pass.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from baselines.harness.distributed import cpu_child_env

ROOT = Path(__file__).resolve().parents[1]
PPO_ARGS = [
    "--env",
    "HistoJAX-Easy-v0",
    "--seeds",
    "1",
    "--num-envs",
    "8",
    "--set",
    "num_steps=16",
    "--set",
    "num_minibatches=2",
    "--set",
    "update_epochs=1",
    "--set",
    "hidden=32",
    "--set",
    "log_every=1",
]


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_all(commands: list[list[str]], envs: list[dict], logs: list[Path], timeout: float) -> list[int]:
    """Start every command, wait for all; on the first failure or at ``timeout`` seconds kill the
    others (each by its own process). Returns the exit codes (``-9`` for killed ones)."""
    procs = []
    for cmd, env, log in zip(commands, envs, logs):
        with open(log, "w") as f:
            procs.append(subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT))
    deadline = time.monotonic() + timeout
    try:
        while any(p.poll() is None for p in procs):
            failed = any(p.returncode not in (None, 0) for p in procs)
            if failed or time.monotonic() > deadline:
                break
            time.sleep(0.2)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return [p.returncode for p in procs]


def load_params(path: Path) -> list[np.ndarray]:
    """The parameter arrays of a checkpoint folder, in tree order."""
    import jax

    from baselines.harness.logs import load_checkpoint

    params, _ = load_checkpoint(path)
    return [np.asarray(a) for a in jax.tree.leaves(params)]


def tail(path: Path, n: int = 30) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-n:])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--local-devices", type=int, default=1, help="CPU devices per process")
    p.add_argument(
        "--dataset", default=None, help="a dataset folder (dataset.json); default: 8 small slides built here"
    )
    p.add_argument("--slides", nargs="*", default=None, help="bundle folders instead of --dataset")
    p.add_argument("--total-steps", type=int, default=384, help="env steps (3 PPO updates of 8 envs x 16 steps)")
    p.add_argument("--timeout", type=float, default=600.0, help="seconds before every process is killed")
    p.add_argument("--compare-single", action="store_true", help="also run as one process and compare")
    p.add_argument("--fast-compile", action="store_true", help="--xla_backend_optimization_level=0 (tests)")
    p.add_argument("--out", default=None, help="run folder (default: a temporary one)")
    args = p.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="histojax-two-process-"))
    out.mkdir(parents=True, exist_ok=True)
    if args.slides:
        env_kwargs = {"slides": [str(Path(s).resolve()) for s in args.slides]}
    elif args.dataset:
        env_kwargs = {"dataset": str(Path(args.dataset).resolve()), "split": "all"}
    else:
        from data_tools.datasets.synth.dataset import make_dataset

        ds = make_dataset(
            out / "dataset",
            n_slides=8,
            size=(320, 256),
            seed=0,
            tile_size=32,
            level_sets=(3,),
            progress=False,
            previews=False,
        )
        env_kwargs = {"slides": [str(out / "dataset" / s["bundle"]) for s in ds["slides"]]}
    n, local = args.processes, args.local_devices
    devices = n * local
    base = [
        sys.executable,
        "-m",
        "baselines.ppo",
        *PPO_ARGS,
        "--total-steps",
        str(args.total_steps),
        "--devices",
        str(devices),
        "--shard-slides",
        "--set",
        "env_kwargs=" + json.dumps(env_kwargs),
    ]
    port = free_port()
    commands = [
        base
        + [
            "--coordinator",
            f"127.0.0.1:{port}",
            "--num-processes",
            str(n),
            "--process-id",
            str(i),
            "--out",
            str(out / "multi"),
        ]
        for i in range(n)
    ]
    logs = [out / f"process-{i}.log" for i in range(n)]
    print(f"{n} processes x {local} CPU device(s), coordinator 127.0.0.1:{port}, logs in {out}", flush=True)
    t0 = time.perf_counter()
    codes = run_all(commands, [cpu_child_env(local, args.fast_compile)] * n, logs, args.timeout)
    wall = time.perf_counter() - t0
    if any(c != 0 for c in codes):
        for log, c in zip(logs, codes):
            print(f"--- {log.name} (exit {c}):\n{tail(log)}")
        print(f"FAILED: exit codes {codes} after {wall:.0f} s")
        return 1
    for log in logs:
        for line in log.read_text().splitlines():
            if " slide(s), " in line or line.endswith(" env steps/s") or " s; wrote " in line:
                print("  " + line)
    print(f"{n} processes finished in {wall:.1f} s (start, compile and train)")
    ok = True
    first = load_params(out / "multi")
    for i in range(1, n):
        other = load_params(out / "multi" / f"process-{i}")
        same = len(other) == len(first) and all(np.array_equal(a, b) for a, b in zip(first, other))
        print(
            f"process {i} parameters {'identical to' if same else 'DIFFER from'} process 0's "
            f"({sum(a.size for a in first):,} values)"
        )
        ok &= same
    if args.compare_single:
        log = out / "single.log"
        t0 = time.perf_counter()
        codes = run_all(
            [base + ["--out", str(out / "single")]], [cpu_child_env(devices, args.fast_compile)], [log], args.timeout
        )
        if codes != [0]:
            print(f"--- single process (exit {codes[0]}):\n{tail(log)}\nFAILED")
            return 1
        single = load_params(out / "single")
        diff = max(float(np.max(np.abs(a - b))) for a, b in zip(first, single))
        close = all(np.allclose(a, b, rtol=1e-5, atol=1e-7) for a, b in zip(first, single))
        print(
            f"one process with {devices} devices: {time.perf_counter() - t0:.1f} s; max |difference| of the "
            f"parameters {diff:.3g} ({'agree' if close else 'DISAGREE'})"
        )
        ok &= close
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
