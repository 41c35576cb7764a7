"""Shared by the trainers: making the env from a config, episode statistics, progress printing,
checkpoints (flax.serialization msgpack), logs (CSV / JSON), learning-curve PNGs (Pillow) and
sharding the env batch over devices (``--devices N``)."""
from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import histojax


def env_overrides(config: dict) -> dict:
    """The ``histojax.make`` overrides named in a trainer config."""
    kw = {"action_mode": config.get("action_mode", "discrete"),
          "with_position": bool(config.get("with_position", False))}
    obs = config.get("obs", "pixels")
    if obs != "pixels":
        kw["obs_mode"] = obs  # e.g. "features" once the env has it
    for k in ("reward", "max_steps_in_episode"):
        if config.get(k) is not None:
            kw[k] = config[k]
    kw.update(config.get("env_kwargs") or {})
    return kw


def make_env(config: dict, auto_reset: bool = True):
    """``(env, params)`` for ``config["env_id"]`` on ``config["slide"]`` (None = sample slide)."""
    return histojax.make(config["env_id"], slide=config.get("slide"), auto_reset=auto_reset,
                         **env_overrides(config))


def reset_envs(env, key, env_params, num_envs: int):
    """The trainers' first step: ``key`` → ``(key, k_init, obs, env_state)`` with ``num_envs``
    vmapped resets and the observations pooled for the network (:func:`networks.preprocess_obs`).
    ``k_init`` is the key the network's parameters are made from, so :func:`params_initialiser`
    and the trainer see the same first observations."""
    from baselines.networks import preprocess_obs

    key, k_init, k_reset = jax.random.split(key, 3)
    obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, num_envs), env_params)
    return key, k_init, preprocess_obs(obs), env_state


def params_initialiser(env, network, num_envs: int, inputs=None):
    """``init_params(key, env_params)``: the network's parameters for a trainer's key, made on the
    first observations of :func:`reset_envs` (``network.init(key, *inputs(obs))``; by default the
    observations alone)."""
    def init_params(key, env_params):
        _, k_init, obs, _ = reset_envs(env, key, env_params, num_envs)
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
        def mean(v):
            return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
        m = {k: mean(v) for k, v in metrics.items()}
        steps = (update + 1) * self.steps_per_update
        dt = time.perf_counter() - self.t0
        extra = "  ".join(f"{k} {v:.4g}" for k, v in m.items()
                          if k not in ("return", "success", "steps_to_success", "episodes"))
        print(f"[{self.name}, {seed}] update {update + 1}/{self.num_updates}  env steps/seed {steps:,}  "
              f"return {m['return']:.3f}  success {m['success']:.1%}  "
              f"steps-to-success {m['steps_to_success']:.1f}  {extra}  ({dt:.0f} s)", flush=True)


def report(progress: Progress, update, metrics: dict):
    """Print progress from inside the jitted, seed-vmapped trainer. A ``jax.pure_callback`` with
    ``vmap_method="broadcast_all"`` gets all seeds in one host call (``jax.debug.callback``
    under ``vmap`` calls once per seed, slicing device arrays from the callback thread, which
    stalled a 2-seed CPU run). Returns an int32 zero that the caller must use (add it to a
    metric) so the callback is not removed as dead code."""
    return jax.pure_callback(progress, jax.ShapeDtypeStruct((), jnp.int32), update, metrics,
                             vmap_method="broadcast_all")


