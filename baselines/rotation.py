"""Datasets larger than device memory: PPO with ``K`` slides resident on the device, the resident
set rotated between phases of updates, the next set loaded while the current one trains.

    python -m baselines.rotation --env HistoJAX-Easy-v0 --set env_kwargs='{"dataset": "DS"}' --resident 2 --rotate-every 4 --budget-mb 64 --seeds 1 --out runs/rotation

How it works (:func:`train_rotating`):

* **Host store.** ``source="memory"`` loads every slide once into host RAM (numpy; nothing of it
  stays on the device); ``source="disk"`` keeps only paths and reads each set's bundles when that
  set is built (a first pass reads every bundle once to learn the array shapes).
* **Sets.** The slides, shuffled once (``seed``), are cut into sets of ``K`` (the last wraps around
  to the first slides); phase ``r`` trains on set ``r mod n_sets``. Every set is packed
  (:func:`histojax.loading.stack_slides`) and padded to one *capacity* shape — the largest over the
  sets — so the jitted phase compiles once.
* **Device bound.** At most two sets are on the device: the one training and the next one. The
  bound is ``2 × set bytes`` (the capacity's bytes), checked against ``budget_bytes`` before any
  data moves (``K=None`` picks the largest ``K`` that fits). Measured while training: the bytes of
  the resident sets' device buffers and of every live jax array at each rotation's peak (both
  sets resident), and ``memory_stats()["peak_bytes_in_use"]`` where the device reports it (GPUs).
* **Prefetch.** Phase ``r`` is dispatched (asynchronously), then a worker thread builds set
  ``r + 1`` (host load, pack, ``jax.device_put``) while it runs; the loop waits for phase ``r``
  before the next prefetch, so a third set is never allocated.
* **Phases.** Each phase resets the envs on its set (episodes in progress at a rotation are
  dropped, like time limits) and runs ``rotate_every`` PPO updates (the trainer's ``update`` in the
  harness's loop, :func:`baselines.harness.runner.scan_updates`); parameters, optimizer state and the
  learning-rate schedule carry over. ``total_timesteps`` is rounded up to whole phases.

One device only (no ``devices`` / ``shard_slides``); every seed trains on the same sets.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import gc
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from baselines import ppo
from baselines.common.config import ConfigError, env_overrides
from baselines.harness.runner import finish_run, scan_updates
from data_tools.cli_output import command_main, print_error
from histojax.core.slide import SlideArrays
from histojax.loading import stack_slides
from histojax.registry import make, slide_paths
from histojax.sharding import PER_SLIDE, host_leaves, on_host, pad_leaf


def live_device_bytes(device=None) -> int:
    """Bytes of the distinct buffers of every live jax array on ``device`` (default: the first
    device). Buffers are counted once by address: an array's shard views alias its buffer."""
    device = device or jax.devices()[0]
    buffers = {}
    for a in jax.live_arrays():
        for s in a.addressable_shards:
            if s.device == device and not a.is_deleted():
                buffers[s.data.unsafe_buffer_pointer()] = int(s.data.nbytes)
    return sum(buffers.values())


def tree_bytes(tree) -> int:
    """Total ``nbytes`` of the arrays of a pytree."""
    return sum(int(a.nbytes) for a in jax.tree.leaves(tree))


