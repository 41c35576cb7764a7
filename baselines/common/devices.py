"""Devices: the accelerator's memory (a rollout that cannot fit is refused before it runs) and sharding the env
batch over devices (``--devices N``)."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P


def device_memory_bytes() -> int:
    """Bytes of memory of the first device: its allocator's limit on a GPU / TPU, the host's RAM on the CPU."""
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 (a backend without memory stats)
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def check_rollout_memory(env, env_params, config) -> int:
    """Refuse, before compiling, a run whose rollout buffer cannot fit the device: one observation's bytes
    × ``num_steps`` × ``num_envs`` × the seeds run at once (``num_seeds`` with ``vmap_seeds``; ``config`` the
    trainer's typed config, e.g. :class:`~baselines.ppo.PPOConfig`), ×2 for the
    shuffled minibatch copy. Returns that estimate (bytes); raises ``ValueError`` naming the figures and
    what to lower when it exceeds the device's memory (:func:`device_memory_bytes`). E.g. ``glimpse:2`` on
    the full C16 set observes ~2.9 MB a step: 35 GB of rollouts at 64 envs × 64 steps × 3 seeds."""
    from histojax.reading.modes.glimpse import observation_bytes

    obs = observation_bytes(env, env_params)
    seeds = config.num_seeds if config.vmap_seeds else 1
    need = 2 * obs * config.num_steps * config.num_envs * seeds
    have = device_memory_bytes()
    if need > have:
        raise ValueError(
            f"the rollouts of this run need about {need / 2**30:.1f} GiB ({obs:,} bytes an observation "
            f"× num_steps {config.num_steps} × num_envs {config.num_envs} × {seeds} seed(s) at "
            f"once × 2), more than this device's {have / 2**30:.1f} GiB: lower num_envs / num_steps, "
            "set vmap_seeds=false, or observe less (e.g. a coarser glimpse level)"
        )
    return need


# ----------------------------------------------------------------------------- devices
def batch_mesh(devices: int | None, num_envs: int) -> Mesh | None:
    """A 1-D ``Mesh`` named ``"batch"`` over the first ``devices`` of ``jax.devices()`` (all
    hosts' devices after ``jax.distributed.initialize()``), or None for ``devices=None``."""
    if devices is None:
        return None
    n, available = int(devices), jax.devices()
    if n < 1:
        raise ValueError(f"devices must be >= 1, got {n}")
    if num_envs % n:
        raise ValueError(f"num_envs={num_envs} must divide by devices={n} (each device steps num_envs / devices envs)")
    if n > len(available):
        raise ValueError(
            f"devices={n} but only {len(available)} {available[0].platform} device(s) are visible; on "
            f"CPU set XLA_FLAGS=--xla_force_host_platform_device_count={n} before jax is imported "
            f"(several hosts: call jax.distributed.initialize() first)"
        )
    return Mesh(np.array(available[:n]), ("batch",))


def shard_batch(mesh: Mesh | None, tree, axis: int = 0):
    """Constrain every array of ``tree`` to be split over ``mesh``'s devices along ``axis`` (the
    env batch). Identity for ``mesh=None``. Under ``jax.vmap`` over seeds JAX inserts the seed
    axis, unconstrained, in front of the spec, so ``axis`` counts the unbatched dimensions."""
    if mesh is None:
        return tree
    sharding = NamedSharding(mesh, P(*([None] * axis), "batch"))
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, sharding), tree)


def replicate_on(mesh: Mesh, tree):
    """Every leaf of ``tree`` replicated on ``mesh``'s devices, except jax arrays already split
    over exactly those devices (a sharded dataset), which are kept as they are."""
    devices = set(mesh.devices.flat)
    replicated = NamedSharding(mesh, P())

    def put(x):
        if isinstance(x, jax.Array) and x.sharding.device_set == devices and not x.sharding.is_fully_replicated:
            return x
        # a Python scalar as a weakly typed jax array first: with several processes device_put compares
        # the value across processes, and a Python float (float64) never equals its float32 copy
        return jax.device_put(jnp.asarray(x) if isinstance(x, (bool, int, float)) else x, replicated)

    return jax.tree.map(put, tree)
