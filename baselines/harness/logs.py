"""What a run writes and prints: progress lines, checkpoints (flax.serialization msgpack), logs (CSV / JSON),
TensorBoard scalars, and the NaN-aware means and smoothing they use."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from baselines import outputs
from baselines.common.config import canonical_config
from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe


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
        extra = "  ".join(
            f"{k} {_number(v, '.4g')}"
            for k, v in m.items()
            if k not in ("return", "success", "steps_to_success", "episodes")
        )
        print(
            f"[{self.name}, {seed}] update {update + 1}/{self.num_updates}  env steps/seed {steps:,}  "
            f"return {_number(m['return'], '.3f')}  success {_number(m['success'], '.1%')}  "
            f"steps-to-success {_number(m['steps_to_success'], '.1f')}  {extra}  ({dt:.0f} s)",
            flush=True,
        )


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
    return jax.pure_callback(
        progress, jax.ShapeDtypeStruct((), jnp.int32), update, metrics, vmap_method="broadcast_all"
    )


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
    w.write_text(out / "config.json", json.dumps(json_safe(config), indent=2, default=str, allow_nan=False))
    return path


MAX_RUN_CONFIG_BYTES = 16 << 20
"""A run's ``config.json`` larger than this (16 MiB; a trainer writes about 1 KB) is not read."""


def _read_regular(path: Path, what: str, max_bytes: int | None = None) -> bytes:
    """The bytes of ``path`` (a link to a regular file is followed: the user's choice), refused in one line naming
    it when it is not a regular file (a FIFO would block the read for ever), larger than ``max_bytes`` when given,
    or changed into one while it was opened. ``OSError`` (e.g. missing) as ``open`` raises it."""
    import os
    import stat

    from data_tools.bundle_files.safe_files import not_regular

    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise HistojaxDataError(path, f"is {not_regular(st)}, not a {what}; refusing to read it")
    if max_bytes is not None and st.st_size > max_bytes:
        raise HistojaxDataError(path, f"{st.st_size:,} bytes, more than a {what} holds ({max_bytes:,}); not read")
    with os.fdopen(os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)), "rb") as f:  # never blocks
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise HistojaxDataError(path, f"changed while it was opened (not a regular file now), not a {what}")
        return f.read() if max_bytes is None else f.read(max_bytes + 1)


def load_checkpoint(path) -> tuple[dict, dict]:
    """``(params, config)`` from a checkpoint file or its run folder. A missing, truncated or corrupt file, one
    that is not a regular file (a FIFO: never waited on), parameters holding NaN or infinite values (a run that
    diverged: every score it gives would be NaN) or a ``config.json`` that is not a JSON object raise
    HistojaxDataError naming it."""
    path = Path(path)
    if path.is_dir():
        path = path / "params.msgpack"
    try:
        data = _read_regular(path, "checkpoint")
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the checkpoint ({e.strerror or e})") from e
    try:
        params = serialization.msgpack_restore(data)
    except Exception as e:  # msgpack's errors (ExtraData, ValueError "incomplete input", ...) share no base
        raise HistojaxDataError(path, f"not a readable checkpoint, truncated or corrupt ({e}); train again") from e
    for leaf in jax.tree.leaves(params):
        arr = np.asarray(leaf)
        if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
            raise HistojaxDataError(
                path, "holds NaN or infinite parameters (a run that diverged?); every score would be NaN: train again"
            )
    config_path = path.parent / "config.json"
    try:
        config = json.loads(_read_regular(config_path, "run's config", MAX_RUN_CONFIG_BYTES))
    except OSError as e:
        raise HistojaxDataError(config_path, f"cannot read the run's config ({e.strerror or e})") from e
    except (ValueError, RecursionError) as e:  # RecursionError: nested deeper than the parser recurses
        raise HistojaxDataError(config_path, f"not valid JSON, truncated or corrupt ({e})") from None
    if not isinstance(config, dict):
        raise HistojaxDataError(config_path, f"holds a JSON {type(config).__name__}, not a run's config (an object)")
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
        w.writerow(
            [
                "step",
                "mean_return",
                "success_rate",
                "success_rate_min_seed",
                "success_rate_max_seed",
                "mean_length",
                "mean_steps_to_success",
            ]
        )
        for i, s in enumerate(steps):
            col = {k: np.asarray(metrics[k])[:, i] for k in keys}
            w.writerow(
                [
                    int(s),
                    _fmt(finite_mean(col["return"])),
                    _fmt(finite_mean(col["success"])),
                    _fmt(finite_extreme(col["success"], np.min)),
                    _fmt(finite_extreme(col["success"], np.max)),
                    _fmt(finite_mean(col["length"])),
                    _fmt(finite_mean(col["steps_to_success"])),
                ]
            )
    data = {
        "summary": summary,
        "step": [int(s) for s in steps],
        "per_seed": {k: np.asarray(v).tolist() for k, v in metrics.items()},
    }
    files.write_text(out / "log.json", json.dumps(json_safe(data), default=_json_default, allow_nan=False))  # NaN: null


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
        w = a[..., max(0, i - k + 1) : i + 1]
        out[..., i] = finite_mean(w, axis=-1)
    return out


def tensorboard_writer(out: Path):
    """A ``tensorboardX.SummaryWriter`` writing event files into ``out`` (beside ``log.csv``), or None when
    tensorboardX is not installed (it is optional: ``pip install tensorboardX``)."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(logdir=str(out))


def _tensorboard_scalars(writer, metrics: dict, first_update: int, steps_per_update: int) -> None:
    """The seed means of one chunk's ``metrics`` (``(seeds, n)``) as scalars ``train/NAME`` at env steps per seed."""
    for j in range(next(iter(metrics.values())).shape[1]):
        step = (first_update + j + 1) * steps_per_update
        for k, v in metrics.items():
            value = finite_mean(v[:, j])
            if np.isfinite(value):
                writer.add_scalar(f"train/{k}", value, step)
    writer.flush()