class SlideStore:
    """The dataset's slides on the host: ``get(i)`` is slide ``i`` as a single-slide
    ``SlideArrays`` of numpy arrays; ``shapes[i]`` its leaves' shapes by field name."""

    def __init__(self, env_id: str, paths: list, source: str = "memory", **overrides):
        if source not in ("memory", "disk"):
            raise ValueError(f"source must be 'memory' or 'disk', got {source!r}")
        self.env_id, self.paths, self.source, self.overrides = env_id, [str(p) for p in paths], source, overrides
        self.cache, self.shapes = {}, []
        for i in range(len(self.paths)):
            slide = self._load(i)
            self.shapes.append({k: v.shape for k, v in host_leaves(slide).items()})
            if source == "memory":
                self.cache[i] = slide

    def _load(self, i: int) -> SlideArrays:
        with on_host():  # the CPU device: host memory, never the accelerator
            _, params = make(self.env_id, slide=self.paths[i], **self.overrides)
        leaves = host_leaves(params.slide)
        return SlideArrays(**{f.name: leaves.get(f.name) for f in dataclasses.fields(SlideArrays)})

    def get(self, i: int) -> SlideArrays:
        """Slide ``i`` (numpy leaves), from RAM or read from its bundle now."""
        return self.cache[i] if self.source == "memory" else self._load(i)

    def nbytes(self) -> int:
        """Bytes of all slides' arrays (the dataset as it would sit on one device)."""
        dtypes = {k: v.dtype for k, v in host_leaves(self.get(0)).items()}
        return sum(math.prod(s) * dtypes[k].itemsize for shapes in self.shapes for k, s in shapes.items())


def plan_sets(num_slides: int, k: int, seed: int = 0) -> list[list[int]]:
    """Slide indices of each resident set: a permutation (``seed``) cut into sets of ``k``, the
    last wrapping around to the first slides."""
    if not 1 <= k <= num_slides:
        raise ValueError(f"resident slides K={k} must be between 1 and the dataset's {num_slides} slides")
    perm = np.random.default_rng(seed).permutation(num_slides).tolist()
    return [[perm[(s * k + j) % num_slides] for j in range(k)] for s in range(math.ceil(num_slides / k))]


def capacity(store: SlideStore, sets: list[list[int]]) -> dict[str, tuple]:
    """The padded leaf shapes every set fits: per-slide arrays ``(K, *largest)``, flat pools the
    largest sum of rows over the sets."""
    k, cap = len(sets[0]), {}
    for name in store.shapes[0]:
        if name in PER_SLIDE:
            shapes = np.array([shapes[name] for shapes in store.shapes], np.int64).reshape(len(store.shapes), -1)
            cap[name] = (k, *(int(v) for v in shapes.max(axis=0)))
        else:
            rows = max(sum(store.shapes[i][name][0] for i in s) for s in sets)
            cap[name] = (int(rows), *store.shapes[0][name][1:])
    cap["slide_logits"] = (k,)
    return cap


def capacity_bytes(store: SlideStore, cap: dict) -> int:
    """Bytes of one set packed to ``cap``."""
    leaves = host_leaves(store.get(0))
    itemsize = {k: v.dtype.itemsize for k, v in leaves.items()} | {"slide_logits": 4}
    return sum(math.prod(s) * itemsize[k] for k, s in cap.items())


def choose_resident(store: SlideStore, budget_bytes: int, k: int | None, seed: int = 0):
    """``(K, sets, cap, set_bytes)``: with ``k=None`` the largest ``K`` whose two sets fit in
    ``budget_bytes``; raises ``ValueError`` when even ``K=1`` (or the given ``k``) does not."""
    candidates = [k] if k is not None else range(len(store.paths), 0, -1)
    for kk in candidates:
        sets = plan_sets(len(store.paths), kk, seed)
        cap = capacity(store, sets)
        nbytes = capacity_bytes(store, cap)
        if 2 * nbytes <= budget_bytes:
            return kk, sets, cap, nbytes
    raise ValueError(
        f"two resident sets of K={candidates[-1]} slide(s) need {2 * nbytes:,} bytes on the device, "
        f"more than the budget of {budget_bytes:,}: use fewer resident slides or a larger budget"
    )


def build_set(store: SlideStore, indices: list[int], cap: dict, device) -> SlideArrays:
    """The slides ``indices`` stacked, padded to ``cap`` and put on ``device`` (asynchronous)."""
    with on_host():
        stacked = stack_slides([store.get(i) for i in indices])
    leaves = host_leaves(stacked)
    del stacked
    padded = {name: pad_leaf(a, cap[name], name) for name, a in leaves.items()}
    return jax.device_put(SlideArrays(**{f.name: padded.get(f.name) for f in dataclasses.fields(SlideArrays)}), device)


