"""Host memory, each measurement in a child process so its peak RSS is its own:

* ``make`` on a dense bundle: peak RSS (VmHWM) rise over the imports against the bytes put on the device
  (on the CPU backend the device copy lives in host RAM too, so it is part of the rise);
* a tiled build of a single-level (non-pyramidal) TIFF: peak RSS of the build (``--single`` writes one
  from a semi-synthetic pyramid first; sizes in px a side). Linux only (``/proc/self/status``).

    python benchmarks/host_memory.py [--size 8192] [--single 20000] [--out /tmp/histojax-host-memory]

* ``--reader DATASET``: reader training (``baselines.ppo``, ``HistoJAX-C16-Diagnosis-v2``, features, the
  train split) stage by stage: RSS and peak RSS after the imports, each stage of ``make`` (the slides
  loaded, stacked, the reading mode's tables), ``make_train``, the compile and the training run, and the
  bytes of the arrays each stage holds (``--mode glimpse:2 --num-envs 256``, 16 steps × 2 updates).

    python benchmarks/host_memory.py --reader /work/c16-full [--mode glimpse:2] [--num-envs 256]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

_MAKE = """
import sys, warnings
warnings.simplefilter("ignore")
import jax, histojax
def status(key):  # kB → bytes
    return int(next(l for l in open("/proc/self/status") if l.startswith(key)).split()[1]) * 1024
with open("/proc/self/clear_refs", "w") as f:  # reset the peak (VmHWM), which a child inherits at fork
    f.write("5")
base = status("VmRSS:")
env, params = histojax.make("HistoJAX-Hard-v0", slide=sys.argv[1])
device = sum(int(a.nbytes) for a in jax.tree.leaves(params.slide))
rise = status("VmHWM:") - base
print(f"make (Hard, 7 levels): {device / 2**20:.0f} MiB on the device, peak RSS rise {rise / 2**20:.0f} MiB "
      f"({rise / device:.2f}x the device bytes; backend {jax.default_backend()})")
"""

_BUILD = """
import sys, time, warnings
warnings.simplefilter("ignore")
from data_tools.bundle import build_bundle
with open("/proc/self/clear_refs", "w") as f:  # reset the peak (VmHWM), which a child inherits at fork
    f.write("5")
t0 = time.perf_counter()
build_bundle(sys.argv[1], sys.argv[2], storage="tiled", progress=False, overwrite=True)
hwm = int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM:")).split()[1]) * 1024
print(f"tiled build of {sys.argv[1]}: peak RSS {hwm / 2**20:.0f} MiB, {time.perf_counter() - t0:.0f} s")
"""


_READER = r"""
import json, sys, time, warnings
warnings.simplefilter("ignore")
def status(key):  # kB -> bytes
    return int(next(l for l in open("/proc/self/status") if l.startswith(key)).split()[1]) * 1024
with open("/proc/self/clear_refs", "w") as f:  # reset the peak (VmHWM), which a child inherits at fork
    f.write("5")
rows, t0 = [], time.perf_counter()
def mark(stage, held=None):
    rows.append({"stage": stage, "rss_gb": status("VmRSS:") / 2**30, "peak_gb": status("VmHWM:") / 2**30,
                 "held_gb": None if held is None else held / 2**30, "s": time.perf_counter() - t0})
    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
def nbytes(tree):
    import jax
    return sum(int(getattr(a, "nbytes", 0)) for a in jax.tree.leaves(tree))
dataset, mode, num_envs, steps, updates = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
import jax
import histojax
from histojax import registry
from baselines import ppo
from baselines.harness.runner import compile_seeds
mark("imports (jax, histojax, baselines.ppo)")
loads = []
load_slide, stack_slides = registry.load_slide, registry.stack_slides
def counted_load(*a, **k):
    out = load_slide(*a, **k)
    loads.append(nbytes(out[0]))
    return out
def counted_stack(slides, **k):
    mark(f"{len(slides)} slides loaded (make)", sum(loads))
    out = stack_slides(slides, **k)
    mark("slides stacked into one SlideArrays (make)", nbytes(out))
    return out
registry.load_slide, registry.stack_slides = counted_load, counted_stack
config = {"env_id": "HistoJAX-C16-Diagnosis-v2", "action_mode": mode, "obs_mode": "features",
          "env_kwargs": {"dataset": dataset, "split": "train", "read_budget": 0.1}, "num_envs": num_envs,
          "num_steps": steps, "total_timesteps": num_envs * steps * updates, "num_minibatches": 4,
          "update_epochs": 2, "print_progress": False, "num_seeds": 1}
