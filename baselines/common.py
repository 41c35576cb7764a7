"""Shared by the trainers: making the env from a config, episode statistics, progress printing,
checkpoints (flax.serialization msgpack), logs (CSV / JSON), learning-curve PNGs (Pillow) and
sharding the env batch over devices (``--devices N``)."""
from __future__ import annotations

import csv
import dataclasses
import functools
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import histojax
from baselines import distributed, outputs
from data_tools.cli_output import build_parser, command_main, positive_float
from data_tools.errors import HistojaxDataError
from histojax.adapters.jax import LogWrapper
from baselines.curves import plot_curves  # noqa: F401  (the learning-curve PNG; kept here for callers)


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """The settings every trainer shares: which trainer, and the env it trains on (spelled as
    ``histojax.make`` spells them). Each algorithm file's config (``PPOConfig``, ``DQNConfig``) adds its own."""

    algo: str = ""                       # the trainer (recorded in config.json)
    env_id: str = "HistoJAX-Easy-v0"     # registered env id
    slide: str | None = None             # bundle folder; None: the id's slide (the sample slide)
    action_mode: str = "discrete"        # the env's action_mode
    obs_mode: str = "pixels"             # the env's obs_mode
    with_position: bool = False          # observation dict with the view position
    reward: str | None = None            # reward preset; None: the env's
    max_steps_in_episode: int | None = None  # None: the id's
    env_kwargs: dict | None = None       # any other histojax.make keyword


OLDER_SPELLINGS = {"obs": "obs_mode"}  # config keys of older runs → the env's spelling


def canonical_config(config: dict) -> dict:
    """``config`` with older key spellings renamed to the env's (``obs`` → ``obs_mode``); a copy."""
    out = dict(config)
    for old, new in OLDER_SPELLINGS.items():
        if old in out:
            value = out.pop(old)
            out.setdefault(new, value)
    return out


def env_overrides(config: dict) -> dict:
    """The ``histojax.make`` overrides named in a trainer config."""
    kw = {"action_mode": config.get("action_mode", "discrete"),
          "with_position": bool(config.get("with_position", False))}
    obs = canonical_config(config).get("obs_mode", "pixels")
    if obs != "pixels":
        kw["obs_mode"] = obs  # e.g. "features" once the env has it
    for k in ("reward", "max_steps_in_episode"):
        if config.get(k) is not None:
            kw[k] = config[k]
    kw.update(config.get("env_kwargs") or {})
    return kw


def device_memory_bytes() -> int:
    """Bytes of memory of the first device: its allocator's limit on a GPU / TPU, the host's RAM on the CPU."""
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 (a backend without memory stats)
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def check_rollout_memory(env, env_params, config: dict) -> int:
    """Refuse, before compiling, a run whose rollout buffer cannot fit the device: one observation's bytes
    × ``num_steps`` × ``num_envs`` × the seeds run at once (``num_seeds`` with ``vmap_seeds``), ×2 for the
    shuffled minibatch copy. Returns that estimate (bytes); raises ``ValueError`` naming the figures and
    what to lower when it exceeds the device's memory (:func:`device_memory_bytes`). E.g. ``glimpse:2`` on
    the full C16 set observes ~2.9 MB a step: 35 GB of rollouts at 64 envs × 64 steps × 3 seeds."""
    from histojax.reading.modes.glimpse import observation_bytes

    obs = observation_bytes(env, env_params)
    seeds = config.get("num_seeds", 1) if config.get("vmap_seeds", True) else 1
    need = 2 * obs * config["num_steps"] * config["num_envs"] * seeds
    have = device_memory_bytes()
    if need > have:
        raise ValueError(f"the rollouts of this run need about {need / 2**30:.1f} GiB ({obs:,} bytes an observation "
                         f"× num_steps {config['num_steps']} × num_envs {config['num_envs']} × {seeds} seed(s) at "
                         f"once × 2), more than this device's {have / 2**30:.1f} GiB: lower num_envs / num_steps, "
                         "set vmap_seeds=false, or observe less (e.g. a coarser glimpse level)")
    return need


def pin_env_shapes(config: dict, env_params) -> dict:
    """``config`` with the env's slide-dependent shapes recorded in ``env_kwargs``, so that the saved
    run rebuilds the same observation and action spaces on other slides: for ``glimpse``, the padded
    cell grid (``glimpse_grid``; otherwise it is the largest grid of the slides loaded, and a policy
    trained on one dataset would not fit another's). Unchanged for the other modes."""
    from histojax.reading.modes.glimpse import GlimpseTables

    tables = getattr(env_params, "mode_data", None)
    if not isinstance(tables, GlimpseTables) or tables.step_obs:  # step_obs: cell-set policies fit any grid
        return config
    kw = dict(config.get("env_kwargs") or {})
    kw.setdefault("glimpse_grid", [int(v) for v in np.asarray(tables.grid)])
    return {**config, "env_kwargs": kw}


def make_env(config: dict, auto_reset: bool = True, mesh: Mesh | None = None):
    """``(env, params)`` for ``config["env_id"]`` on ``config["slide"]`` (None = sample slide).
    With ``config["shard_slides"]`` and a ``mesh``, the slides are split over its devices
    (:func:`histojax.sharding.make_sharded`); without a mesh they all load on one device."""
    if config.get("shard_slides") and mesh is not None:
        from histojax.sharding import make_sharded

        return make_sharded(config["env_id"], mesh, slide=config.get("slide"), auto_reset=auto_reset,
                            **env_overrides(config))
    return histojax.make(config["env_id"], slide=config.get("slide"), auto_reset=auto_reset,
                         **env_overrides(config))