def train_rotating(
    config,
    budget_bytes: int,
    resident: int | None = None,
    rotate_every: int = 4,
    source: str = "memory",
    keys=None,
    set_seed: int = 0,
) -> dict:
    """PPO (``config`` as :func:`baselines.ppo.make_train`: a :class:`~baselines.ppo.PPOConfig` or its dict) on a dataset with at most two sets of
    ``resident`` slides on the device (see the module doc). The dataset is the one ``config``
    names (``slide`` / ``env_kwargs`` ``slides`` or ``dataset``). Returns ``{"params",
    "metrics": {name: (seeds, updates)}, "rotation": {measured bytes and the plan}, "env",
    "env_params" (on set 0), "config" (the record of the config trained, as ``config.json`` holds it)}``."""
    config = ppo.PPOConfig.coerce(config, where="rotation.train_rotating")
    if config.devices is not None or config.shard_slides:
        raise ValueError("rotating slides runs on one device (no devices / shard_slides)")
    kw = env_overrides(config)
    paths = slide_paths(
        config.env_id,
        slide=config.slide,
        slides=kw.pop("slides", None),
        dataset=kw.pop("dataset", None),
        split=kw.pop("split", "train"),
        fold=kw.pop("fold", None),
        **kw,
    )
    store = SlideStore(config.env_id, paths, source=source, **kw)
    k, sets, cap, set_bytes = choose_resident(store, budget_bytes, resident, set_seed)
    batch = config.num_envs * config.num_steps
    num_updates = max(1, config.total_timesteps // batch)
    phases = math.ceil(num_updates / rotate_every)
    env_kwargs = {a: b for a, b in (config.env_kwargs or {}).items() if a not in ("slides", "dataset", "split", "fold")}
    config = config.replace(total_timesteps=phases * rotate_every * batch, slide=paths[0], env_kwargs=env_kwargs)
    with on_host():  # the env and the jittable pieces; their own env params (one slide) stay off the accelerator
        train = ppo.make_train(config)
    device = jax.devices()[0]
    base = train.env_params
    num_seeds = config.num_seeds
    keys = jax.random.split(jax.random.PRNGKey(config.seed or 0), num_seeds) if keys is None else keys

    @jax.jit
    def init_states(keys, env_params):
        params = jax.lax.map(lambda kk: train.init_params(kk, env_params), keys)
        return jax.vmap(lambda kk, p: train.init_runner(kk, env_params, p)[0])(keys, params)  # the train states

    def run_phase(state, key, env_params, first_update):
        """``rotate_every`` updates of one seed's train state from freshly reset envs (the harness's loop,
        :func:`~baselines.harness.runner.scan_updates`): ``(state, key, metrics)``."""
        _, env_state, obs0, key = train.init_runner(key, env_params, state.params)
        runner, metrics = scan_updates(
            lambda c, i: train.update(c, i, env_params), (state, env_state, obs0, key), first_update, rotate_every, None
        )
        return runner[0], runner[3], metrics

    @jax.jit
    def phase(states, keys, env_params, first_update):
        return jax.vmap(lambda s, kk: run_phase(s, kk, env_params, first_update))(states, keys)

    # before any set: the trainer's own arrays (on a CPU-only machine also make_train's one slide, which
    # on an accelerator stays on the host)
    gc.collect()  # unreachable arrays of earlier work would count here and vanish mid-run (seen in the test suite)
    baseline = live_device_bytes(device)
    t0 = time.perf_counter()
    current = build_set(store, sets[0], cap, device)
    states = init_states(keys, base.replace(slide=current))
    jax.block_until_ready(states)
    state_bytes = tree_bytes(states) + tree_bytes(keys)
    compiled = phase.lower(states, keys, base.replace(slide=current), jnp.int32(0)).compile()
    compile_seconds = time.perf_counter() - t0
    resident_peak, live_peak, metrics = tree_bytes(current), 0, []
    t0 = train.progress.t0 = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        for r in range(phases):
            states, keys, m = compiled(states, keys, base.replace(slide=current), jnp.int32(r * rotate_every))  # async
            nxt = pool.submit(build_set, store, sets[(r + 1) % len(sets)], cap, device) if r + 1 < phases else None
            metrics.append(m)
            jax.block_until_ready((states, m))  # phase r done before set r + 2 may be built
            if nxt is not None:
                nxt = jax.block_until_ready(nxt.result())
                resident_peak = max(resident_peak, tree_bytes(current) + tree_bytes(nxt))
                live_peak = max(live_peak, live_device_bytes(device))
                current = nxt
                del nxt
    train_seconds = time.perf_counter() - t0
    stats = device.memory_stats() or {}
    metrics = jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a], axis=1), *metrics)
    rotation = {
        "budget_bytes": int(budget_bytes),
        "num_slides": len(paths),
        "resident_slides": k,
        "sets": sets,
        "rotate_every": rotate_every,
        "phases": phases,
        "set_bytes": int(set_bytes),
        "bound_bytes": int(2 * set_bytes),
        "dataset_bytes": int(store.nbytes()),
        "resident_peak_bytes": int(resident_peak),
        "live_peak_bytes": int(live_peak),
        "baseline_bytes": int(baseline),
        "train_state_bytes": int(state_bytes),
        "source": source,
        "device_peak_bytes_in_use": stats.get("peak_bytes_in_use"),
        "train_seconds": train_seconds,
        "compile_seconds": compile_seconds,
        "env_steps_per_second": phases * rotate_every * batch * num_seeds / train_seconds,
    }
    return {
        "params": states.params,
        "metrics": metrics,
        "rotation": rotation,
        "env": train.env,
        "env_params": base.replace(slide=current),
        "config": config.as_dict(),
        "steps_per_update": batch,
    }