train = ppo.make_train(config)
p = train.env_params
mark("make_train (make: mode tables; network)", nbytes(p))
print(json.dumps({"slide_arrays_gb": nbytes(p.slide) / 2**30, "mode_tables_gb": nbytes(p.mode_data) / 2**30,
                  "slides": int(p.slide.num_slides)}), file=sys.stderr, flush=True)
keys = jax.random.split(jax.random.key(0), 1)
call = compile_seeds(train, keys)
mark("compiled")
jax.block_until_ready(call(keys))
mark(f"trained ({num_envs} envs x {steps} steps x {updates} updates)")
print(json.dumps(rows))
"""


def reader_memory(dataset, mode: str, num_envs: int, steps: int, updates: int) -> list[dict]:
    """Run the reader-training stages in a child process: its rows (stage, rss_gb, peak_gb, held_gb, s)."""
    import json

    done = subprocess.run(
        [sys.executable, "-c", _READER, str(dataset), mode, str(num_envs), str(steps), str(updates)],
        stdout=subprocess.PIPE,
        text=True,
    )  # stages printed live on stderr
    if done.returncode != 0:
        raise SystemExit(f"host_memory: reader training failed (exit status {done.returncode})")
    return json.loads(done.stdout.strip().splitlines()[-1])


def single_level_tiff(pyramid: Path, out: Path, tile: int = 512) -> Path:
    """Level 0 of ``pyramid`` rewritten as a single-level tiled JPEG TIFF, one tile at a time."""
    import numpy as np
    import tifffile

    from data_tools.slide_files.open import open_slide

    with open_slide(pyramid) as r:
        w, h = r.dimensions
        tiles = (r.read_region(0, x, y, tile, tile) for y in range(0, h, tile) for x in range(0, w, tile))
        tifffile.imwrite(
            out, tiles, shape=(h, w, 3), dtype=np.uint8, tile=(tile, tile), photometric="rgb", compression="jpeg"
        )
    return out


def main(argv=None) -> int:
    """Print the figures; returns 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=8192, help="side in px of the dense bundle's slide (default 8192)")
    p.add_argument("--single", type=int, default=0, help="side in px of a single-level TIFF to build tiled (0: skip)")
    p.add_argument("--out", default="/tmp/histojax-host-memory")
    p.add_argument("--reader", type=Path, help="a dataset folder: measure reader training on it stage by stage")
    p.add_argument("--mode", default="glimpse:2", help="the reader's action mode (default glimpse:2)")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=16, help="steps per update (default 16)")
    p.add_argument("--updates", type=int, default=2)
    args = p.parse_args(argv)
    if args.reader is not None:
        if not (args.reader / "dataset.json").is_file():
            print(
                f"host_memory: {args.reader}: no dataset.json (make one with python -m data_tools c16 ...)",
                file=sys.stderr,
            )
            return 2
        print(f"reader training on {args.reader}, {args.mode}, {args.num_envs} envs:")
        print(f"{'stage':58s} {'RSS GB':>7s} {'peak GB':>8s} {'held GB':>8s} {'s':>6s}")
        for r in reader_memory(args.reader, args.mode, args.num_envs, args.steps, args.updates):
            held = "" if r["held_gb"] is None else f"{r['held_gb']:.2f}"
            print(f"{r['stage']:58s} {r['rss_gb']:7.2f} {r['peak_gb']:8.2f} {held:>8s} {r['s']:6.0f}")
        return 0
    from data_tools.bundle import build_bundle
    from data_tools.datasets.synth.large_slide import make_large_slide

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    slide = out / f"pyramid{args.size}.tif"
    if not slide.exists():
        make_large_slide(slide, size=args.size, tissue_fraction=0.1, seed=0, progress=False)
    bundle = out / f"dense{args.size}"
    if not bundle.exists():
        build_bundle(
            slide,
            bundle,
            annotations_path=slide.with_suffix(".geojson"),
            tile_size=64,
            magnification_range=16,
            progress=False,
        )
    subprocess.run([sys.executable, "-c", _MAKE, str(bundle)], check=True)
    if args.single:
        pyramid = out / f"pyramid{args.single}.tif"
        if not pyramid.exists():
            make_large_slide(pyramid, size=args.single, tissue_fraction=0.1, seed=0, progress=False)
        single = out / f"single{args.single}.tif"
        if not single.exists():
            single_level_tiff(pyramid, single)
        subprocess.run([sys.executable, "-c", _BUILD, str(single), str(out / f"tiled{args.single}")], check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