def env_vmap(fn, num_args: int, mesh: Mesh | None = None, sharded_slides: bool = False):
    """``fn(*per_env_args, env_params)`` (an env's ``reset`` with 1 arg, ``step`` with 3) over a
    batch of envs: ``jax.vmap`` with the params shared, or, for slides sharded over ``mesh``,
    each device's block of envs on its own slides (:func:`histojax.sharding.vmap_local`)."""
    if sharded_slides:
        from histojax.sharding import vmap_local

        return vmap_local(fn, mesh, num_args)
    return jax.vmap(fn, in_axes=(0,) * num_args + (None,))


def reset_envs(env, key, env_params, num_envs: int, reset_all=None):
    """The trainers' first step: ``key`` → ``(key, k_init, obs, env_state)`` with ``num_envs``
    vmapped resets (``reset_all``, default ``jax.vmap(env.reset)``, see :func:`env_vmap`) and the
    observations pooled for the network (:func:`networks.preprocess_obs`).
    ``k_init`` is the key the network's parameters are made from, so :func:`params_initialiser`
    and the trainer see the same first observations."""
    from baselines.networks import preprocess_obs

    reset_all = reset_all or env_vmap(env.reset, 1)
    key, k_init, k_reset = jax.random.split(key, 3)
    obs, env_state = reset_all(jax.random.split(k_reset, num_envs), env_params)
    return key, k_init, preprocess_obs(obs), env_state


def params_initialiser(env, network, num_envs: int, reset_all=None, inputs=None):
    """``init_params(key, env_params)``: the network's parameters for a trainer's key, made on the
    first observations of :func:`reset_envs` (``network.init(key, *inputs(obs))``; by default the
    observations alone)."""
    def init_params(key, env_params):
        _, k_init, obs, _ = reset_envs(env, key, env_params, num_envs, reset_all)
        return network.init(k_init, *(inputs(obs) if inputs is not None else (obs,)))
    return init_params


def episode_stats(info: dict) -> dict:
    """Means over the episodes that finished in a batch of steps (any shape): ``episodes``,
    ``return``, ``success`` (rate), ``length`` and ``steps_to_success`` (mean length of the
    successful ones; NaN when none)."""
    done = info["returned_episode"].astype(jnp.float32)
    succ = info["returned_episode_success"].astype(jnp.float32) * done
    n, ns = done.sum(), succ.sum()
    length = info["returned_episode_lengths"].astype(jnp.float32)
    safe = lambda a, d: jnp.where(d > 0, a / jnp.maximum(d, 1.0), jnp.nan)  # noqa: E731
    return {
        "episodes": n,
        "return": safe((info["returned_episode_returns"] * done).sum(), n),
        "success": safe(ns, n),
        "length": safe((length * done).sum(), n),
        "steps_to_success": safe((length * succ).sum(), ns),
    }


class Progress:
    """Host side of the progress callback (:func:`report`): prints the seed mean of one update's
    metrics every ``every`` updates."""

    def __init__(self, num_seeds: int, num_updates: int, steps_per_update: int, every: int, name: str = ""):
        self.num_seeds, self.num_updates, self.every = num_seeds, num_updates, max(1, every)
        self.steps_per_update, self.name = steps_per_update, name
        self.calls: dict[int, int] = {}
        self.t0 = time.perf_counter()

    def __call__(self, update, metrics):
        """Called once per update with scalars, or with ``(seeds,)`` arrays (see :func:`report`)."""
        batched = np.ndim(update) > 0
        update = int(np.asarray(update).reshape(-1)[0])
        seed = "all seeds" if batched else f"seed {self.calls.get(update, 0)}"
        self.calls[update] = self.calls.get(update, 0) + 1
        if (update + 1) % self.every == 0 or update + 1 == self.num_updates:
            self._print(update, {k: np.asarray(v, np.float64).reshape(-1) for k, v in metrics.items()}, seed)
        return np.zeros(np.shape(np.asarray(metrics[next(iter(metrics))])), np.int32)

    def _print(self, update, metrics, seed):
        m = {k: finite_mean(v) for k, v in metrics.items()}
        steps = (update + 1) * self.steps_per_update
        dt = time.perf_counter() - self.t0
        extra = "  ".join(f"{k} {_number(v, '.4g')}" for k, v in m.items()
                          if k not in ("return", "success", "steps_to_success", "episodes"))
        print(f"[{self.name}, {seed}] update {update + 1}/{self.num_updates}  env steps/seed {steps:,}  "
              f"return {_number(m['return'], '.3f')}  success {_number(m['success'], '.1%')}  "
              f"steps-to-success {_number(m['steps_to_success'], '.1f')}  {extra}  ({dt:.0f} s)", flush=True)


def _number(value: float, spec: str) -> str:
    """``value`` formatted by ``spec``; ``"n/a"`` for NaN (an update in which no episode ended, or no
    episode succeeded, has no return, success or steps-to-success to show)."""
    return "n/a" if np.isnan(value) else format(value, spec)


def report(progress: Progress, update, metrics: dict):
    """Print progress from inside the jitted, seed-vmapped trainer. A ``jax.pure_callback`` with
    ``vmap_method="broadcast_all"`` gets all seeds in one host call (``jax.debug.callback``
    under ``vmap`` calls once per seed, slicing device arrays from the callback thread, which
    stalled a 2-seed CPU run). Returns an int32 zero that the caller must use (add it to a
    metric) so the callback is not removed as dead code."""
    return jax.pure_callback(progress, jax.ShapeDtypeStruct((), jnp.int32), update, metrics,
                             vmap_method="broadcast_all")