# ----------------------------------------------------------------------------- checkpoints
def save_checkpoint(out: Path, params, config: dict, name: str = "params.msgpack") -> Path:
    """Write ``params`` (any pytree of arrays; seeds stacked on axis 0) as flax msgpack and the
    config as ``config.json`` beside it. Returns the params path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    path.write_bytes(serialization.msgpack_serialize(jax.tree.map(np.asarray, jax.device_get(params))))
    (out / "config.json").write_text(json.dumps(config, indent=2, default=str))
    return path


def load_checkpoint(path) -> tuple[dict, dict]:
    """``(params, config)`` from a checkpoint file or its run folder."""
    path = Path(path)
    if path.is_dir():
        path = path / "params.msgpack"
    params = serialization.msgpack_restore(path.read_bytes())
    config = json.loads((path.parent / "config.json").read_text())
    return jax.tree.map(jnp.asarray, params), config


# ----------------------------------------------------------------------------- logs
def write_logs(out: Path, steps: np.ndarray, metrics: dict, summary: dict) -> None:
    """``log.csv``: one row per logged update with the mean over seeds (and min/max of the success
    rate over seeds); ``log.json``: the per-seed arrays and the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    keys = [k for k in ("return", "success", "length", "steps_to_success") if k in metrics]
    with open(out / "log.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "mean_return", "success_rate", "success_rate_min_seed", "success_rate_max_seed",
                    "mean_length", "mean_steps_to_success"])
        for i, s in enumerate(steps):
            col = {k: np.asarray(metrics[k])[:, i] for k in keys}
            with np.errstate(all="ignore"):
                w.writerow([int(s), _fmt(np.nanmean(col["return"])), _fmt(np.nanmean(col["success"])),
                            _fmt(np.nanmin(col["success"])), _fmt(np.nanmax(col["success"])),
                            _fmt(np.nanmean(col["length"])), _fmt(np.nanmean(col["steps_to_success"]))])
    data = {"summary": summary, "step": [int(s) for s in steps],
            "per_seed": {k: np.asarray(v).tolist() for k, v in metrics.items()}}
    (out / "log.json").write_text(json.dumps(data, default=_json_default))


def _fmt(v):
    return "" if not np.isfinite(v) else f"{v:.5g}"


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def smooth(a: np.ndarray, k: int) -> np.ndarray:
    """Trailing moving average along the last axis, ignoring NaN."""
    if k <= 1:
        return a
    out = np.full_like(a, np.nan, dtype=np.float64)
    for i in range(a.shape[-1]):
        w = a[..., max(0, i - k + 1): i + 1]
        with np.errstate(all="ignore"):
            out[..., i] = np.nanmean(w, axis=-1) if np.isfinite(w).any() else np.nan
    return out


def plot_curves(path, steps, panels: dict, title: str = "", reference: dict | None = None,
                width: int = 900, height_per_panel: int = 220) -> Path:
    """A learning-curve PNG drawn with Pillow: one panel per ``panels[name] = (seeds, points)``
    array; the seed mean as a line and the seed min–max as a band; ``reference[name] = value``
    draws a dashed horizontal line (e.g. the random agent)."""
    from PIL import Image, ImageDraw

    steps = np.asarray(steps, np.float64)
    n = len(panels)
    top, left, right, gap = 28, 70, 20, 40
    H = top + n * (height_per_panel + gap)
    img = Image.new("RGB", (width, H), "white")
    d = ImageDraw.Draw(img)
    d.text((left, 6), title, fill="black")
    x0, x1 = left, width - right
    smax = max(steps.max(), 1.0) if len(steps) else 1.0
    for p, (name, arr) in enumerate(panels.items()):
        arr = np.asarray(arr, np.float64)
        arr = arr[None] if arr.ndim == 1 else arr
        y0 = top + p * (height_per_panel + gap) + 10
        y1 = y0 + height_per_panel - 20
        finite = arr[np.isfinite(arr)]
        ref = (reference or {}).get(name)
        vals = np.concatenate([finite, [ref] if ref is not None and np.isfinite(ref) else []])
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 1.0)
        if hi - lo < 1e-9:
            lo, hi = lo - 0.5, hi + 0.5
        pad = 0.05 * (hi - lo)
        lo, hi = lo - pad, hi + pad
        X = lambda s: x0 + (x1 - x0) * s / smax  # noqa: E731
        Y = lambda v: y1 - (y1 - y0) * (v - lo) / (hi - lo)  # noqa: E731
        d.rectangle([x0, y0, x1, y1], outline=(120, 120, 120))
        for frac in (0.0, 0.5, 1.0):
            v = lo + pad + frac * (hi - lo - 2 * pad)
            d.line([x0 - 4, Y(v), x0, Y(v)], fill="black")
            d.text((4, Y(v) - 6), f"{v:.3g}", fill="black")
        for frac in (0.0, 0.5, 1.0):
            s = frac * smax
            label = f"{s:,.0f}"
            w = d.textlength(label)
            d.text((min(X(s) - w / 2, x1 - w), y1 + 4), label, fill="black")  # the last one right-aligned
        d.text((x0 + 6, y0 + 4), name, fill=(0, 0, 0))
        with np.errstate(all="ignore"):
            mean = np.nanmean(arr, axis=0)
            mn, mx = np.nanmin(arr, axis=0), np.nanmax(arr, axis=0)
        ok = np.isfinite(mean)
        if arr.shape[0] > 1:
            for i in range(len(steps) - 1):
                if ok[i] and ok[i + 1]:
                    d.polygon([(X(steps[i]), Y(mx[i])), (X(steps[i + 1]), Y(mx[i + 1])),
                               (X(steps[i + 1]), Y(mn[i + 1])), (X(steps[i]), Y(mn[i]))], fill=(190, 210, 240))
        pts = [(X(s), Y(v)) for s, v, o in zip(steps, mean, ok) if o]
        if len(pts) > 1:
            d.line(pts, fill=(20, 60, 200), width=2)
        if ref is not None and np.isfinite(ref):
            for xs in range(int(x0), int(x1), 12):
                d.line([xs, Y(ref), min(xs + 6, x1), Y(ref)], fill=(200, 40, 40), width=2)
            d.text((x1 - 150, Y(ref) - 14), f"random agent {ref:.3g}", fill=(200, 40, 40))
    d.text((x1 - 120, H - 16), "env steps per seed", fill="black")
    path = Path(path)
    img.save(path)
    return path


