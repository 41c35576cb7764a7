"""The gigapixel case end to end, nothing to download: write a large semi-synthetic pyramidal TIFF
(``data_tools.datasets.synth.large_slide``: mostly glass, real CAMELYON16 tissue and tumour outlines, synthetic pixels),
build it into a tiled bundle (streamed, in a child process so its peak RSS is its own), and run the
env at full resolution.

Prints: TIFF write time and size; build time and peak RAM; per level the device bytes against
(kept tiles × tile bytes) and against the dense level; env steps/s at batch ``--batch`` on the finest
level (``lax.scan`` over ``vmap(step)``, random pan actions, starts on random tissue tiles).

    python benchmarks/large_slide.py [--size 100000] [--tissue-fraction 0.1] [--levels 3] [--out out/large]
                                     [--batch 1024] [--steps 100] [--reuse] [--cleanup] [--compare-sample]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def finest_steps_per_second(env, params, batch: int, steps: int) -> float:
    """Env steps/s of ``lax.scan`` over ``vmap(step)`` with ``batch`` envs on the finest level: starts on
    random tissue tiles (kept tiles of a tiled bundle, tiles with any saturation for a dense one), random
    pan / stay actions (UP, DOWN, LEFT, RIGHT, STAY), best of 3 timed scans of ``steps`` steps."""
    import jax
    import jax.numpy as jnp

    import histojax

    t = env.tile_size
    finest = env.n_levels - 1
    level = env.bundles[0].pixels[finest]
    if hasattr(level, "index"):
        cells = np.argwhere(level.index > 0)
    else:
        gh, gw = level.shape[0] // t, level.shape[1] // t
        tiles = level[: gh * t, : gw * t].reshape(gh, t, gw, t, 3)
        cells = np.argwhere((tiles.max(axis=(1, 3, 4)).astype(int) - tiles.min(axis=(1, 3, 4))) > 40)
    rng = np.random.default_rng(0)
    pick = cells[rng.integers(0, len(cells), batch)]
    zeros = jnp.zeros((batch,), jnp.int32)
    w, h = int(params.slide.level_width[finest]), int(params.slide.level_height[finest])
    state = histojax.EnvState(
        z=zeros + finest,
        x=jnp.asarray(np.minimum(pick[:, 1] * t, w - t), jnp.int32),
        y=jnp.asarray(np.minimum(pick[:, 0] * t, h - t), jnp.int32),
        t=zeros,
        slide_index=zeros,
        orientation=zeros,
    )
    pan = jnp.asarray([0, 1, 2, 3, 6], jnp.int32)  # stay on the finest level

    def run(key, state, params):
        def body(carry, key):
            state, _, checksum = carry
            a = pan[jax.random.randint(key, (batch,), 0, 5)]
            obs, state, reward, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, batch), state, a, params
            )
            return (state, obs, checksum + reward.sum()), None  # every observation is materialised

        obs0 = jnp.zeros((batch, t, t, 3), jnp.uint8)
        carry, _ = jax.lax.scan(body, (state, obs0, jnp.float32(0)), jax.random.split(key, steps))
        return carry

    fn = jax.jit(run)
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(fn(key, state, params))
    best = float("inf")
    for i in range(3):
        t0 = time.perf_counter()
        carry = jax.block_until_ready(fn(jax.random.fold_in(key, i), state, params))
        best = min(best, time.perf_counter() - t0)
    assert int(np.asarray(carry[0].z).min()) == finest
    return batch * steps / best


def compare_sample(batch: int, steps: int) -> dict:
    """Finest-level steps/s on the embedded sample slide, dense vs tiled bundle (same views and rewards)."""
    import tempfile

    import histojax
    from data_tools.bundle import build_bundle

    data = Path(histojax.__file__).parent / "data"
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for storage in ("dense", "tiled"):
            b = build_bundle(
                data / "CMU-1-Small-Region.svs",
                Path(tmp) / storage,
                progress=False,
                storage=storage,
                annotations_path=data / "CMU-1-Small-Region.target.xml",
                level_sets=(7,),
            )
            env, params = histojax.make("HistoJAX-Hard-v0", slide=b, auto_reset=False, max_steps_in_episode=10**9)
            out[storage] = round(finest_steps_per_second(env, params, batch, steps))
            print(f"sample slide, {storage} bundle: {out[storage]:,} finest-level steps/s at batch {batch}", flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=100_000, help="canvas side in level-0 px (default 100000)")
    p.add_argument("--tissue-fraction", type=float, default=0.1)
    p.add_argument("--levels", type=int, default=3, help="zoom level count of the bundle and env (default 3)")
    p.add_argument("--tile-size", type=int, default=128)
    p.add_argument("--out", default="out/large", help="folder for the TIFF, bundle and results.json")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--steps", type=int, default=100, help="steps per timed scan")
    p.add_argument("--reuse", action="store_true", help="reuse an existing TIFF / bundle of the same size")
    p.add_argument("--cleanup", action="store_true", help="delete the TIFF and bundle at the end")
    p.add_argument("--max-device-gib", type=float, default=16.0)
    p.add_argument(
        "--compare-sample",
        action="store_true",
        help="also time the embedded sample slide's finest level, dense vs tiled bundle",
    )
    args = p.parse_args()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tif = out / f"large_{args.size}.tif"
    bundle = out / f"large_{args.size}_bundle"
    results: dict = {
        "size": args.size,
        "tissue_fraction": args.tissue_fraction,
        "levels": args.levels,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
    }
    previous = out / f"results_{args.size}.json"
    if args.reuse and previous.is_file():  # keep the write / build figures of the run that made them
        results = {**json.loads(previous.read_text()), **results}

    # 1. the TIFF
    if not (args.reuse and tif.is_file()):
        from data_tools.datasets.synth.large_slide import make_large_slide

        t0 = time.perf_counter()
        prov = make_large_slide(tif, size=args.size, tissue_fraction=args.tissue_fraction)
        results["tiff_seconds"] = round(time.perf_counter() - t0, 1)
        results["tiff_tile_counts"] = prov["tile_counts"]
        results["tissue_fraction_actual"] = round(prov["tissue_fraction"], 4)
        results["tumour_fraction_actual"] = round(prov["tumour_fraction"], 5)
    results["tiff_bytes"] = tif.stat().st_size
    results["writer_peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(
        f"TIFF {tif}: {args.size}×{args.size} px, {results['tiff_bytes'] / 2**20:.1f} MiB, "
        f"written in {results.get('tiff_seconds', 'n/a')} s (writer peak RSS "
        f"{results['writer_peak_rss_bytes'] / 2**20:.0f} MiB)",
        flush=True,
    )

    # 2. the tiled bundle, built in a child process
    if not (args.reuse and (bundle / "metadata.json").is_file()):
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "data_tools",
                "build",
                str(tif),
                "--annotations",
                str(tif.with_suffix(".geojson")),
                "--out",
                str(bundle),
                "--levels",
                str(args.levels),
                "--tile-size",
                str(args.tile_size),
                "--storage",
                "tiled",
                "--overwrite",
            ],
            check=True,
        )
        results["build_seconds"] = round(time.perf_counter() - t0, 1)
    from data_tools.bundle_files.reading import read_metadata

    meta = read_metadata(bundle)
    t = meta.tile_size
    results["build_peak_rss_bytes"] = meta["build"]["peak_rss_bytes"]
    results["build_seconds_per_level"] = meta["build"]["seconds_per_level"]
    print(
        f"build: {results.get('build_seconds', 'n/a')} s, peak RSS {results['build_peak_rss_bytes'] / 2**20:.0f} MiB",
        flush=True,
    )
    rows = []
    for lv in meta.levels:
        tissue_bytes = lv["kept_tiles"] * t * t * 3
        ratio = lv["device_bytes"] / max(tissue_bytes, 1)
        rows.append(
            {
                "downsample": lv["downsample"],
                "size": [lv["width"], lv["height"]],
                "grid": lv["grid"],
                "kept_tiles": lv["kept_tiles"],
                "pool_tiles": lv["pool_tiles"],
                "sat_pool_tiles": lv["sat_pool_tiles"],
                "device_bytes": lv["device_bytes"],
                "dense_device_bytes": lv["dense_device_bytes"],
                "ratio_to_tissue_tiles": round(ratio, 3),
            }
        )
        print(
            f"  level {lv['width']}×{lv['height']} px (downsample {lv['downsample']:.4g}): "
            f"{lv['kept_tiles']:,} tissue tiles of {lv['grid'][0] * lv['grid'][1]:,}, device "
            f"{lv['device_bytes'] / 2**20:,.1f} MiB = {ratio:.3f} × tissue tiles' bytes; dense would be "
            f"{lv['dense_device_bytes'] / 2**20:,.1f} MiB",
            flush=True,
        )
    results["per_level"] = rows
    results["device_bytes"] = meta.device_bytes
    results["dense_device_bytes"] = sum(lv["dense_device_bytes"] for lv in meta.levels)

    # 3. the env at full resolution
    import jax

    import histojax

    env_id = {3: "HistoJAX-Easy-v0", 5: "HistoJAX-Medium-v0", 7: "HistoJAX-Hard-v0"}[args.levels]
    t0 = time.perf_counter()
    env, params = histojax.make(
        env_id,
        slide=bundle,
        verify=False,
        auto_reset=False,
        max_device_bytes=int(args.max_device_gib * 2**30),
        max_steps_in_episode=10**9,
    )
    results["load_seconds"] = round(time.perf_counter() - t0, 1)
    w, h = int(params.slide.level_width[-1]), int(params.slide.level_height[-1])
    results["steps_per_second"] = round(finest_steps_per_second(env, params, args.batch, args.steps))
    results["batch"] = args.batch
    print(
        f"env: {env_id} loaded in {results['load_seconds']} s ({sum(int(a.nbytes) for a in jax.tree.leaves(params.slide)) / 2**20:,.0f} MiB "
        f"of device arrays); finest level {w}×{h} px: {results['steps_per_second']:,} steps/s at batch "
        f"{args.batch} (lax.scan over vmap(step), pan actions)",
        flush=True,
    )
    if args.compare_sample:
        results["sample_steps_per_second"] = compare_sample(args.batch, args.steps)
    (out / f"results_{args.size}.json").write_text(json.dumps(results, indent=1))
    if args.cleanup:
        shutil.rmtree(bundle, ignore_errors=True)
        tif.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