# ----------------------------------------------------------------------------- checkpoints
def save_checkpoint(out: Path, params, config: dict, name: str = "params.msgpack", stage=None) -> Path:
    """Write ``params`` (any pytree of arrays; seeds stacked on axis 0) as flax msgpack and the
    config as ``config.json`` beside it, each atomically, or staged in ``stage``
    (:func:`baselines.outputs.staged`: written with the run's other files as a whole). Returns the params path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    w = stage or outputs
    w.write_bytes(path, serialization.msgpack_serialize(jax.tree.map(np.asarray, jax.device_get(params))))
    w.write_text(out / "config.json", json.dumps(config, indent=2, default=str))
    return path


def load_checkpoint(path) -> tuple[dict, dict]:
    """``(params, config)`` from a checkpoint file or its run folder. A missing, truncated or corrupt
    file raises HistojaxDataError naming it."""
    path = Path(path)
    if path.is_dir():
        path = path / "params.msgpack"
    try:
        data = path.read_bytes()
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the checkpoint ({e.strerror or e})") from e
    try:
        params = serialization.msgpack_restore(data)
    except Exception as e:  # msgpack's errors (ExtraData, ValueError "incomplete input", ...) share no base
        raise HistojaxDataError(path, f"not a readable checkpoint, truncated or corrupt ({e}); train again") from e
    config_path = path.parent / "config.json"
    try:
        config = json.loads(config_path.read_text())
    except OSError as e:
        raise HistojaxDataError(config_path, f"cannot read the run's config ({e.strerror or e})") from e
    except ValueError as e:
        raise HistojaxDataError(config_path, f"not valid JSON, truncated or corrupt ({e})") from e
    return jax.tree.map(jnp.asarray, params), canonical_config(config)  # older runs spelled obs_mode "obs"


# ----------------------------------------------------------------------------- logs
def write_logs(out: Path, steps: np.ndarray, metrics: dict, summary: dict, stage=None) -> None:
    """``log.csv``: one row per logged update with the mean over seeds (and min/max of the success
    rate over seeds); ``log.json``: the per-seed arrays and the summary. Each written atomically, or
    staged in ``stage`` (:func:`baselines.outputs.staged`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = stage or outputs
    keys = [k for k in ("return", "success", "length", "steps_to_success") if k in metrics]
    with files.open_text(out / "log.csv") as f:
        w = csv.writer(f)
        w.writerow(["step", "mean_return", "success_rate", "success_rate_min_seed", "success_rate_max_seed",
                    "mean_length", "mean_steps_to_success"])
        for i, s in enumerate(steps):
            col = {k: np.asarray(metrics[k])[:, i] for k in keys}
            w.writerow([int(s), _fmt(finite_mean(col["return"])), _fmt(finite_mean(col["success"])),
                        _fmt(finite_extreme(col["success"], np.min)), _fmt(finite_extreme(col["success"], np.max)),
                        _fmt(finite_mean(col["length"])), _fmt(finite_mean(col["steps_to_success"]))])
    data = {"summary": summary, "step": [int(s) for s in steps],
            "per_seed": {k: np.asarray(v).tolist() for k, v in metrics.items()}}
    files.write_text(out / "log.json", json.dumps(data, default=_json_default))


def _fmt(v):
    return "" if not np.isfinite(v) else f"{v:.5g}"


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _count(n: int, noun: str) -> str:
    """``"1 seed"``, ``"4 seeds"``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def finite_mean(a, axis=None):
    """Mean of the finite entries of ``a`` (over ``axis``), NaN where there are none, without numpy's
    "Mean of empty slice" warning: e.g. a window of updates in which no episode ended (or none
    succeeded, for the steps to success) has no value, and says so with NaN."""
    a = np.asarray(a, np.float64)
    ok = np.isfinite(a)
    n = ok.sum(axis=axis)
    total = np.where(ok, a, 0.0).sum(axis=axis)
    out = np.divide(total, n, out=np.full(np.shape(total), np.nan), where=n > 0)
    return out if np.ndim(out) else float(out)


def finite_extreme(a, fn, axis=None):
    """``fn`` (``np.min`` / ``np.max``) of the finite entries of ``a``, NaN where there are none
    (no "All-NaN slice" warning)."""
    a = np.asarray(a, np.float64)
    ok = np.isfinite(a)
    fill = np.inf if fn is np.min else -np.inf
    out = fn(np.where(ok, a, fill), axis=axis)
    out = np.where(ok.any(axis=axis), out, np.nan)
    return out if np.ndim(out) else float(out)


def smooth(a: np.ndarray, k: int) -> np.ndarray:
    """Trailing moving average along the last axis, ignoring NaN."""
    if k <= 1:
        return a
    out = np.full_like(a, np.nan, dtype=np.float64)
    for i in range(a.shape[-1]):
        w = a[..., max(0, i - k + 1): i + 1]
        out[..., i] = finite_mean(w, axis=-1)
    return out


def make_random_rollout(env, num_envs: int, num_steps: int):
    """A jitted function ``(key, params) -> (info, last observations)`` that runs ``num_steps`` steps of ``num_envs``
    random-agent environments (auto-reset, episode statistics, every observation extracted) with
    ``lax.scan`` over ``vmap``."""
    env = LogWrapper(env)
    space = env.action_space()

    def rollout(key, params):
        key, key_reset = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, key):
            state, _ = carry
            key_act, key_step = jax.random.split(key)
            action = jax.vmap(space.sample)(jax.random.split(key_act, num_envs))
            obs, state, reward, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key_step, num_envs), state, action, params)
            keep = ("returned_episode", "returned_episode_returns", "returned_episode_success")
            # the observations go into the carry, so every view is really extracted (a random agent
            # ignores them, and XLA would otherwise skip the crop and overstate steps/s)
            return (state, obs), {k: info[k] for k in keep}

        (_, last_obs), infos = jax.lax.scan(body, (state, obs), jax.random.split(key, num_steps))
        return infos, last_obs  # returning the carried views keeps them alive

    return jax.jit(rollout)


def random_agent_reference(config: dict, num_envs: int = 256, num_steps: int = 400, seed: int = 0,
                           env_and_params=None) -> dict:
    """Episode statistics of the uniform random agent on the same env (for the curves): the
    trainer's ``env_and_params`` when given (for slides sharded over devices, those of this
    process's first device), else the env made from ``config``."""
    if env_and_params is None:
        env, params = make_env(config)
    else:
        env, params = env_and_params
        env = getattr(env, "_env", env)  # the bare env under a LogWrapper
        if config.get("shard_slides"):
            from histojax.sharding import first_local_group

            params = params.replace(slide=first_local_group(params.slide))
    info, _ = jax.device_get(make_random_rollout(env, num_envs, num_steps)(jax.random.PRNGKey(seed), params))
    info = {**info, "returned_episode_lengths": np.zeros_like(info["returned_episode_returns"])}
    stats = jax.device_get(episode_stats(info))
    return {"return": float(stats["return"]), "success": float(stats["success"])}


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
        raise ValueError(f"num_envs={num_envs} must divide by devices={n} (each device steps "
                         f"num_envs / devices envs)")
    if n > len(available):
        raise ValueError(
            f"devices={n} but only {len(available)} {available[0].platform} device(s) are visible; on "
            f"CPU set XLA_FLAGS=--xla_force_host_platform_device_count={n} before jax is imported "
            f"(several hosts: call jax.distributed.initialize() first)")
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


def seeds_runner(train, init_params, env_params, config: dict, progress: Progress, mesh: Mesh | None = None,
                 env=None):
    """One jitted program over all seeds: ``run(keys, params=None)`` trains ``len(keys)`` seeds
    (``jax.vmap`` over keys, or ``lax.map`` with ``config["vmap_seeds"] = False``) on
    ``env_params`` (or ``params``); ``run.compile(keys)`` compiles ahead of time and returns the
    same call. With a ``mesh`` (:func:`batch_mesh`) the keys and env params (slide arrays) are
    placed replicated on its devices; ``train`` shards the env batch itself (:func:`shard_batch`).
    Shared by PPO and DQN. With ``env`` the env params given are checked first
    (:func:`histojax.registry.check_params`: a ``stride`` or step limit changed after ``make`` is named,
    not trained on)."""
    from histojax.registry import check_params

    def checked(p):
        if env is not None:
            check_params(env, p, where="train: env params")
        return p

    def all_seeds(keys, p):
        # Initial parameters always via lax.map: jit(vmap(init)) of the orthogonal initialisers
        # (batched QR) never finished on jaxlib 0.10's CPU backend.
        params = jax.lax.map(lambda k: init_params(k, p), keys)
        if config["vmap_seeds"]:
            return jax.vmap(train, in_axes=(0, None, 0))(keys, p, params)
        return jax.lax.map(lambda kp: train(kp[0], p, kp[1]), (keys, params))

    jitted = jax.jit(all_seeds)
    # replicated on the mesh's devices (a no-op for arrays already placed there; slides sharded
    # over the mesh, see histojax.sharding, stay as they are)
    place = (lambda x: x) if mesh is None else functools.partial(replicate_on, mesh)

    def run(keys, params=None):
        progress.t0 = time.perf_counter()
        return jitted(place(keys), place(checked(env_params if params is None else params)))

    def compile_(keys, params=None):
        """Compile ahead of time; returns ``compiled(keys, params=None)`` (``.exe``: the
        ``jax.stages.Compiled``, e.g. for ``.as_text()``)."""
        params = place(checked(env_params if params is None else params))
        exe = jitted.lower(place(keys), params).compile()

        def call(keys, p=None):
            progress.t0 = time.perf_counter()
            return exe(place(keys), params if p is None else place(checked(p)))
        call.exe = exe
        return call

    run.compile, run.raw, run.mesh = compile_, train, mesh
    return run


# ----------------------------------------------------------------------------- chunks, checkpoints, resume
CHECKPOINT_DIR = "checkpoint"     # RUN/checkpoint/: runner.msgpack, checkpoint.json, config.json
RUNNER_FORMAT = 1


def chunk_plan(num_updates: int, every: int | None) -> tuple[int, int]:
    """``(chunk, n_chunks)``: a run of ``num_updates`` updates split into ``n_chunks`` chunks of ``chunk``
    updates, checkpointed after each; ``chunk`` ≤ ``every`` (``None`` or ≤ 0: one chunk), the chunks as
    even as they can be (``n_chunks × chunk − num_updates < n_chunks`` updates of the last chunk are skipped)."""
    every = num_updates if every is None or every <= 0 else min(int(every), num_updates)
    n_chunks = -(-num_updates // every)
    return -(-num_updates // n_chunks), n_chunks


def scan_updates(update, carry, first_update, n_updates: int, num_updates: int):
    """``lax.scan`` of ``update(carry, i) -> (carry, metrics)`` over ``i = first_update + arange(n_updates)``;
    an ``i ≥ num_updates`` is skipped (``lax.cond``: the carry is kept, its metrics are NaN), so the last,
    shorter chunk of a run runs in the same compiled program as the others."""
    def skip(c, i):
        shapes = jax.eval_shape(update, c, i)[1]
        return c, jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.inexact) else 0,
                                                  s.dtype), shapes)

    def body(c, i):
        return jax.lax.cond(i < num_updates, update, skip, c, i)
    return jax.lax.scan(body, carry, first_update + jnp.arange(n_updates))


