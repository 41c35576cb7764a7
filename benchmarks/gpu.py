"""Every GPU figure the project owes, from one command, in one process, under one time budget
(``make bench-gpu``). It also runs on a CPU at smaller sizes (``--tiny``), which is how
``tests/training/test_bench_gpu.py`` keeps it from rotting.

Sections, in the order they run (each is measured, or says why it was skipped):

1. ``machine``: device kind, GPU model / driver / memory from ``nvidia-smi`` when present, device
   memory as JAX reports it, JAX and jaxlib versions, the command line.
2. ``copy``: the device's memory-copy bandwidth (a jitted elementwise copy ``x + 1`` of a large
   ``uint8`` array; GB/s counts the bytes of the array once per call), and the equivalent bound for
   pixel observations in views/s (bandwidth / bytes of one ``T × T × 3`` view).
3. ``env``: env steps/s of ``lax.scan`` over ``vmap(step)`` (random actions, auto-reset, every
   observation materialised: :func:`benchmarks.throughput.full_step_rollout`) on the sample slide,
   pixels and features, at batch 1, 4, 16, … up to ``--max-batch`` (default 65,536); a batch that
   runs out of device memory (XLA ``RESOURCE_EXHAUSTED``) stops the growth, and the table says so.
   Pixel rows stand beside the copy bound (a pixel step writes at least one view).
4. ``ppo``: PPO end-to-end env steps/s (:func:`baselines.ppo.make_train`, ``HistoJAX-Easy-v0``) on
   features and on pixels; compile time measured apart (:func:`baselines.harness.runner.compile_seeds`), not in the rate.
5. ``encoders``: embedding views/s of every encoder :func:`encoder_names` lists (128-px views,
   uint8); an encoder whose optional dependency or weights are missing is skipped with the reason.
6. ``dataset``: a C16 dataset (``--dataset DIR``, or the small variant built into ``OUT/c16-small``
   with ``colour-stats`` features) in feature mode: env steps/s per batch and the bytes of the slide
   arrays on the device; and in pixel mode when the dataset has pixels and they fit the device
   (the full true-scale set needs 27.6 / 34.3 / 42.4 GiB for 3 / 5 / 7 levels; see
   docs/results/c16.md), else the reason.

Time budget: ``--time-budget`` seconds (default 480, so one 10-minute device run holds it with room
for start-up); once it is spent, the items left are skipped and named as skipped for time. Writes
``OUT/gpu.json`` and ``OUT/gpu.md`` (the markdown table it also prints).

    python benchmarks/gpu.py --out benchmarks/results/gpu
    python benchmarks/gpu.py --tiny --out /tmp/gpu-tiny            # CPU, seconds
    python benchmarks/gpu.py --dataset c16-full --levels 7 --out benchmarks/results/gpu-c16-full
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import histojax  # noqa: E402
from benchmarks.throughput import full_step_rollout  # noqa: E402
from data_tools.cli_output import command_main, positive_float  # noqa: E402
from data_tools.errors import HistojaxDataError  # noqa: E402

GIB = 2**30
# device bytes of the full true-scale C16 set (docs/c16-benchmark.md, benchmarks/c16_device_bytes.py)
C16_FULL_GIB = {"pixels": {3: 27.6, 5: 34.3, 7: 42.4}, "features (colour-stats)": {3: 0.98, 5: 1.33, 7: 1.73}}


# ----------------------------------------------------------------------------- helpers
class Budget:
    """Seconds left of the run's time budget (wall clock from construction)."""

    def __init__(self, seconds: float):
        self.seconds, self.t0 = float(seconds), time.perf_counter()

    def used(self) -> float:
        return time.perf_counter() - self.t0

    def spent(self) -> bool:
        return self.used() >= self.seconds

    def skip_reason(self) -> str:
        return f"time budget spent ({self.used():.0f} s of --time-budget {self.seconds:.0f} s)"