def add_arguments(p) -> None:
    """The options of ``python -m baselines.rotation`` and ``histojax rotation``: the rotation flags,
    then every flag of ``python -m baselines.ppo`` (:func:`baselines.ppo.add_arguments`)."""
    own = p.add_argument_group("rotation flags")
    own.add_argument("--resident", type=int, default=None, help="slides on the device per set (default: most that fit)")
    own.add_argument("--rotate-every", type=int, default=4, help="PPO updates per resident set")
    own.add_argument("--budget-mb", type=float, default=None, help="device MiB for the two resident sets (required)")
    own.add_argument("--source", default="memory", choices=("memory", "disk"), help="host RAM or read bundles per set")
    ppo.add_arguments(p.add_argument_group("PPO flags"))


def run(args, parser) -> int:
    """Train PPO with rotating resident sets on parsed ``args``; writes the run folder."""
    if args.budget_mb is None:
        parser.error("--budget-mb is required")
    if args.coordinator is not None or args.distributed:
        raise SystemExit("baselines.rotation runs in one process (no --coordinator / --distributed)")
    try:
        config = ppo.PPOConfig.from_dict(ppo.config_from_args(args), where="the options (--set)")
    except ConfigError as e:
        return print_error(e)
    out = Path(args.out or f"runs/rotation-{config.env_id}")
    result = train_rotating(config, int(args.budget_mb * 2**20), args.resident, args.rotate_every, args.source)
    rot = result["rotation"]
    print(
        f"resident sets: K={rot['resident_slides']} of {rot['num_slides']} slides, {rot['phases']} phases of "
        f"{rot['rotate_every']} updates; dataset {rot['dataset_bytes']:,} bytes, budget {rot['budget_bytes']:,}, bound {rot['bound_bytes']:,}, resident peak {rot['resident_peak_bytes']:,}, "
        f"all live arrays at peak {rot['live_peak_bytes']:,} (before the first set {rot['baseline_bytes']:,}, "
        f"train state {rot['train_state_bytes']:,})"
    )
    finish_run(
        "ppo",
        result["config"],
        out,
        result["params"],
        result["metrics"],
        result["steps_per_update"],
        rot["train_seconds"],
        rot["compile_seconds"],
        env_and_params=(result["env"], result["env_params"]),
    )
    return 0


main = command_main(add_arguments, run, "python -m baselines.rotation", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