def chunked_runner(train):
    """The run of ``train`` (a ``make_train`` runner with ``init_runner(key, env_params, params)``,
    ``update(runner, update_index, env_params) -> (runner, metrics)`` and ``runner_params(runner)``, each
    for one seed) in chunks of ``config["checkpoint_every"]`` updates (:func:`chunk_plan`): ``start(keys)``
    → the seeds' runner states (params, optimizer state, env state, observation, key; seeds on axis 0);
    ``chunk(runners, first_update)`` → ``(runners, metrics (seeds, chunk))``, compiled once (ahead of time,
    on the first call; ``chunk.compile_seconds``). Seeds are vmapped (or ``lax.map``-ed with
    ``vmap_seeds=False``) as in :func:`seeds_runner`."""
    from histojax.registry import check_params

    config, env_params, mesh = train.config, train.env_params, getattr(train, "mesh", None)
    size, _ = chunk_plan(train.num_updates, config.get("checkpoint_every"))
    place = (lambda x: x) if mesh is None else functools.partial(replicate_on, mesh)
    if getattr(train, "env", None) is not None:
        check_params(train.env, env_params, where="train: env params")
    env_params = place(env_params)

    def start_all(keys, p):
        params = jax.lax.map(lambda k: train.init_params(k, p), keys)  # lax.map: see seeds_runner
        if config["vmap_seeds"]:
            return jax.vmap(train.init_runner, in_axes=(0, None, 0))(keys, p, params)
        return jax.lax.map(lambda kp: train.init_runner(kp[0], p, kp[1]), (keys, params))

    def chunk_all(runners, p, first):
        def one(r):
            return scan_updates(lambda c, i: train.update(c, i, p), r, first, size, train.num_updates)
        if config["vmap_seeds"]:
            return jax.vmap(one)(runners)
        return jax.lax.map(one, runners)

    start_jit, chunk_jit = jax.jit(start_all), jax.jit(chunk_all)
    compiled = {}

    def start(keys):
        return start_jit(place(keys), env_params)

    def template(keys):
        """The runner states' structure, shapes and dtypes (``jax.eval_shape``; nothing runs)."""
        return jax.eval_shape(start_all, place(keys), env_params)

    def chunk(runners, first_update: int):
        first = jnp.asarray(first_update, jnp.int32)
        if "exe" not in compiled:
            t0 = time.perf_counter()
            compiled["exe"] = chunk_jit.lower(runners, env_params, first).compile()
            chunk.compile_seconds = time.perf_counter() - t0
        return compiled["exe"](runners, env_params, first)

    chunk.compile_seconds = 0.0  # the compile of the first call, seconds
    start.template, start.size = template, size
    return start, chunk


