"""HistoGym vs histojax, measured in one run on the same slide.

(a) **HistoGym-style loop**: one Python env re-implementing XjtuAI/HistoGym's ``gymhisto.py`` step
    (random action; positions in DeepZoom tile units, fractional after a zoom; each step reads the
    view with OpenSlide ``DeepZoomGenerator(slide, tile_size, overlap=1, limit_bounds=False)``
    ``.get_tile(level, (col, row))``, resizes it to the observation size and converts it to a
    channel-first numpy array; at the finest DeepZoom level the reward's overlap is computed with
    shapely as HistoGym's ``utils/coordination.check_overlap`` does: every annotation polygon of
    every level rebuilt with ``Polygon(...).buffer(0)``, a box at ``(col·256, row·256)`` of side
    ``tile_size``, the last intersecting polygon kept). HistoGym's per-step ``print`` goes to
    ``os.devnull`` (formatting kept, terminal I/O not), which can only make HistoGym look faster.
(b) **histojax**, jitted, ``vmap`` over the batch and ``lax.scan`` over steps, random actions,
    auto-reset, ``reward="histogym"`` (``benchmarks/throughput.py``'s ``full_step_rollout`` /
    ``measure``), with pixel observations and with feature observations (``obs_mode="features"``;
    if the bundle has no feature grid, a random float16 grid of the ``features`` command's default
    shape — 1280-d, stride = tile size — is attached in memory: the step's cost does not depend on
    the values).
(c) The ratios histojax / HistoGym-style per batch against the targets (pixels ≥ 1,000×,
    features ≥ 10,000×).
(d) The batched crop's bandwidth (view bytes/s at batch 1024) against numpy's memory-copy
    bandwidth measured in the same run (target ≥ 50 %), plus alternative crop formulations
    (:func:`crop_alternatives`), each checked for exactness against ``histojax.core.views.view_pixels``
    and timed alone and inside the full step.

    python benchmarks/vs_histogym.py [--quick] [--slide FILE --annotations FILE] [--env HistoJAX-Medium-v0]

Needs the ``bench`` extra (``pip install -e '.[bench]'``: openslide-python, openslide-bin).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run as a script from anywhere

import histojax  # noqa: E402
import histojax.core.modes.base as hx_modes  # noqa: E402  (the pixel observation looks view_pixels up here)
from benchmarks.throughput import full_step_rollout, measure, memcpy_bandwidth  # noqa: E402
from histojax.core.views import view_pixels  # noqa: E402

PIXEL_TARGET = 1_000
FEATURE_TARGET = 10_000
BANDWIDTH_TARGET = 0.5


# --------------------------------------------------------------------------- (a) HistoGym-style env
def histogym_polygons(path) -> list[list[tuple[float, float]]]:
    """Level-0 polygons as HistoGym reads them: every ASAP ``Annotation``'s coordinates in order,
    whatever its group (HistoGym ignores groups); GeoJSON through ``data_tools``."""
    path = Path(path)
    if path.suffix.lower() == ".xml":
        from defusedxml import ElementTree

        root = ElementTree.parse(str(path)).getroot()
        polys = []
        for ann in root.iter("Annotation"):
            coords = sorted(ann.iter("Coordinate"), key=lambda c: float(c.get("Order")))
            pts = [(float(c.get("X")), float(c.get("Y"))) for c in coords]
            if len(pts) >= 3:
                polys.append(pts)
        return polys
    from data_tools.annotations import load_annotations

    ann = load_annotations(path)
    return [list(p.exterior.coords) for p in ann.tumour.geoms]


class HistoGymStyleEnv:
    """A faithful re-implementation of the per-step work of HistoGym's ``HistoEnv`` (see module doc).

    ``agent_pos = [z, col, row]`` in DeepZoom tile units of level ``z``; starts at the first
    DeepZoom level with more than one tile and both sides larger than a tile, at ``(0, 0)``."""

    UP, DOWN, LEFT, RIGHT, ZOOM_IN, ZOOM_OUT, STAY = range(7)

    def __init__(self, slide_path, annotation_path, tile_size: int = 128, overlap: int = 1, max_step: int = 2000):
        import openslide
        from openslide.deepzoom import DeepZoomGenerator

        self.tile_size = tile_size
        self.slide = openslide.OpenSlide(str(slide_path))
        self.dz = DeepZoomGenerator(self.slide, tile_size=tile_size, overlap=overlap, limit_bounds=False)
        self.max_step = max_step
        self.min_z = self._init_position()[0]
        self.max_z = self.dz.level_count - 1
        coords = histogym_polygons(annotation_path)
        w0, h0 = self.dz.level_dimensions[-1]
        self.coords_dz = [
            [[(x * w / w0, y * h / h0) for x, y in poly] for poly in coords] for (w, h) in self.dz.level_dimensions
        ]
        self.agent_pos = self._init_position()
        self.bound = self._all_bounds()
        self.count = 0
        self.log = open(os.devnull, "w")
        self.seconds_read = 0.0  # tile read + resize + numpy conversion
        self.seconds_overlap = 0.0  # the shapely reward
        self.finest_steps = 0

    def _init_position(self):
        t = self.tile_size
        for i, (tiles, size) in enumerate(zip(self.dz.level_tiles, self.dz.level_dimensions)):
            if (tiles[0] > 1 or tiles[1] > 1) and size[0] > t and size[1] > t:
                return [i, 0, 0]
        return [self.dz.level_count - 1, 0, 0]

    def _get_bound(self):
        z = min(max(self.agent_pos[0], self.min_z), self.max_z)
        tx, ty = self.dz.level_tiles[z]
        return self.max_z, tx - 1, ty - 1

    def _all_bounds(self):
        t, bound = self.tile_size, {}
        for z in range(self.min_z, self.max_z + 1):
            mx, my = self.dz.level_tiles[z]
            mx, my = mx - 1, my - 1
            corner = self.dz.get_tile(z, (mx, my))
            if corner.size[0] < t:
                mx = round(mx - (t - corner.size[0]) / t, 2)
            if corner.size[1] < t:
                my = round(my - (t - corner.size[1]) / t, 2)
            bound[z] = (mx, my)
        return bound

    def _get_state(self):
        t0 = time.perf_counter()
        z, x, y = self.agent_pos
        tile = self.dz.get_tile(z, (x, y))
        tile = tile.resize((self.tile_size, self.tile_size))
        state = np.array(tile).transpose(2, 0, 1)
        self.seconds_read += time.perf_counter() - t0
        return state

    def _check_overlap(self, z, x, y):
        from shapely.geometry import Polygon
        from shapely.geometry import box as make_box

        t0 = time.perf_counter()
        # HistoGym rebuilds the polygons of every level on every call (get_segment_all)
        segments = [[Polygon(c).buffer(0) for c in level] for level in self.coords_dz][z]
        minx, miny = x * 256, y * 256  # HistoGym's xy_to_coor_dz default tile size, whatever tile_size is
        tile_box = make_box(minx, miny, minx + self.tile_size, miny + self.tile_size)
        hit = None
        for i, seg in enumerate(segments):
            if seg.intersects(tile_box):
                hit = i  # only the last intersecting polygon is kept
        ratio = segments[hit].intersection(tile_box).area / tile_box.area if hit is not None else 0
        self.seconds_overlap += time.perf_counter() - t0
        return hit is not None, hit, ratio

    def reset(self):
        print("HistoEnv Reset!... Time Step is %s" % self.count, file=self.log)
        self.agent_pos = self._init_position()
        self.state = self._get_state()
        self.bound = self._all_bounds()
        self.count = 0
        return self.state

    def step(self, action):
        pos, t = self.agent_pos, self.tile_size
        self.count += 1
        if action == self.UP:
            pos[2] = 0 if pos[2] < 1 else round(pos[2] - 1, 2)
        if action == self.DOWN:
            b = self._get_bound()[2]
            if pos[2] + 1 >= b or pos[2] + 2 > b:
                pos[2] = b if pos[2] + 1 >= b else pos[2] + 1
                edge = self.dz.get_tile(pos[0], (pos[1], pos[2]))
                if edge.size[1] < t:
                    pos[2] = round(pos[2] - (t - edge.size[1]) / t, 2)
            else:
                pos[2] = round(pos[2] + 1, 2)
        if action == self.LEFT:
            pos[1] = 0 if pos[1] < 1 else round(pos[1] - 1, 2)
        if action == self.RIGHT:
            b = self._get_bound()[1]
            if pos[1] + 1 >= b or pos[1] + 2 > b:
                pos[1] = b if pos[1] + 1 >= b else pos[1] + 1
                edge = self.dz.get_tile(pos[0], (pos[1], pos[2]))
                if edge.size[0] < t:
                    pos[1] = round(pos[1] - (t - edge.size[0]) / t, 2)
            else:
                pos[1] = round(pos[1] + 1, 2)
        if action == self.ZOOM_IN and pos[0] < self._get_bound()[0]:
            new = [pos[0] + 1, pos[1] * 2 + 0.5, pos[2] * 2 + 0.5]
            new[1] = min(new[1], self.bound[new[0]][0])
            new[2] = min(new[2], self.bound[new[0]][1])
            pos = new
        if action == self.ZOOM_OUT and pos[0] > self._init_position()[0]:
            new = [pos[0] - 1, (pos[1] - 0.5) / 2, (pos[2] - 0.5) / 2]
            new[1] = min(max(new[1], 0), self.bound[new[0]][0])
            new[2] = min(max(new[2], 0), self.bound[new[0]][1])
            pos = new
        pos[2] = round(pos[2], 2)
        pos[1] = round(pos[1], 2)
        self.agent_pos = pos
        self.state = self._get_state()
        if pos[0] == self._get_bound()[0]:
            self.finest_steps += 1
            _, _, ratio = self._check_overlap(pos[0], pos[1], pos[2])
        else:
            ratio = 0
        reward = ratio * 1000 - 0.01
        done = self.count >= self.max_step
        info = {"agent position: ": "level %s :(%s,%s)" % (pos[0], pos[1], pos[2])}
        print(info, reward, ratio, file=self.log)
        return self.state, reward, done, info


def histogym_steps_per_s(slide_path, annotation_path, tile_size: int, steps: int, seed: int = 0) -> dict:
    """Steps/s of the HistoGym-style loop (random actions, reset when done) over ``steps`` steps."""
    env = HistoGymStyleEnv(slide_path, annotation_path, tile_size=tile_size)
    rng = np.random.default_rng(seed)
    env.reset()
    for _ in range(20):  # warm the decoder and the tile cache a little
        env.step(int(rng.integers(7)))
    env.seconds_read = env.seconds_overlap = 0.0
    env.finest_steps = 0
    total = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        _, reward, done, _ = env.step(int(rng.integers(7)))
        total += reward
        if done:
            env.reset()
    elapsed = time.perf_counter() - t0
    return {
        "sps": steps / elapsed,
        "seconds": elapsed,
        "read_ms": 1e3 * env.seconds_read / steps,
        "overlap_ms": 1e3 * env.seconds_overlap / max(env.finest_steps, 1),
        "finest": env.finest_steps / steps,
        "levels": (env.min_z, env.max_z),
        "return": total,
    }


# --------------------------------------------------------------------------- (b) histojax envs
def features_env(env, params, make_kwargs: dict, dim: int = 1280):
    """``(env, params, note)`` with ``obs_mode="features"``, or ``(None, None, note)`` if this
    histojax has no feature observations. Uses the bundle's feature grid if it has one, else
    attaches a random float16 grid (``dim``-d, stride = tile size) to the slide in memory."""
    from histojax.core.modes.factory import OBS_MODES

    if "features" not in OBS_MODES:
        return None, None, "this histojax has no obs_mode='features': feature rows skipped"
    from data_tools.errors import HistojaxDataError

    try:
        fenv, fparams = histojax.make(env.name, **make_kwargs, obs_mode="features")
        return fenv, fparams, f"the bundle's feature grid ({fparams.slide.features.shape[1]}-d)"
    except HistojaxDataError:
        pass
    from data_tools.features.store import grid_shape

    slide, t = params.slide, env.tile_size
    widths, heights = np.asarray(slide.level_width), np.asarray(slide.level_height)
    grids = [grid_shape(int(w), int(h), t, t) for w, h in zip(widths, heights)]
    sizes = np.array([gh * gw for gh, gw in grids])
    rows = np.random.default_rng(0).standard_normal((int(sizes.sum()), dim)).astype(np.float16)
    slide = slide.replace(
        features=jnp.asarray(rows),
        feature_offset=jnp.asarray(np.concatenate([[0], np.cumsum(sizes)[:-1]]), jnp.int32),
        feature_grid_width=jnp.asarray([g[1] for g in grids], jnp.int32),
        feature_grid_height=jnp.asarray([g[0] for g in grids], jnp.int32),
        feature_stride=jnp.asarray(t, jnp.int32),
    )
    params = params.replace(slide=slide)
    env = dataclasses.replace(env, obs_mode="features", _default_params=params)
    return (
        env,
        params,
        (
            f"no feature grid in the bundle: a random float16 {dim}-d grid (stride {t} px, "
            f"{int(sizes.sum())} views) attached in memory (the step's cost does not depend on values)"
        ),
    )


QUICK_STEPS = None  # --quick: env-steps per timed call (throughput.measure uses 200,000)


def timed(make_fn, env, params, batch: int, seconds: float) -> float:
    """``throughput.measure``, or with ``--quick`` the same loop with shorter calls."""
    if QUICK_STEPS is None:
        return measure(make_fn, env, params, batch, seconds)
    steps = max(10, QUICK_STEPS // batch)
    return _time(make_fn(env, batch, steps), (params,), seconds, steps * batch)


def step_breakdown(env, params, fenv, fparams, batch: int, seconds: float) -> list[tuple[str, float, float | None]]:
    """Full step at ``batch`` (observations materialised): as is (auto-reset, start drawn by
    inverting the cumulative start weights), with one view per step (``final_observation=False``),
    and without auto-reset."""
    variants = [
        ("as is (auto-reset)", lambda e: e),
        ("final_observation=False", lambda e: dataclasses.replace(e, final_observation=False)),
        ("auto_reset=False", lambda e: dataclasses.replace(e, auto_reset=False)),
    ]
    out = []
    for name, variant in variants:
        pix = timed(full_step_rollout, variant(env), params, batch, seconds)
        feat = timed(full_step_rollout, variant(fenv), fparams, batch, seconds) if fenv else None
        out.append((name, pix, feat))
    return out


# --------------------------------------------------------------------------- (d) crop formulations
# Each layout is (name, prepare(slide) -> slide with ``pixels`` in that layout, crop(slide, z, x, y, T)).
def _rows_flat_bytes(slide, z, x, y, t):
    """Row gather on the flat byte array: T slices of 3T contiguous bytes."""
    rows = (slide.level_offset[z] + (y + jnp.arange(t)) * slide.level_width[z] + x) * 3
    out = jax.vmap(lambda s: lax.dynamic_slice(slide.pixels, (s,), (3 * t,)))(rows)
    return out.reshape(t, t, 3)


def _padded_3d(slide, z, x, y, t):
    """One ``dynamic_slice`` of a level-stacked ``(n, H_max, W_max, 3)`` array (levels zero-padded)."""
    return lax.dynamic_slice(slide.pixels, (z, y, x, 0), (1, t, t, 3))[0]


def _rows_u32(slide, z, x, y, t):
    """Row gather on an RGBX uint32 array (one word per pixel), unpacked to uint8 RGB."""
    rows = slide.level_offset[z] + (y + jnp.arange(t)) * slide.level_width[z] + x
    words = jax.vmap(lambda s: lax.dynamic_slice(slide.pixels, (s,), (t,)))(rows)
    return lax.bitcast_convert_type(words, jnp.uint8)[..., :3]


def _prepare_flat(slide):
    return slide.replace(pixels=slide.pixels.reshape(-1))


def _prepare_padded(slide):
    pix = np.asarray(slide.pixels)
    off, w, h = (np.asarray(a) for a in (slide.level_offset, slide.level_width, slide.level_height))
    stack = np.zeros((len(w), h.max(), w.max(), 3), np.uint8)
    for k in range(len(w)):
        stack[k, : h[k], : w[k]] = pix[off[k] : off[k] + h[k] * w[k]].reshape(h[k], w[k], 3)
    return slide.replace(pixels=jnp.asarray(stack))


def _prepare_u32(slide):
    pix = np.asarray(slide.pixels)
    rgbx = np.zeros((pix.shape[0], 4), np.uint8)
    rgbx[:, :3] = pix
    return slide.replace(pixels=jnp.asarray(rgbx.view(np.uint32)[:, 0]))


CROPS = {
    "rows (current views.py)": (lambda s: s, view_pixels),
    "rows of flat bytes": (_prepare_flat, _rows_flat_bytes),
    "padded 3-D dynamic_slice": (_prepare_padded, _padded_3d),
    "rows of RGBX uint32": (_prepare_u32, _rows_u32),
}


def _random_positions(slide, key, batch, n_levels, t):
    kz, kx, ky = jax.random.split(key, 3)
    z = jax.random.randint(kz, (batch,), 0, n_levels)
    x = (jax.random.uniform(kx, (batch,)) * (slide.level_width[z] - t + 1)).astype(jnp.int32)
    y = (jax.random.uniform(ky, (batch,)) * (slide.level_height[z] - t + 1)).astype(jnp.int32)
    return z, x, y


def crop_rollout(crop, batch: int, steps: int, n_levels: int, t: int):
    """Crop alone: ``steps`` batches of ``batch`` random views; every view is materialised (the
    batch of views is the scan carry) and one pixel of each consumed."""

    def run(key, slide):
        def body(carry, key):
            _, checksum = carry
            z, x, y = _random_positions(slide, key, batch, n_levels, t)
            obs = jax.vmap(crop, in_axes=(None, 0, 0, 0, None))(slide, z, x, y, t)
            return (obs, checksum + obs[:, t // 2, t // 2, 1].astype(jnp.int32).sum()), None

        init = (jnp.zeros((batch, t, t, 3), jnp.uint8), jnp.int32(0))
        return jax.lax.scan(body, init, jax.random.split(key, steps))[0]

    return jax.jit(run)


def positions_rollout(batch: int, steps: int, n_levels: int, t: int):
    """The random positions alone (subtracted from the crop timings)."""

    def run(key, slide):
        def body(total, key):
            z, x, y = _random_positions(slide, key, batch, n_levels, t)
            return total + (z + x + y).sum(), None

        return jax.lax.scan(body, jnp.int32(0), jax.random.split(key, steps))[0]

    return jax.jit(run)


def _time(fn, args, seconds: float, per_call: int) -> float:
    jax.block_until_ready(fn(jax.random.PRNGKey(0), *args))  # compile
    calls, t0 = 0, time.perf_counter()
    while True:
        jax.block_until_ready(fn(jax.random.PRNGKey(calls + 1), *args))
        calls += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return calls * per_call / elapsed


def check_exact(slide, crop, prepared, n_levels: int, t: int, n: int = 512) -> bool:
    """The crop equals ``view_pixels`` on ``n`` random views over all levels (plus the corners)."""
    z, x, y = _random_positions(slide, jax.random.PRNGKey(7), n, n_levels, t)
    zc = jnp.arange(n_levels, dtype=jnp.int32)
    z = jnp.concatenate([z, zc, zc])
    x = jnp.concatenate([x, jnp.zeros_like(zc), slide.level_width[zc] - t])
    y = jnp.concatenate([y, jnp.zeros_like(zc), slide.level_height[zc] - t])
    ref = jax.jit(jax.vmap(view_pixels, in_axes=(None, 0, 0, 0, None)), static_argnums=4)(slide, z, x, y, t)
    got = jax.jit(jax.vmap(crop, in_axes=(None, 0, 0, 0, None)), static_argnums=4)(prepared, z, x, y, t)
    return bool(jnp.array_equal(ref, got))


@contextlib.contextmanager
def patched_view(crop):
    """Temporarily make the env's observation use ``crop`` (module-level name looked up at trace time)."""
    old = hx_modes.view_pixels
    hx_modes.view_pixels = crop
    try:
        yield
    finally:
        hx_modes.view_pixels = old


