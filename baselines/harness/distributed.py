"""Several processes (hosts) training one program: ``jax.distributed`` set up from the command line.

Every process runs the same command with its own ``--process-id``; ``--coordinator`` is the
``host:port`` of process 0 (reachable from all). On GPU clusters under SLURM or Open MPI,
``--distributed`` lets ``jax.distributed.initialize()`` find all of that itself. CPU processes
talk through gloo collectives (``jax_cpu_collectives_implementation``); GPUs use NCCL.
After it, ``jax.devices()`` lists every process's devices and a ``Mesh`` over them spans hosts
(see docs/scaling.md).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

ROOT = Path(__file__).resolve().parents[1]


def initialize(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    timeout_s: int = 300,
) -> None:
    """``jax.distributed.initialize`` (before any other JAX call), with gloo CPU collectives so a
    CPU mesh can span processes. ``coordinator=None``: cluster auto-detection (SLURM, Open MPI,
    ...); else ``num_processes`` and ``process_id`` are required. Raises ``ValueError`` naming
    the missing argument; waits at most ``timeout_s`` seconds for the other processes."""
    if coordinator is not None and (num_processes is None or process_id is None):
        raise ValueError("--coordinator needs --num-processes and --process-id too")
    if coordinator is not None and not 0 <= int(process_id) < int(num_processes):
        raise ValueError(f"--process-id must be in [0, {num_processes}), got {process_id}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=int(timeout_s),
    )


def add_arguments(parser) -> None:
    """The ``--coordinator`` / ``--num-processes`` / ``--process-id`` / ``--distributed`` flags."""
    parser.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="several processes: address of process 0's coordinator (jax.distributed)",
    )
    parser.add_argument("--num-processes", type=int, default=None, help="with --coordinator: how many processes")
    parser.add_argument("--process-id", type=int, default=None, help="with --coordinator: this process, 0 .. N-1")
    parser.add_argument(
        "--distributed",
        action="store_true",
        help="several processes, found by jax.distributed.initialize() itself (SLURM, Open MPI)",
    )


def from_args(args) -> bool:
    """Initialise from parsed flags (:func:`add_arguments`); True when several processes run."""
    if getattr(args, "coordinator", None) is None and not getattr(args, "distributed", False):
        return False
    initialize(args.coordinator, args.num_processes, args.process_id)
    return True


def cpu_child_env(devices: int, fast_compile: bool = False) -> dict:
    """Environment for a child Python process on CPU with ``devices`` fake CPU devices
    (``--xla_force_host_platform_device_count``; ``fast_compile`` adds
    ``--xla_backend_optimization_level=0``) and this repository importable."""
    flags = [os.environ.get("XLA_FLAGS", ""), f"--xla_force_host_platform_device_count={devices}"]
    if fast_compile:
        flags.append("--xla_backend_optimization_level=0")
    return {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": " ".join(flags).strip(),
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