def save_runner(folder: Path, runners, update: int, metrics: dict, train_seconds: float, config: dict,
                num_updates: int, chunk: int) -> Path:
    """Write a run's state after ``update`` updates into ``folder`` (``RUN/checkpoint``): ``runner.msgpack``
    (flax msgpack: every array of the seeds' runner states, the metrics so far, the update index), then
    ``checkpoint.json`` (a summary for people). Each file atomically; the msgpack holds all that
    :func:`load_runner` needs, so a run killed between the two resumes from the msgpack."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    leaves = jax.tree.leaves(jax.device_get(runners))
    state = {"format": RUNNER_FORMAT, "update": int(update), "num_updates": int(num_updates), "chunk": int(chunk),
             "config_sha256": config_digest(config),
             "train_seconds": float(train_seconds),
             "leaves": {str(i): np.asarray(a) for i, a in enumerate(leaves)},
             "metrics": {k: np.asarray(v) for k, v in metrics.items()}}
    path = outputs.write_bytes(folder / "runner.msgpack", serialization.msgpack_serialize(state))
    outputs.write_text(folder / "checkpoint.json", json.dumps(
        {"update": int(update), "num_updates": int(num_updates), "checkpoint_every": int(chunk),
         "train_seconds": round(float(train_seconds), 3), "saved": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
         "resume": f"histojax train --algo {config.get('algo', 'ppo')} --resume {folder.parent}"}, indent=1))
    return path


def config_digest(config: dict) -> str:
    """SHA-256 of a run config (JSON, keys sorted): ties a checkpoint to the run that wrote it."""
    import hashlib

    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def load_runner(folder: Path, template, num_updates: int, chunk: int, config: dict | None = None):
    """``(runners, update, metrics, train_seconds)`` from ``folder/runner.msgpack`` (:func:`save_runner`),
    checked against ``template`` (:func:`chunked_runner`'s ``start.template``: the runner states this config
    makes) and the run's ``num_updates`` / ``chunk``. A missing, corrupt or mismatching file raises
    HistojaxDataError naming it."""
    path = Path(folder) / "runner.msgpack"
    try:
        state = serialization.msgpack_restore(path.read_bytes())
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the run's checkpoint ({e.strerror or e}); nothing to resume") from e
    except Exception as e:  # msgpack's errors share no base
        raise HistojaxDataError(path, f"not a readable checkpoint, truncated or corrupt ({e})") from e
    if not isinstance(state, dict) or state.get("format") != RUNNER_FORMAT or "leaves" not in state:
        raise HistojaxDataError(path, "not a histojax training checkpoint (no runner state of format "
                                      f"{RUNNER_FORMAT})")
    if config is not None and state.get("config_sha256") != config_digest(config):
        raise HistojaxDataError(path, f"written by a run of another config than {Path(folder) / 'config.json'} (a new "
                                      "run started in this folder before its first checkpoint?); train again")
    if (state["num_updates"], state["chunk"]) != (num_updates, chunk):
        raise HistojaxDataError(path, f"saved for {state['num_updates']} updates in chunks of {state['chunk']}, "
                                      f"but the run's config.json makes {num_updates} in chunks of {chunk}")
    want, treedef = jax.tree.flatten(template)
    got = [state["leaves"].get(str(i)) for i in range(len(want))]
    if len(state["leaves"]) != len(want) or any(
            g is None or tuple(np.shape(g)) != tuple(w.shape) or np.asarray(g).dtype != w.dtype
            for g, w in zip(got, want)):
        raise HistojaxDataError(path, "its arrays do not match the runner state of the run's config.json "
                                      "(another trainer, network or env); train again")
    return (jax.tree.unflatten(treedef, [jnp.asarray(g) for g in got]), int(state["update"]),
            {k: np.asarray(v) for k, v in state["metrics"].items()}, float(state["train_seconds"]))


def tensorboard_writer(out: Path):
    """A ``tensorboardX.SummaryWriter`` writing event files into ``out`` (beside ``log.csv``), or None when
    tensorboardX is not installed (it is optional: ``pip install tensorboardX``)."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(logdir=str(out))