def is_oom(error: BaseException) -> bool:
    """Whether ``error`` is XLA running out of device memory."""
    text = f"{type(error).__name__}: {error}"
    return any(s in text for s in ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory", "OOM"))


def skipped(reason: str) -> dict:
    return {"skipped": reason}


def encoder_names() -> list[str]:
    """The registered feature encoders: ``data_tools.features``' registry when it has one
    (``ENCODERS`` / ``encoder_names()`` in the package or in ``efficientnet``), else the two that
    ``load_encoder`` knows (EfficientNet-Lite0 and colour-stats)."""
    import data_tools.features as pkg
    from data_tools.features import colour, efficientnet

    for module in (pkg, efficientnet):
        if callable(getattr(module, "encoder_names", None)):
            return list(module.encoder_names())
        if getattr(module, "ENCODERS", None):
            return list(module.ENCODERS)
    return [efficientnet.NAME, colour.NAME]


def colour_feature_bundle(out: Path) -> Path:
    """A copy of the sample bundle at ``out`` with a ``colour-stats`` feature grid (seconds on a CPU)."""
    from data_tools.bundle_files.reading import read_metadata
    from data_tools.features.grid import compute_features
    from histojax.sample import sample_bundle

    if not (out.is_dir() and read_metadata(out).features):
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(sample_bundle(progress=False), out)
        compute_features(out, encoder_name="colour-stats", progress=False)
    return out


def machine(argv) -> dict:
    """The device, its memory, the software versions and the command line."""
    import jaxlib

    dev = jax.devices()[0]
    info = {
        "platform": dev.platform,
        "device_kind": dev.device_kind,
        "device_count": jax.device_count(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "python": platform.python_version(),
        "host": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "command": " ".join(["python", "benchmarks/gpu.py", *argv]),
    }
    try:
        stats = dev.memory_stats() or {}
    except Exception:  # CPU backends may not report
        stats = {}
    info["device_memory_bytes"] = int(stats["bytes_limit"]) if "bytes_limit" in stats else None
    if shutil.which("nvidia-smi"):
        try:
            out = subprocess.run(
                ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                capture_output=True,
                text=True,
                timeout=30,
            ).stdout
            name, driver, memory = [s.strip() for s in out.splitlines()[0].split(",")]
            info.update(gpu=name, driver=driver, gpu_memory=memory)
        except Exception as e:  # noqa: BLE001 - report, do not fail the run
            info["nvidia_smi"] = f"failed: {e}"
    else:
        info["nvidia_smi"] = "not found (no NVIDIA driver on this machine)"
    return info


def copy_bandwidth(nbytes: int, seconds: float) -> float:
    """Device memory-copy bandwidth in bytes/s: a jitted ``x + 1`` over ``nbytes`` of ``uint8`` (read
    and write once each; counted as ``nbytes`` per call, as a copy of ``nbytes``), best call."""
    x = jnp.zeros((nbytes,), jnp.uint8)
    f = jax.jit(lambda a: a + jnp.uint8(1))
    jax.block_until_ready(f(x))  # compile
    best, t_end = float("inf"), time.perf_counter() + seconds
    calls = 0
    while calls < 3 or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        x = jax.block_until_ready(f(x))
        best = min(best, time.perf_counter() - t0)
        calls += 1
    return nbytes / best


def measure(env, params, batch: int, env_steps: int, seconds: float) -> dict:
    """Env steps/s of :func:`benchmarks.throughput.full_step_rollout` (``env_steps // batch`` scan steps
    of ``batch`` envs per call, at least 2), timed over whole calls for at least ``seconds`` after a
    first call that compiles (its seconds, compile plus one call, are returned as ``first_call_s``)."""
    steps = max(2, env_steps // batch)
    fn = full_step_rollout(env, batch, steps)
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(key, params))
    first = time.perf_counter() - t0
    calls, t0 = 0, time.perf_counter()
    while True:
        jax.block_until_ready(fn(jax.random.fold_in(key, calls + 1), params))
        calls += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return {"steps_per_s": calls * steps * batch / elapsed, "first_call_s": first}


def batches_up_to(max_batch: int) -> list[int]:
    """1, 4, 16, … (powers of 4) up to ``max_batch``, and ``max_batch`` itself."""
    out, b = [], 1
    while b < max_batch:
        out.append(b)
        b *= 4
    return out + [max_batch]


def env_rows(env, params, args, budget: Budget, view_bytes: int | None, bandwidth: float | None) -> dict:
    """Steps/s per batch until ``--max-batch``, the budget, or device memory runs out."""
    rows, stop = [], None
    for batch in batches_up_to(args.max_batch):
        if budget.spent():
            stop = f"batch {batch} and up: {budget.skip_reason()}"
            break
        try:
            timing = measure(env, params, batch, args.env_steps, args.seconds)
        except Exception as e:  # noqa: BLE001
            if not is_oom(e):
                raise
            stop = f"batch {batch}: out of device memory ({str(e).splitlines()[0][:160]}); larger batches not tried"
            break
        row = {"batch": batch, **timing}
        if view_bytes and bandwidth:
            row["copy_bound_views_per_s"] = bandwidth / view_bytes
            row["of_copy_bound"] = timing["steps_per_s"] / row["copy_bound_views_per_s"]
        rows.append(row)
    return {"rows": rows, "stopped": stop}


def ppo_item(obs_mode: str, slide, args) -> dict:
    """PPO end-to-end env steps/s on ``HistoJAX-Easy-v0`` (compile apart)."""
    from baselines.harness.runner import compile_and_run
    from baselines.ppo import make_train

    config = {
        "env_id": "HistoJAX-Easy-v0",
        "obs_mode": obs_mode,
        "slide": None if slide is None else str(slide),
        "num_envs": args.ppo_envs,
        "num_steps": args.ppo_steps,
        "num_minibatches": 4,
        "total_timesteps": args.ppo_envs * args.ppo_steps * args.ppo_updates,
        "hidden": args.ppo_hidden,
        "num_seeds": 1,
        "print_progress": False,
        "log_every": 10**9,
    }
    run = make_train(config)
    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    out, compile_s, train_s = compile_and_run(run, keys)
    steps = run.num_updates * run.steps_per_update
    success = float(np.asarray(out["metrics"]["success"])[0, -1])  # NaN when no episode ended
    return {
        "obs_mode": obs_mode,
        "num_envs": args.ppo_envs,
        "num_steps": args.ppo_steps,
        "updates": run.num_updates,
        "env_steps": steps,
        "train_s": train_s,
        "compile_s": compile_s,
        "steps_per_s": steps / train_s,
        "last_update_success": success,
    }


def encoder_item(name: str, args) -> dict:
    """Embedding views/s of the encoder ``name`` on random 128-px uint8 views (compile apart)."""
    from data_tools.features.efficientnet import load_encoder

    try:
        encoder = load_encoder(name)
    except (ImportError, FileNotFoundError, OSError) as e:
        return skipped(f"cannot load {name!r}: {type(e).__name__}: {e}")
    views = jnp.asarray(np.random.default_rng(0).integers(0, 256, (args.encoder_batch, 128, 128, 3), np.uint8))
    t0 = time.perf_counter()
    jax.block_until_ready(encoder.embed(views))
    compile_s = time.perf_counter() - t0
    calls, t0 = 0, time.perf_counter()
    while True:
        jax.block_until_ready(encoder.embed(views))
        calls += 1
        if time.perf_counter() - t0 >= args.seconds:
            break
    return {
        "dim": encoder.dim,
        "image_size": encoder.image_size,
        "batch": args.encoder_batch,
        "compile_s": compile_s,
        "views_per_s": calls * args.encoder_batch / (time.perf_counter() - t0),
    }


def device_memory(info: dict) -> int | None:
    return info.get("device_memory_bytes")


def dataset_item(folder: Path, obs_mode: str, args, budget: Budget, memory: int | None) -> dict:
    """Env steps/s and device bytes of ``folder``'s train split in ``obs_mode``."""
    from data_tools.bundle_files.format import select_levels, slide_device_bytes
    from data_tools.bundle_files.reading import read_metadata

    ds = json.loads((folder / "dataset.json").read_text())
    env_id = f"HistoJAX-C16-{args.c16_level}-v0"
    if obs_mode == "pixels" and memory:
        n_levels = histojax.registry.spec_of(env_id).settings["n_levels"]
        metas = [read_metadata(folder / b) for b in ds[args.split]]
        if all(len(m.pixel_levels) == len(m["levels"]) for m in metas):
            need = sum(slide_device_bytes(m, select_levels(m, n_levels), pixels=True) for m in metas)
            if need > 0.9 * memory:
                return skipped(
                    f"pixel mode needs {need / GIB:.1f} GiB, more than 90 % of the device's {memory / GIB:.1f} GiB"
                )
    t0 = time.perf_counter()
    try:
        env, params = histojax.make(
            env_id,
            dataset=str(folder),
            split=args.split,
            obs_mode=obs_mode,
            with_position=True,
            max_device_bytes=memory or 64 * GIB,
        )
    except Exception as e:  # noqa: BLE001 - a refused mode is a reason, not a crash
        if obs_mode == "pixels" or is_oom(e):
            return skipped(f"make refused it: {type(e).__name__}: {str(e).splitlines()[0][:200]}")
        raise
    made = time.perf_counter() - t0
    device = sum(int(a.nbytes) for a in jax.tree.leaves(params.slide))
    table = env_rows(env, params, _with(args, max_batch=args.dataset_max_batch), budget, None, None)
    return {
        "env_id": env_id,
        "split": args.split,
        "slides": int(params.slide.num_slides),
        "obs_mode": obs_mode,
        "device_bytes": device,
        "make_s": made,
        **table,
    }


def _with(args, **changes):
    import argparse

    return argparse.Namespace(**{**vars(args), **changes})


def small_c16(out: Path) -> Path:
    """The small C16 variant with ``colour-stats`` features, built into ``out`` once (seconds)."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    if not (out / "dataset.json").is_file():
        make_c16_dataset(out, small=True, features="colour-stats", progress=False)
    return out


# ----------------------------------------------------------------------------- the run
def add_arguments(p) -> None:
    p.add_argument("--out", default="benchmarks/results/gpu", help="folder for gpu.json and gpu.md")
    p.add_argument(
        "--tiny",
        action="store_true",
        help="CPU-sized settings (seconds): max batch 16, 0.05 s per figure, 4 MiB copy, tiny PPO, "
        "colour-stats features, EfficientNet skipped",
    )
    p.add_argument("--time-budget", type=positive_float, default=480.0, help="seconds for the whole run (default 480)")
    p.add_argument("--max-batch", type=int, default=None, help="largest env batch (default 65536; --tiny 16)")
    p.add_argument(
        "--seconds", type=positive_float, default=None, help="timed seconds per figure (default 1; --tiny 0.05)"
    )
    p.add_argument(
        "--env-steps",
        type=int,
        default=None,
        help="env steps per timed call, split over the batch (default 65536; --tiny 256)",
    )
    p.add_argument(
        "--copy-mb", type=int, default=None, help="MiB copied for the bandwidth bound (default 1024; --tiny 4)"
    )
    p.add_argument("--env", default="HistoJAX-Hard-v0", help="env of the batch sweep (sample slide)")
    p.add_argument(
        "--features-encoder",
        default=None,
        help="feature grid of the sweep's feature rows: efficientnet-lite0 (default) or colour-stats (--tiny)",
    )
    p.add_argument("--ppo-envs", type=int, default=None, help="PPO envs (default 4096; --tiny 8)")
    p.add_argument("--ppo-steps", type=int, default=None, help="PPO steps per update (default 64; --tiny 4)")
    p.add_argument("--ppo-updates", type=int, default=None, help="PPO updates timed (default 8; --tiny 1)")
    p.add_argument("--ppo-hidden", type=int, default=None, help="PPO network width (default 256; --tiny 16)")
    p.add_argument("--encoder-batch", type=int, default=None, help="views per encoder call (default 1024; --tiny 4)")
    p.add_argument(
        "--skip-encoders",
        nargs="*",
        default=None,
        metavar="NAME",
        help="encoders not measured (default none; --tiny efficientnet-lite0)",
    )
    p.add_argument(
        "--dataset", default=None, help="C16 dataset folder (default: build the small variant in OUT/c16-small)"
    )
    p.add_argument("--split", default="train", choices=("train", "test"))
    p.add_argument(
        "--c16-level",
        default="Easy",
        choices=("Easy", "Medium", "Hard"),
        help="HistoJAX-C16-<level>-v0: 3 / 5 / 7 levels",
    )
    p.add_argument(
        "--dataset-max-batch", type=int, default=None, help="largest dataset batch (default 16384; --tiny 16)"
    )
    p.add_argument("--no-dataset-pixels", action="store_true", help="skip the dataset's pixel mode")


def argparse_defaults(tiny: bool = True):
    """The parsed defaults (``--tiny`` ones by default), for callers that build the pieces themselves."""
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--tiny"] if tiny else [])
    _defaults(args)
    return args


def _defaults(args) -> None:
    tiny = args.tiny
    for name, big, small in [
        ("max_batch", 65536, 16),
        ("seconds", 1.0, 0.05),
        ("env_steps", 65536, 256),
        ("copy_mb", 1024, 4),
        ("features_encoder", "efficientnet-lite0", "colour-stats"),
        ("ppo_envs", 4096, 8),
        ("ppo_steps", 64, 4),
        ("ppo_updates", 8, 1),
        ("ppo_hidden", 256, 16),
        ("encoder_batch", 1024, 4),
        ("skip_encoders", [], ["efficientnet-lite0"]),
        ("dataset_max_batch", 16384, 16),
    ]:
        if getattr(args, name) is None:
            setattr(args, name, small if tiny else big)


def run(args, parser=None) -> int:
    _defaults(args)
    budget = Budget(args.time_budget)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {
        "machine": machine(sys.argv[1:] if _ARGV is None else _ARGV),
        "settings": {k: v for k, v in vars(args).items()},
    }

    def timed(section: str, fn):
        """Run ``fn()`` into ``report[section]`` unless the budget is spent; print progress."""
        if budget.spent():
            report[section] = skipped(budget.skip_reason())
        else:
            t0 = time.perf_counter()
            report[section] = fn()
            print(f"[{budget.used():6.1f} s] {section} done in {time.perf_counter() - t0:.1f} s", flush=True)

    # 2. copy bound
    def copy():
        bw = copy_bandwidth(args.copy_mb * 2**20, args.seconds)
        return {"bytes": args.copy_mb * 2**20, "bytes_per_s": bw}

    timed("copy", copy)
    bandwidth = report["copy"].get("bytes_per_s")

    # 3. env sweep, pixels and features (sample slide)
    def env_pixels():
        env, params = histojax.make(args.env)
        view_bytes = env.tile_size**2 * 3
        return {
            "env_id": args.env,
            "view_bytes": view_bytes,
            **env_rows(env, params, args, budget, view_bytes, bandwidth),
        }

    def feature_bundle():
        if args.features_encoder == "colour-stats":
            return colour_feature_bundle(out / "sample-colour-stats")
        from histojax.sample import sample_feature_bundle

        return sample_feature_bundle()

    def env_features():
        try:
            bundle = feature_bundle()
        except (ImportError, OSError, HistojaxDataError) as e:  # e.g. EfficientNet weights not installed
            return skipped(f"no {args.features_encoder} feature grid: {type(e).__name__}: {e}")
        env, params = histojax.make(args.env, slide=bundle, obs_mode="features")
        return {
            "env_id": args.env,
            "encoder": args.features_encoder,
            "dim": int(params.slide.features.shape[1]),
            **env_rows(env, params, args, budget, None, None),
        }

    timed("env_pixels", env_pixels)
    timed("env_features", env_features)

    # 4. PPO end to end
    def ppo_features():
        grid = report["env_features"]
        if "skipped" in grid:
            return skipped(f"no feature bundle ({grid['skipped']})")
        return ppo_item("features", feature_bundle(), args)

    timed("ppo_features", ppo_features)
    timed("ppo_pixels", lambda: ppo_item("pixels", None, args))

    # 5. encoders
    def encoders():
        result = {}
        for name in encoder_names():
            if name in args.skip_encoders:
                result[name] = skipped("--skip-encoders" if not args.tiny else "--tiny (too slow on a CPU)")
            elif budget.spent():
                result[name] = skipped(budget.skip_reason())
            else:
                result[name] = encoder_item(name, args)
        return result

    timed("encoders", encoders)

    # 6. the C16 dataset
    memory = device_memory(report["machine"])
    folder = [None]

    def dataset_features():
        folder[0] = Path(args.dataset) if args.dataset else small_c16(out / "c16-small")
        return {"dataset": str(folder[0]), **dataset_item(folder[0], "features", args, budget, memory)}

    def dataset_pixels():
        if args.no_dataset_pixels:
            return skipped("--no-dataset-pixels")
        if folder[0] is None:
            return skipped("no dataset (its feature mode was skipped)")
        return {"dataset": str(folder[0]), **dataset_item(folder[0], "pixels", args, budget, memory)}

    timed("dataset_features", dataset_features)
    timed("dataset_pixels", dataset_pixels)

    report["total_s"] = budget.used()
    md = markdown(report)
    (out / "gpu.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    (out / "gpu.md").write_text(md)
    print(md)
    print(f"wrote {out / 'gpu.json'} and {out / 'gpu.md'}")
    return 0


# ----------------------------------------------------------------------------- the table
def _f(x, digits: int = 0) -> str:
    return "—" if x is None else f"{x:,.{digits}f}"


def _memory(m: dict) -> str:
    if m.get("gpu_memory"):
        return m["gpu_memory"]
    return "not reported" if m["device_memory_bytes"] is None else f"{m['device_memory_bytes'] / GIB:.1f} GiB"


def markdown(r: dict) -> str:
    """The report as one markdown page (what docs/results/benchmarks.md takes once measured on a GPU)."""
    m = r["machine"]
    lines = [
        "# histojax GPU benchmark (`benchmarks/gpu.py`)",
        "",
        f"- device: {m.get('gpu', m['device_kind'])} ({m['platform']}, {m['device_count']} device(s)); "
        f"driver {m.get('driver', '—')}; memory {_memory(m)}",
        f"- JAX {m['jax']}, jaxlib {m['jaxlib']}, Python {m['python']}; host {m['host']}",
        f"- command: `{m['command']}`; total {r['total_s']:.0f} s",
        "",
    ]

    def skip_line(name, sec):
        return f"**{name}: skipped** — {sec['skipped']}"

    c = r["copy"]
    lines += [
        "## Memory-copy bound",
        "",
        skip_line("copy", c)
        if "skipped" in c
        else f"jitted `x + 1` over {c['bytes'] / 2**20:,.0f} MiB of uint8: **{c['bytes_per_s'] / 1e9:,.1f} GB/s**",
        "",
    ]
    for key, title in (
        ("env_pixels", "Env steps/s, pixel observations"),
        ("env_features", "Env steps/s, feature observations"),
    ):
        sec = r[key]
        lines += [f"## {title}", ""]
        if "skipped" in sec:
            lines += [skip_line(key, sec), ""]
            continue
        extra = f", {sec['encoder']} {sec['dim']}-d" if "encoder" in sec else f", {sec['view_bytes']:,} B per view"
        lines += [
            f"`{sec['env_id']}`, sample slide{extra}; `lax.scan` over `vmap(step)`, random actions, auto-reset.",
            "",
        ]
        if key == "env_pixels":
            lines += ["| batch | steps/s | copy bound, views/s | of bound |", "|---|---|---|---|"]
            lines += [
                f"| {x['batch']:,} | {_f(x['steps_per_s'])} | {_f(x.get('copy_bound_views_per_s'))} | "
                f"{x['of_copy_bound']:.1%} |"
                if "of_copy_bound" in x
                else f"| {x['batch']:,} | {_f(x['steps_per_s'])} | — | — |"
                for x in sec["rows"]
            ]
        else:
            lines += ["| batch | steps/s |", "|---|---|"] + [
                f"| {x['batch']:,} | {_f(x['steps_per_s'])} |" for x in sec["rows"]
            ]
        if sec["stopped"]:
            lines += ["", f"Stopped: {sec['stopped']}."]
        lines += [""]
    lines += [
        "## PPO end to end (`HistoJAX-Easy-v0`)",
        "",
        "| obs | envs × steps × updates | env steps/s | compile s | last-update success |",
        "|---|---|---|---|---|",
    ]
    for key in ("ppo_features", "ppo_pixels"):
        sec = r[key]
        if "skipped" in sec:
            lines.append(f"| {key[4:]} | skipped: {sec['skipped']} | | | |")
        else:
            succ = "—" if not sec["last_update_success"] >= 0 else f"{sec['last_update_success']:.1%}"
            lines.append(
                f"| {sec['obs_mode']} | {sec['num_envs']} × {sec['num_steps']} × {sec['updates']} | "
                f"{_f(sec['steps_per_s'])} | {sec['compile_s']:.1f} | {succ} |"
            )
    lines += ["", "## Encoders (128-px uint8 views)", ""]
    enc = r["encoders"]
    if "skipped" in enc:
        lines += [skip_line("encoders", enc)]
    else:
        lines += ["| encoder | dim | input px | batch | views/s | compile s |", "|---|---|---|---|---|---|"]
        for name, sec in enc.items():
            lines.append(
                f"| {name} | skipped: {sec['skipped']} | | | | |"
                if "skipped" in sec
                else f"| {name} | {sec['dim']} | {sec['image_size'] or 128} | {sec['batch']} | "
                f"{_f(sec['views_per_s'])} | {sec['compile_s']:.1f} |"
            )
    lines += [""]
    for key, title in (
        ("dataset_features", "C16 dataset, feature mode"),
        ("dataset_pixels", "C16 dataset, pixel mode"),
    ):
        sec = r[key]
        lines += [f"## {title}", ""]
        if "skipped" in sec:
            lines += [skip_line(key, sec), ""]
            continue
        lines += [
            f"`{sec['env_id']}` on `{sec['dataset']}` ({sec['split']}: {sec['slides']} slides), "
            f"{sec['device_bytes'] / GIB:.3f} GiB ({sec['device_bytes']:,} B) of slide arrays on the device; "
            f"make {sec['make_s']:.1f} s.",
            "",
            "| batch | steps/s |",
            "|---|---|",
        ]
        lines += [f"| {x['batch']:,} | {_f(x['steps_per_s'])} |" for x in sec["rows"]]
        if sec["stopped"]:
            lines += ["", f"Stopped: {sec['stopped']}."]
        lines += [""]
    return "\n".join(lines) + "\n"


_command = command_main(add_arguments, run, "python benchmarks/gpu.py", __doc__)


def main(argv=None) -> int:
    """``python benchmarks/gpu.py``: parse ``argv`` (default ``sys.argv[1:]``), run, return the exit status."""
    global _ARGV
    _ARGV = list(sys.argv[1:] if argv is None else argv)
    return _command(argv)


_ARGV: list[str] | None = None  # the command line of the current run, for the report

if __name__ == "__main__":
    raise SystemExit(main())