def random_agent_reference(config: dict, num_envs: int = 256, num_steps: int = 400, seed: int = 0) -> dict:
    """Episode statistics of the uniform random agent on the same env (for the curves)."""
    from histojax.demo import make_random_rollout

    env, params = make_env(config)
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


def seeds_runner(train, init_params, env_params, config: dict, progress: Progress, mesh: Mesh | None = None):
    """One jitted program over all seeds: ``run(keys, params=None)`` trains ``len(keys)`` seeds
    (``jax.vmap`` over keys, or ``lax.map`` with ``config["vmap_seeds"] = False``) on
    ``env_params`` (or ``params``); ``run.compile(keys)`` compiles ahead of time and returns the
    same call. With a ``mesh`` (:func:`batch_mesh`) the keys and env params (slide arrays) are
    placed replicated on its devices; ``train`` shards the env batch itself (:func:`shard_batch`).
    Shared by PPO and DQN."""
    def all_seeds(keys, p):
        # Initial parameters always via lax.map: jit(vmap(init)) of the orthogonal initialisers
        # (batched QR) never finished on jaxlib 0.10's CPU backend.
        params = jax.lax.map(lambda k: init_params(k, p), keys)
        if config["vmap_seeds"]:
            return jax.vmap(train, in_axes=(0, None, 0))(keys, p, params)
        return jax.lax.map(lambda kp: train(kp[0], p, kp[1]), (keys, params))

    jitted = jax.jit(all_seeds)
    # replicated on the mesh's devices (a no-op for arrays already placed there)
    place = (lambda x: x) if mesh is None else (lambda x: jax.device_put(x, NamedSharding(mesh, P())))

    def run(keys, params=None):
        progress.t0 = time.perf_counter()
        return jitted(place(keys), place(env_params if params is None else params))

    def compile_(keys, params=None):
        """Compile ahead of time; returns ``compiled(keys, params=None)`` (``.exe``: the
        ``jax.stages.Compiled``, e.g. for ``.as_text()``)."""
        params = place(env_params if params is None else params)
        exe = jitted.lower(place(keys), params).compile()

        def call(keys, p=None):
            progress.t0 = time.perf_counter()
            return exe(place(keys), params if p is None else place(p))
        call.exe = exe
        return call

    run.compile, run.raw, run.mesh = compile_, train, mesh
    return run