def run_chunked(train, out: Path, keys=None, resume: bool = False, on_checkpoint=None):
    """Run ``train`` in chunks (:func:`chunked_runner`), writing ``out/checkpoint/`` after each
    (:func:`save_runner`; the run's config in ``out/checkpoint/config.json`` first) and TensorBoard scalars
    into ``out`` when tensorboardX is installed. ``resume``: continue from ``out/checkpoint`` (same config);
    the result equals the uninterrupted run's bit for bit (the same compiled chunk on the same states).
    ``on_checkpoint(update)`` is called after each checkpoint. Returns ``({"params", "metrics"},
    compile seconds, train seconds)`` with metrics ``(seeds, num_updates)``."""
    out, config, num_updates = Path(out), train.config, train.num_updates
    folder = out / CHECKPOINT_DIR
    keys = jax.random.split(jax.random.PRNGKey(config.get("seed", 0)), config["num_seeds"]) if keys is None else keys
    if getattr(train, "chunked", None) is None:  # made once per trainer: the chunk compiles once
        train.chunked = chunked_runner(train)
    start, chunk = train.chunked
    if resume:
        runners, done, metrics, train_s = load_runner(folder, start.template(keys), num_updates, start.size, config)
        print(f"resuming {out} at update {done}/{num_updates}", flush=True)
        compile_s = 0.0
    else:
        folder.mkdir(parents=True, exist_ok=True)
        outputs.write_text(folder / "config.json", json.dumps(config, indent=2, default=str))
        t0 = time.perf_counter()
        runners = jax.block_until_ready(start(keys))
        compile_s, train_s, done, metrics = time.perf_counter() - t0, 0.0, 0, {}
    writer = tensorboard_writer(out) if jax.process_index() == 0 else None
    try:
        while done < num_updates:
            t0, compiled_before = time.perf_counter(), chunk.compile_seconds
            runners, m = chunk(runners, done)
            m = jax.block_until_ready(m)
            compiled_now = chunk.compile_seconds - compiled_before  # > 0 on the first call only
            compile_s += compiled_now
            train_s += time.perf_counter() - t0 - compiled_now
            n = min(start.size, num_updates - done)  # the last chunk's skipped updates are dropped
            m = {k: np.asarray(v)[:, :n] for k, v in jax.device_get(m).items()}
            if writer is not None:
                _tensorboard_scalars(writer, m, done, train.steps_per_update)
            metrics = {k: np.concatenate([metrics[k], v], axis=1) if k in metrics else v for k, v in m.items()}
            done += n
            save_runner(folder, runners, done, metrics, train_s, config, num_updates, start.size)
            if on_checkpoint is not None:
                on_checkpoint(done)
    finally:
        if writer is not None:
            writer.close()
    return {"params": train.runner_params(runners), "metrics": metrics}, compile_s, train_s


def _tensorboard_scalars(writer, metrics: dict, first_update: int, steps_per_update: int) -> None:
    """The seed means of one chunk's ``metrics`` (``(seeds, n)``) as scalars ``train/NAME`` at env steps per seed."""
    for j in range(next(iter(metrics.values())).shape[1]):
        step = (first_update + j + 1) * steps_per_update
        for k, v in metrics.items():
            value = finite_mean(v[:, j])
            if np.isfinite(value):
                writer.add_scalar(f"train/{k}", value, step)
    writer.flush()


# ----------------------------------------------------------------------------- the command line and a run
def add_arguments(p, defaults: dict) -> None:
    """Declare a trainer's options on the parser (or argument group) ``p``, with ``defaults`` its
    config defaults: the one declaration behind ``python -m baselines.ppo|dqn|ppo_rnn``,
    ``histojax train --algo ...`` and ``baselines.rotation``."""
    p.add_argument("--env", default=defaults["env_id"], help="registered env id")
    p.add_argument("--slide", default=None, help="bundle folder (default: the embedded sample slide)")
    p.add_argument("--dataset", default=None, metavar="DIR",
                   help="a dataset folder (histojax dataset / data_tools c16 / synth; its dataset.json): "
                        "train on its slides (make(env, dataset=DIR))")
    p.add_argument("--split", default=None, metavar="S",
                   help="with --dataset: the split to train on (default: the env's, 'train')")
    p.add_argument("--fold", type=int, default=None, metavar="I",
                   help="with --dataset built with --folds K: train on fold I's train side (the other K - 1 folds); "
                        "make(..., fold=I)")
    p.add_argument("--action-mode", default="discrete",
                   help="discrete | continuous | glimpse[:LEVEL] | zoom_select[:K] (histojax.reading.modes.base)")
    p.add_argument("--obs-mode", "--obs", dest="obs_mode", default="pixels",
                   help="the env's obs_mode: pixels | features | ... (--obs: the older spelling)")
    p.add_argument("--with-position", action="store_true", help="observation dict with the view position")
    p.add_argument("--reward", default=None, help="reward preset (default: the env's, 'dense')")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--total-steps", type=int, default=defaults["total_timesteps"], help="env steps per seed")
    p.add_argument("--num-envs", type=int, default=defaults["num_envs"])
    p.add_argument("--lr", type=positive_float, default=defaults["lr"], help="learning rate (finite, > 0)")
    p.add_argument("--devices", type=int, default=None,
                   help="shard the env batch over the first N devices (PPO; on CPU set "
                        "XLA_FLAGS=--xla_force_host_platform_device_count=N)")
    p.add_argument("--shard-slides", action="store_true",
                   help="with --devices N: split the dataset's slides over the devices (each device holds and "
                        "draws only its own slides; docs/scaling.md)")
    distributed.add_arguments(p)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other config entry, value parsed as JSON (e.g. --set ent_coef=0.02)")
    p.add_argument("--out", default=None, help="run folder (default runs/<algo>-<env>)")
    if "checkpoint_every" in defaults:
        p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                       help=f"save the whole training state to OUT/checkpoint/ every N updates "
                            f"(default {defaults['checkpoint_every']}; 0: only at the end)")
        p.add_argument("--resume", default=None, metavar="RUN",
                       help="continue the killed run in folder RUN from its last checkpoint, with its own "
                            "config (RUN/checkpoint/config.json; other options are ignored); the result equals an "
                            "uninterrupted run's")