def crop_alternatives(env, params, batch: int, seconds: float, bandwidth: float, full_step: bool = True) -> list[dict]:
    """Time every formulation in ``CROPS`` alone at ``batch`` and (``full_step``) inside the env's
    full step; each checked for exactness first."""
    t, n = env.tile_size, env.n_levels
    steps = max(10, 50_000 // batch)
    view_bytes = t * t * 3
    base = _time(positions_rollout(batch, steps, n, t), (params.slide,), seconds, steps * batch)
    out = []
    for name, (prepare, crop) in CROPS.items():
        prepared = prepare(params.slide)
        exact = check_exact(params.slide, crop, prepared, n, t)
        vps = _time(crop_rollout(crop, batch, steps, n, t), (prepared,), seconds, steps * batch)
        crop_only = 1.0 / max(1.0 / vps - 1.0 / base, 1e-12)  # minus drawing random positions
        row = {
            "name": name,
            "exact": exact,
            "views_per_s": vps,
            "crop_views_per_s": crop_only,
            "crop_bw": crop_only * view_bytes / bandwidth,
            "device_bytes": prepared.pixels.nbytes,
        }
        if full_step:
            p2 = params.replace(slide=prepared)
            with patched_view(crop):
                row["step_sps"] = timed(full_step_rollout, env, p2, batch, seconds)
        out.append(row)
        del prepared
    return out


# --------------------------------------------------------------------------- main
def slide_and_bundle(args):
    """``(slide path, annotation path, bundle path or None for the embedded sample)``."""
    from histojax.cache import cached_bundle
    from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE

    if args.slide is None:
        return SAMPLE_SLIDE, SAMPLE_ANNOTATIONS, None
    if args.annotations is None:
        raise SystemExit("--slide needs --annotations (the reward needs the tumour polygons)")
    slide, ann = Path(args.slide), Path(args.annotations)
    out = cached_bundle(slide, ann, tile_size=args.tile_size, prefix=f"vs-histogym-{slide.stem}", storage="dense")
    return slide, ann, out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--slide", default=None, help="slide file (default: the embedded CMU-1-Small-Region.svs)")
    p.add_argument("--annotations", default=None, help="its ASAP XML or GeoJSON annotation")
    p.add_argument(
        "--env",
        default="HistoJAX-Medium-v0",
        help="histojax scenario (default Medium: 5 levels, as HistoGym's 5 DeepZoom levels "
        "of the sample slide at 128 px)",
    )
    p.add_argument("--tile-size", type=int, default=128)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 4096])
    p.add_argument("--histogym-steps", type=int, default=2000)
    p.add_argument("--seconds", type=float, default=3.0, help="minimum timed seconds per histojax measurement")
    p.add_argument("--crop-batch", type=int, default=1024)
    p.add_argument("--no-crop-step", action="store_true", help="time the crop alternatives alone only")
    p.add_argument(
        "--quick",
        action="store_true",
        help="short run (< 3 min): 100 HistoGym steps, 0.3 s and 20,000 env-steps per call",
    )
    args = p.parse_args(argv)
    if args.quick:
        global QUICK_STEPS
        QUICK_STEPS = 20_000
        args.histogym_steps, args.seconds = min(args.histogym_steps, 100), min(args.seconds, 0.3)

    slide_path, ann_path, bundle = slide_and_bundle(args)
    bandwidth = memcpy_bandwidth()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
        f"(load average {load[0]:.1f} at start: shared while measuring), Python {platform.python_version()}, "
        f"JAX {jax.__version__} on {jax.devices()[0].platform}"
    )
    print(f"slide: {Path(slide_path).name}, annotation: {Path(ann_path).name}")
    print(f"numpy memory copy: {bandwidth / 1e9:.2f} GB/s")

    # (a)
    import openslide

    hg = histogym_steps_per_s(slide_path, ann_path, args.tile_size, args.histogym_steps)
    print(
        f"\n(a) HistoGym-style loop (OpenSlide {openslide.__library_version__}, openslide-python "
        f"{openslide.__version__}, DeepZoom levels {hg['levels'][0]}..{hg['levels'][1]}, {args.tile_size} px, "
        f"{args.histogym_steps} random steps in {hg['seconds']:.1f} s):"
    )
    print(
        f"    {hg['sps']:,.0f} steps/s; tile read + resize + numpy {hg['read_ms']:.2f} ms/step; "
        f"shapely overlap {hg['overlap_ms']:.2f} ms per finest-level step ({hg['finest']:.0%} of steps)"
    )

    # (b)
    make_kwargs = dict(slide=bundle, reward="histogym", tile_size=args.tile_size)
    env, params = histojax.make(args.env, **make_kwargs)
    fenv, fparams, fnote = features_env(env, params, make_kwargs)
    print(
        f"\n(b) histojax {args.env} ({env.n_levels} levels, {env.tile_size} px views, reward='histogym', "
        f"auto-reset), lax.scan over vmap(step), >= {args.seconds:g} s per measurement"
    )
    print(f"    features: {fnote}")
    view_bytes = env.tile_size**2 * 3
    rows = []
    for batch in args.batches:
        sps = timed(full_step_rollout, env, params, batch, args.seconds)
        fsps = timed(full_step_rollout, fenv, fparams, batch, args.seconds) if fenv else None
        rows.append((batch, sps, fsps))
        print(
            f"    batch {batch:>5}: pixels {sps:>12,.0f} steps/s"
            + (f", features {fsps:>12,.0f} steps/s" if fsps else ""),
            flush=True,
        )

    # (c)
    print(
        f"\n(c) histojax / HistoGym-style (HistoGym-style = {hg['sps']:,.0f} steps/s); "
        f"targets: pixels >= {PIXEL_TARGET:,}x, features >= {FEATURE_TARGET:,}x"
    )
    print(
        f"    {'batch':>6} {'pixels steps/s':>15} {'ratio':>10} {'':>4} {'features steps/s':>17} {'ratio':>10} {'':>4}"
    )
    for batch, sps, fsps in rows:
        r = sps / hg["sps"]
        line = f"    {batch:>6} {sps:>15,.0f} {r:>9,.0f}x {'ok' if r >= PIXEL_TARGET else 'MISS':>4}"
        if fsps:
            fr = fsps / hg["sps"]
            line += f" {fsps:>17,.0f} {fr:>9,.0f}x {'ok' if fr >= FEATURE_TARGET else 'MISS':>4}"
        print(line)

    # (d)
    at = {b: s for b, s, _ in rows}
    if args.crop_batch in at:
        gbs = at[args.crop_batch] * view_bytes
        print(
            f"\n(d) full step at batch {args.crop_batch}: view bytes {gbs / 1e9:.2f} GB/s = "
            f"{gbs / bandwidth:.0%} of memcpy {bandwidth / 1e9:.2f} GB/s (target >= {BANDWIDTH_TARGET:.0%})"
        )
    else:
        print(f"\n(d) (batch {args.crop_batch} not among --batches: full-step bandwidth not measured)")
    alts = crop_alternatives(env, params, args.crop_batch, args.seconds, bandwidth, full_step=not args.no_crop_step)
    print(
        f"    crop formulations at batch {args.crop_batch} (crop alone: random views, each materialised, "
        f"time of drawing positions subtracted):"
    )
    print(
        f"    {'formulation':<26} {'exact':>5} {'crop views/s':>13} {'crop GB/s':>10} {'of memcpy':>9} "
        f"{'full step/s':>12} {'layout MB':>9}"
    )
    for a in alts:
        step = f"{a['step_sps']:>12,.0f}" if "step_sps" in a else f"{'-':>12}"
        print(
            f"    {a['name']:<26} {str(a['exact']):>5} {a['crop_views_per_s']:>13,.0f} "
            f"{a['crop_views_per_s'] * view_bytes / 1e9:>10.2f} {a['crop_bw']:>9.0%} {step} "
            f"{a['device_bytes'] / 2**20:>9.1f}"
        )
    print(f"\n(e) where the step's time goes at batch {args.crop_batch} (observations materialised as the scan carry):")
    for name, pix, feat in step_breakdown(env, params, fenv, fparams, args.crop_batch, args.seconds):
        print(
            f"    {name:<40} pixels {pix:>12,.0f} steps/s ({pix / hg['sps']:>8,.0f}x)"
            + (f", features {feat:>12,.0f} steps/s ({feat / hg['sps']:>9,.0f}x)" if feat else ""),
            flush=True,
        )
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"\nload average at the end: {load[0]:.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