def parse_args(argv=None, defaults: dict | None = None, description: str = ""):
    """Parse a baseline's command line (``defaults``: its config defaults; :func:`add_arguments`)."""
    add = functools.partial(add_arguments, defaults=defaults)
    return build_parser(add, description=description.split("\n\n")[0], one_line=False).parse_args(argv)


def config_from_args(args, defaults: dict) -> dict:
    """The trainer config of parsed arguments: ``defaults`` with the options and ``--set`` entries applied."""
    config = {**defaults, "env_id": args.env, "slide": args.slide, "action_mode": args.action_mode,
              "obs_mode": args.obs_mode, "with_position": args.with_position, "reward": args.reward,
              "num_seeds": args.seeds, "seed": args.seed, "total_timesteps": args.total_steps,
              "num_envs": args.num_envs, "lr": args.lr}
    if getattr(args, "checkpoint_every", None) is not None:
        config["checkpoint_every"] = args.checkpoint_every
    if args.devices is not None:
        if "devices" not in defaults:
            raise SystemExit("--devices is supported by the PPO baseline only")
        config["devices"] = args.devices
    if getattr(args, "shard_slides", False):
        if "shard_slides" not in defaults:
            raise SystemExit("--shard-slides is supported by the PPO baseline only")
        config["shard_slides"] = True
    for item in args.set:
        k, _, v = item.partition("=")
        if k not in defaults:
            raise SystemExit(f"unknown config entry {k!r}; known: {', '.join(defaults)}")
        try:
            config[k] = json.loads(v)
        except json.JSONDecodeError:
            config[k] = v
    fold = getattr(args, "fold", None)
    if getattr(args, "dataset", None) is not None or getattr(args, "split", None) is not None or fold is not None:
        if args.dataset is None:
            raise SystemExit(f"{'--split' if getattr(args, 'split', None) is not None else '--fold'} needs --dataset DIR")
        config["env_kwargs"] = {**(config.get("env_kwargs") or {}), "dataset": args.dataset,
                                **({"split": args.split} if args.split is not None else {}),
                                **({"fold": fold} if fold is not None else {})}
    return config


def finish_run(algo: str, config: dict, out: Path, params, metrics: dict, steps_per_update: int,
               train_seconds: float, compile_seconds: float, env_and_params=None) -> dict:
    """Logs, curve, checkpoint and a printed summary (shared by PPO and DQN). ``env_and_params``:
    the trainer's, for the random-agent reference of slides sharded over devices."""
    metrics = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
    n_updates = metrics["success"].shape[1]
    steps = (np.arange(n_updates) + 1) * steps_per_update
    k = max(1, n_updates // 40)  # smooth over ~1/40 of the run for the curve and the final figure
    tail = slice(max(0, n_updates - k), None)
    final = {name: finite_mean(metrics[name][:, tail]) for name in ("return", "success", "length", "steps_to_success")}
    final_per_seed = {name: finite_mean(metrics[name][:, tail], axis=1).tolist() for name in ("return", "success")}
    ref = random_agent_reference(config, env_and_params=env_and_params)
    summary = {"algo": algo, "env_id": config["env_id"], "env_steps_per_seed": int(steps[-1]),
               "seeds": int(metrics["success"].shape[0]), "train_seconds": train_seconds,
               "compile_seconds": compile_seconds,
               "env_steps_per_second_all_seeds": float(steps[-1] * metrics["success"].shape[0] / train_seconds),
               "final_window_updates": k, "final": final, "final_per_seed": final_per_seed,
               "random_agent": ref}
    panels = {"mean return": smooth(metrics["return"], k), "success rate": smooth(metrics["success"], k),
              "mean steps to success": smooth(metrics["steps_to_success"], k)}
    title = (f"{algo.upper()} on {config['env_id']} ({config['action_mode']}, obs {config['obs_mode']}"
             f"{' + position' if config['with_position'] else ''}), {_count(metrics['success'].shape[0], 'seed')}")
    # the run's files as a whole: on a full disk (the error names the file) the previous run's stay together
    with outputs.staged() as stage:
        write_logs(out, steps, metrics, summary, stage=stage)
        with stage.writing(out / "curve.png") as tmp:
            plot_curves(tmp, steps, panels, title=title,
                        reference={"mean return": ref["return"], "success rate": ref["success"]})
        save_checkpoint(out, params, config, stage=stage)
    print(f"\n{algo} {config['env_id']}: {steps[-1]:,} env steps/seed x {summary['seeds']} seeds in "
          f"{train_seconds:.0f} s (+{compile_seconds:.0f} s compile), "
          f"{summary['env_steps_per_second_all_seeds']:,.0f} env steps/s")
    print(f"final (last {k} updates, training policy): return {final['return']:.3f}  success {final['success']:.1%}  "
          f"mean length {final['length']:.1f}  steps to success {final['steps_to_success']:.1f}")
    print(f"random agent: return {ref['return']:.3f}  success {ref['success']:.1%}")
    print(f"wrote {out}/log.csv, log.json, curve.png, params.msgpack, config.json")
    return summary


def train_and_save(algo: str, make_train_fn, args, defaults: dict, unit: str) -> int:
    """The command of a baseline (shared by every algorithm file), on ``args`` parsed with
    :func:`add_arguments`: compile, train all seeds in one program, then write logs, curve and
    checkpoint with :func:`finish_run`."""
    if getattr(args, "resume", None) is not None:
        run = Path(args.resume)
        config = resume_config(run, algo)
        run_and_save(algo, make_train_fn, config, run, unit, resume=True)
        return 0
    config = config_from_args(args, defaults=defaults)
    if (args.coordinator is not None or args.distributed) and "devices" not in defaults:
        raise SystemExit("several processes (--coordinator / --distributed) are supported by the PPO baseline only")
    distributed.from_args(args)
    run_and_save(algo, make_train_fn, config, Path(args.out or f"runs/{algo}-{config['env_id']}"), unit)
    return 0


def resume_config(run: Path, algo: str) -> dict:
    """The config of the run to resume in folder ``run`` (``run/checkpoint/config.json``, written when it
    started). A missing or unreadable file, or another trainer's run, raises HistojaxDataError naming it."""
    path = Path(run) / CHECKPOINT_DIR / "config.json"
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the run's config ({e.strerror or e}): not a run started with "
                                      "checkpoints, nothing to resume") from e
    except ValueError as e:
        raise HistojaxDataError(path, f"not valid JSON, truncated or corrupt ({e})") from e
    if not isinstance(config, dict):
        raise HistojaxDataError(path, "not a run config (a JSON object)")
    if config.get("algo", algo) != algo:
        raise HistojaxDataError(path, f"a {config['algo']} run; resume it with --algo {config['algo']}")
    return canonical_config(config)


def trainer_command(algo: str, make_train_fn, defaults: dict, unit: str, doc: str):
    """A trainer module's command: ``(add_arguments, run, main)`` for ``python -m baselines.<algo>`` and
    ``histojax train --algo <algo>``, the options :func:`add_arguments` with the trainer's ``defaults``."""
    def add(parser) -> None:
        """The trainer's options (:func:`baselines.common.add_arguments` with its defaults)."""
        add_arguments(parser, defaults)

    def run(args, parser=None) -> int:
        """Train on parsed ``args`` and write the run folder (:func:`train_and_save`)."""
        return train_and_save(algo, make_train_fn, args, defaults, unit)

    return add, run, command_main(add, run, f"python -m baselines.{algo}", doc)


def compile_and_run(train, keys) -> tuple[dict, float, float]:
    """Compile ``train`` (a ``make_train`` runner) ahead of time for ``keys`` and run it once:
    ``(result, compile seconds, run seconds)``, the run timed to completion (``block_until_ready``)."""
    t0 = time.perf_counter()
    compiled = train.compile(keys)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = jax.block_until_ready(compiled(keys))
    return result, compile_s, time.perf_counter() - t0


def run_and_save(algo: str, make_train_fn, config: dict, out: Path, unit: str = "updates", resume: bool = False,
                 on_checkpoint=None):
    """Make, compile and run the trainer for ``config`` (all seeds in one program, compile time
    measured apart), then :func:`finish_run` into ``out``. A trainer that runs in chunks (PPO,
    recurrent PPO, DQN: ``train.init_runner``) saves its whole state to ``out/checkpoint/`` every
    ``checkpoint_every`` updates (:func:`run_chunked`); ``resume`` continues from there.
    Returns ``(config, params, summary)`` with the trainer's full config."""
    train = make_train_fn(config)
    config = train.config
    if config.get("shard_slides"):
        from histojax.sharding import device_bytes, local_slides

        n, nbytes = local_slides(train.env_params.slide)
        per = device_bytes(train.env_params.slide)
        print(f"process {jax.process_index()} of {jax.process_count()}: {n} slide(s), {nbytes:,} bytes of slide arrays "
              f"on its {len(per)} device(s), {max(per.values()):,} on each", flush=True)
    keys = jax.random.split(jax.random.PRNGKey(config.get("seed", 0)), config["num_seeds"])
    chunked = hasattr(train, "init_runner") and jax.process_count() == 1
    if resume and not chunked:
        raise ValueError(f"{algo} runs on several processes cannot resume (no checkpoints along the way)")
    if chunked:
        chunk, n_chunks = chunk_plan(train.num_updates, config.get("checkpoint_every"))
        print(f"{algo.upper()} on {config['env_id']}: {train.num_updates} {unit} x {train.steps_per_update} env steps "
              f"x {config['num_seeds']} seeds, checkpoint every {chunk} {unit} in {out}/{CHECKPOINT_DIR}; "
              "compiling ...", flush=True)
        result, compile_s, train_s = run_chunked(train, out, keys, resume=resume, on_checkpoint=on_checkpoint)
    else:
        print(f"{algo.upper()} on {config['env_id']}: {train.num_updates} {unit} x {train.steps_per_update} env steps "
              f"x {config['num_seeds']} seeds; compiling ...", flush=True)
        result, compile_s, train_s = compile_and_run(train, keys)
    if jax.process_index() > 0:  # several processes: process 0 writes the run, the others their parameters
        save_checkpoint(out / f"process-{jax.process_index()}", result["params"], config)
        print(f"process {jax.process_index()}: {train_s:.1f} s; wrote {out}/process-{jax.process_index()}/params.msgpack")
        return config, result["params"], None
    summary = finish_run(algo, config, out, result["params"], result["metrics"], train.steps_per_update, train_s,
                         compile_s, env_and_params=(train.env, train.env_params))
    return config, result["params"], summary
