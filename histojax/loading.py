"""Loading slides onto the device: a bundle on disk read through one verified read
(:func:`data_tools.bundle_files.reading.read_slide`) and packed into :class:`~histojax.core.slide.SlideArrays`
(dense or tiled, with or without pixels and feature grid), the device-memory budget of a slide, and the stacking
of loaded slides into one dataset (:func:`stack_slides`). Host work done once by ``make``; the env core
(:mod:`histojax.core`) reads no file and imports nothing from here.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from data_tools.bundle_files.format import BundleMetadata, slide_device_bytes
from data_tools.bundle_files.reading import Bundle, SlideRead, read_metadata, read_slide
from data_tools.errors import BundleError
from histojax.core.slide import SlideArrays, start_logits

DEFAULT_MAX_DEVICE_BYTES = 4 * 2**30  # the memory budget of one slide on the device
HOST_PEAK_FACTOR = 1.6  # make's peak RSS rise / device bytes on the CPU backend (benchmarks/host_memory.py)


def _log_weights(weights: np.ndarray) -> np.ndarray:
    """Normalised log-weights; a weight of 0 (a slide never drawn) is ``-inf``, without a warning."""
    with np.errstate(divide="ignore"):
        return np.log(weights / weights.sum())


def release_heap() -> None:
    """Hand the C heap's free memory back to the system (glibc ``malloc_trim``; nothing elsewhere). Buffers of a
    few MB freed after glibc raised its mmap threshold stay in the heap, resident, until trimmed: without
    it a dataset's per-slide device arrays (host memory on the CPU backend) stayed in RSS after stacking."""
    import ctypes
    import ctypes.util

    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError, TypeError):
        pass


def stack_slides(slides: list[SlideArrays], weights=None, consume: bool = False) -> SlideArrays:
    """One ``SlideArrays`` for a dataset of slides of any sizes (same number of levels): flat arrays
    concatenated with offsets shifted, per-level arrays stacked on a new leading axis, start
    logits padded with ``-inf`` to the largest coarsest level. ``weights`` (default uniform) are
    the relative probabilities of drawing each slide at reset. ``consume=True``: the slides' arrays are
    deleted once stacked (using them afterwards raises) and their memory handed back (:func:`release_heap`),
    so the host does not hold the dataset twice while the caller still holds the list."""
    n_levels = {int(s.level_width.shape[0]) for s in slides}
    if len(n_levels) != 1:
        raise ValueError(f"slides of a dataset need the same number of levels, got {sorted(n_levels)}")
    with_features = [s.features is not None for s in slides]
    if any(with_features) and not all(with_features):
        raise ValueError("either every slide of a dataset has a feature grid or none has")
    if all(with_features) and len({int(s.features.shape[1]) for s in slides}) != 1:
        raise ValueError("feature grids of a dataset's slides must have the same dimension")
    tiled = [s.is_tiled for s in slides]
    if len({s.has_pixels for s in slides}) != 1:
        raise ValueError("either every slide of a dataset has its pixels on the device or none has")
    pix = slides[0].has_pixels
    if any(tiled) and not all(tiled):
        raise ValueError(
            "a dataset cannot mix dense and tiled slides: rebuild them all with the same --storage (dense or tiled)"
        )
    if all(tiled):
        pixel_base = sat_base = np.zeros(len(slides), np.int64)  # level_offset / sat_offset unused
        tile_base = np.cumsum([0] + [int(s.tile_pool.shape[0]) if pix else 0 for s in slides[:-1]])
        satp_base = np.cumsum([0] + [int(s.sat_pool.shape[0]) for s in slides[:-1]])
        index_base = np.cumsum([0] + [int(s.sat_index.shape[0]) for s in slides[:-1]])
        t = int(slides[0].sat_pool.shape[1]) - 1
        n_tiles = tile_base[-1] + (slides[-1].tile_pool.shape[0] if pix else 0)
        n_sats = satp_base[-1] + slides[-1].sat_pool.shape[0]
        if any(int(s.sat_pool.shape[1]) != t + 1 for s in slides):
            raise ValueError("tiled slides of a dataset need the same tile size")
        if (
            n_tiles * t * t >= 2**31
            or n_sats * (t + 1) ** 2 >= 2**31
            or index_base[-1] + slides[-1].sat_index.shape[0] >= 2**31
        ):
            raise ValueError("the dataset holds too many tiles for int32 indexing; use fewer slides or levels")
    else:
        pixel_base = np.cumsum([0] + [int(s.pixels.shape[0]) if pix else 0 for s in slides[:-1]])
        sat_base = np.cumsum([0] + [int(s.tumour_sat.shape[0]) for s in slides[:-1]])
        if (
            pixel_base[-1] + (slides[-1].pixels.shape[0] if pix else 0) >= 2**31
            or sat_base[-1] + slides[-1].tumour_sat.shape[0] >= 2**31
        ):
            raise ValueError("the dataset holds too many pixels for int32 indexing; use fewer slides or levels")
    h = max(int(s.start_logits.shape[0]) for s in slides)
    w = max(int(s.start_logits.shape[1]) for s in slides)
    logits = np.full((len(slides), h, w), -np.inf, np.float32)
    for i, s in enumerate(slides):
        logits[i, : s.start_logits.shape[0], : s.start_logits.shape[1]] = np.asarray(s.start_logits)
    weights = np.ones(len(slides)) if weights is None else np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(slides),) or np.any(weights < 0) or weights.sum() <= 0:
        raise ValueError(f"slide weights must be {len(slides)} non-negative numbers, not all zero")
    stacked = dict(
        pixels=None if all(tiled) or not pix else jnp.concatenate([s.pixels for s in slides]),
        level_offset=jnp.stack([s.level_offset + int(b) for s, b in zip(slides, pixel_base)]),
        level_width=jnp.stack([s.level_width for s in slides]),
        level_height=jnp.stack([s.level_height for s in slides]),
        downsample=jnp.stack([s.downsample for s in slides]),
        tumour_sat=None if all(tiled) else jnp.concatenate([s.tumour_sat for s in slides]),
        sat_offset=jnp.stack([s.sat_offset + int(b) for s, b in zip(slides, sat_base)]),
        start_logits=jnp.asarray(logits),
        slide_logits=jnp.asarray(_log_weights(weights), dtype=jnp.float32),
    )
    if all(tiled):
        stacked.update(
            tile_pool=jnp.concatenate([s.tile_pool for s in slides]) if pix else None,
            tile_index=jnp.concatenate([s.tile_index + int(b) for s, b in zip(slides, tile_base)]) if pix else None,
            tile_offset=jnp.stack([s.tile_offset + int(b) for s, b in zip(slides, index_base)]),
            tile_grid_width=jnp.stack([s.tile_grid_width for s in slides]),
            sat_pool=jnp.concatenate([s.sat_pool for s in slides]),
            sat_index=jnp.concatenate([s.sat_index + int(b) for s, b in zip(slides, satp_base)]),
        )
    if all(s.slide_label is not None for s in slides):
        stacked["slide_label"] = jnp.stack([jnp.asarray(s.slide_label, jnp.int32) for s in slides])
    if all(with_features):
        feature_base = np.cumsum([0] + [int(s.features.shape[0]) for s in slides[:-1]])
        dtype = jnp.result_type(*[s.features.dtype for s in slides])
        stacked.update(
            features=jnp.concatenate([s.features.astype(dtype) for s in slides]),
            feature_offset=jnp.stack([s.feature_offset + int(b) for s, b in zip(slides, feature_base)]),
            feature_grid_width=jnp.stack([s.feature_grid_width for s in slides]),
            feature_grid_height=jnp.stack([s.feature_grid_height for s in slides]),
            feature_stride=jnp.stack([jnp.asarray(s.feature_stride, jnp.int32) for s in slides]),
        )
    out = SlideArrays(**jax.block_until_ready(stacked))
    if consume:
        kept = {id(leaf) for leaf in jax.tree.leaves(out)}  # a one-slide concatenate may return its input
        for s in slides:
            for leaf in jax.tree.leaves(s):
                if isinstance(leaf, jax.Array) and id(leaf) not in kept and not leaf.is_deleted():
                    leaf.delete()
        release_heap()
    return out


def tiled_slide_arrays(bundle: Bundle, tile_size: int, pixels: bool = True) -> SlideArrays:
    """Pack the tiled levels of a loaded bundle (levels chosen, coarsest first) into a tiled ``SlideArrays``:
    pools concatenated with each level's indices shifted by its pool base. ``pixels=False``: the
    feature-only layout (no RGB pool or tile index; the pool files are never read)."""
    n = len(bundle.pixels)
    tile_base = np.cumsum([0] + [int(p.pool.shape[0]) for p in bundle.pixels[:-1]])
    sat_base = np.cumsum([0] + [int(m.pool.shape[0]) for m in bundle.tumour[:-1]])
    grid_sizes = np.array([p.index.size for p in bundle.pixels], dtype=np.int64)
    n_tiles = sum(int(p.pool.shape[0]) for p in bundle.pixels) if pixels else 0
    n_sats = sum(int(m.pool.shape[0]) for m in bundle.tumour)
    if (n_tiles + 1) * tile_size**2 >= 2**31 or n_sats * (tile_size + 1) ** 2 >= 2**31 or grid_sizes.sum() >= 2**31:
        raise BundleError(
            bundle.path,
            f"{n_tiles:,} tiles are too many for int32 indexing of the pool px in one "
            "slide (at most 2**31 px, 6 GiB of RGB); use fewer or coarser levels",
        )
    t = tile_size
    tile_pool = np.empty((n_tiles + 1, t, t, 3), np.uint8) if pixels else None
    sat_pool = np.empty((n_sats, t + 1, t + 1), np.uint32)
    for p, m, b, c in zip(bundle.pixels, bundle.tumour, tile_base, sat_base):
        if pixels:
            tile_pool[b : b + p.pool.shape[0]] = p.pool
        sat_pool[c : c + m.pool.shape[0]] = m.pool
    if pixels:
        tile_pool[-1] = 255  # the spare tile the view's row slices may run into
    if pixels and n_tiles and np.ptp(tile_pool[0].reshape(-1, 3), axis=0).any():
        raise BundleError(bundle.path, "tile 0 of a tiled bundle must be the blank tile; rebuild the bundle")
    widths = np.array([p.width for p in bundle.pixels], dtype=np.int32)
    heights = np.array([p.height for p in bundle.pixels], dtype=np.int32)
    downsample = BundleMetadata(bundle.metadata).downsamples
    zeros = jnp.zeros((n,), jnp.int32)
    arrays = SlideArrays(
        pixels=None,
        tumour_sat=None,
        level_offset=zeros,
        sat_offset=zeros,
        level_width=jnp.asarray(widths),
        level_height=jnp.asarray(heights),
        downsample=jnp.asarray(downsample, dtype=jnp.float32),
        start_logits=jnp.asarray(start_logits(bundle.tissue, tile_size, getattr(bundle, "region", None))),
        slide_label=jnp.asarray(slide_label_from_metadata(bundle.metadata), dtype=jnp.int32),
        tile_pool=jnp.asarray(tile_pool) if pixels else None,
        tile_index=jnp.asarray(
            np.concatenate([p.index.ravel() + int(b) for p, b in zip(bundle.pixels, tile_base)]).astype(np.int32)
        )
        if pixels
        else None,
        tile_offset=jnp.asarray(np.concatenate([[0], np.cumsum(grid_sizes)[:-1]]), dtype=jnp.int32),
        tile_grid_width=jnp.asarray([p.index.shape[1] for p in bundle.pixels], dtype=jnp.int32),
        sat_pool=jnp.asarray(sat_pool),
        sat_index=jnp.asarray(
            np.concatenate([m.index.ravel() + int(c) for m, c in zip(bundle.tumour, sat_base)]).astype(np.int32)
        ),
    )
    # the memory-mapped pools and indices were copied: drop the file pages they read from this process's
    # resident memory (they stay readable); for a dataset they added about 0.8x the device bytes to RSS
    for level in (*bundle.pixels, *bundle.tumour):
        _release_pages(level.pool)
        _release_pages(level.index)
    return arrays


def _release_pages(array) -> None:
    """Drop the pages a memory-mapped array (``np.load(..., mmap_mode="r")``) has read from this process's
    resident memory (they stay readable from the file); other arrays are left alone."""
    import mmap

    m = getattr(array, "_mmap", None)
    if m is not None and hasattr(m, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        m.madvise(mmap.MADV_DONTNEED)


def slide_arrays_from_bundle(bundle: Bundle, tile_size: int, pixels: bool = True) -> SlideArrays:
    """Pack host arrays of a loaded bundle (levels already chosen, coarsest first) into ``SlideArrays``
    (dense, or tiled for a tiled bundle); ``pixels=False`` leaves the pixels off (feature-only layout)."""
    if BundleMetadata(bundle.metadata).is_tiled:
        return tiled_slide_arrays(bundle, tile_size, pixels)
    widths = np.array([p.shape[1] for p in bundle.pixels], dtype=np.int64)
    heights = np.array([p.shape[0] for p in bundle.pixels], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(widths * heights)[:-1]])
    sat_sizes = (widths + 1) * (heights + 1)
    sat_offsets = np.concatenate([[0], np.cumsum(sat_sizes)[:-1]])
    if widths @ heights >= 2**31 or sat_sizes.sum() >= 2**31:
        raise BundleError(bundle.path, "too many pixels for int32 indexing in one slide; use fewer or coarser levels")
    downsample = BundleMetadata(bundle.metadata).downsamples
    # one host buffer per flat array, filled level by level from the (memory-mapped) bundle arrays, put on
    # the device and freed before the next: the host peak is one flat array, not several copies of it
    pixel_array = None
    if pixels:
        flat = np.empty((int(widths @ heights), 3), np.uint8)
        for p, o in zip(bundle.pixels, offsets):
            flat[o : o + p.shape[0] * p.shape[1]] = np.asarray(p).reshape(-1, 3)
            _release_pages(p)
        pixel_array = jax.device_put(flat, may_alias=False).block_until_ready()  # a copy: the host buffer can go
        del flat
    sat = np.empty(int(sat_sizes.sum()), np.uint32)
    for t, o, w, h in zip(bundle.tumour, sat_offsets, widths, heights):
        s = sat[o : o + (h + 1) * (w + 1)].reshape(h + 1, w + 1)
        s[0], s[:, 0] = 0, 0
        for a in range(0, h, 256):  # row blocks: temporaries of 256 rows, not of the whole level
            block = s[1 + a : 1 + min(h, a + 256), 1:]
            np.cumsum(np.asarray(t[a : a + 256]), axis=1, dtype=np.uint32, out=block)  # wraps mod 2**32, as documented
            np.cumsum(block, axis=0, dtype=np.uint32, out=block)
            block += s[a, 1:]
        _release_pages(t)
    tumour_sat = jax.device_put(sat, may_alias=False).block_until_ready()
    del sat
    return SlideArrays(
        pixels=pixel_array,
        level_offset=jnp.asarray(offsets, dtype=jnp.int32),
        level_width=jnp.asarray(widths, dtype=jnp.int32),
        level_height=jnp.asarray(heights, dtype=jnp.int32),
        downsample=jnp.asarray(downsample, dtype=jnp.float32),
        tumour_sat=tumour_sat,
        sat_offset=jnp.asarray(sat_offsets, dtype=jnp.int32),
        start_logits=jnp.asarray(start_logits(bundle.tissue, tile_size, getattr(bundle, "region", None))),
        slide_label=jnp.asarray(slide_label_from_metadata(bundle.metadata), dtype=jnp.int32),
    )


def slide_label_from_metadata(metadata: dict) -> int:
    """Slide-level label from a bundle's annotations: 1 (tumour) when any tumour was annotated,
    else 0. Override with ``make(..., labels=...)`` (a CSV of slide, label) where that is wrong."""
    return BundleMetadata(metadata).slide_label


def load_slide(
    path,
    n_levels: int,
    verify: bool = True,
    max_device_bytes: int = DEFAULT_MAX_DEVICE_BYTES,
    features=None,
    pixels: bool = True,
) -> tuple[SlideArrays, Bundle]:
    """Load the ``n_levels`` zoom levels of the bundle at ``path`` onto the device.

    ``features``: ``None`` loads the bundle's feature grid if it has one (``python -m data_tools
    features``), ``True`` requires it (``BundleError`` naming the command to run otherwise),
    ``False`` skips it. ``pixels=False``: the feature-only layout (no pixels on the device; needs the
    feature grid).

    Refuses, before reading any array, a slide whose levels need more than
    ``max_device_bytes`` (pixels and summed-area tables, see ``device_bytes``; for a tiled bundle the
    pools and index grids recorded in its metadata), and checks the bytes really allocated afterwards.
    It bounds the device arrays only, not the process's host memory: packing goes through host copies
    one flat array at a time, so on the CPU backend (where the device arrays are host memory too) the
    peak RSS rise of ``make`` is about :data:`HOST_PEAK_FACTOR` × the device bytes (measured with
    ``benchmarks/host_memory.py``; see docs/bad-input.md).

    Returns the ``SlideArrays`` (levels coarsest first) and the host ``Bundle``
    (metadata and thumbnails for rendering, levels also coarsest first).
    """
    path = Path(path)

    def refuse_over_budget(metadata, chosen: list[int], load_features: bool) -> None:
        needed = slide_device_bytes(metadata, chosen, pixels, load_features, path)
        if needed > max_device_bytes:
            finest = metadata.levels[chosen[-1]]
            what = "pixels, tumour tables" if pixels else "tumour tables"
            raise BundleError(
                path,
                f"{n_levels} levels need {needed:,} bytes on the device ({what}"
                f"{' and feature grid' if load_features else ''}; finest level "
                f"{finest.width}×{finest.height} px), more than what is left of max_device_bytes="
                f"{max_device_bytes:,}: "
                + (
                    "use obs_mode='features' (no pixels on the device), "
                    if pixels
                    else "recompute the feature grid with a smaller --dim or larger --stride, "
                )
                + "use fewer slides (split=, slides=) or levels, build from a coarser finest level, or "
                "raise max_device_bytes (it bounds the arrays put on the device, not host memory: on the "
                f"CPU backend make's peak RSS rise is about {HOST_PEAK_FACTOR}x these bytes)",
            )

    def pack(read: SlideRead) -> tuple[SlideArrays, Bundle]:
        arrays = slide_arrays_from_bundle(read.bundle, read.metadata.tile_size, pixels)
        if read.load_features:
            arrays = with_features(arrays, path, *read.feature_levels())
        allocated = sum(int(a.nbytes) for a in jax.tree.leaves(arrays))
        if allocated > max_device_bytes:  # what was really put on the device (start weights, labels, ... included)
            raise BundleError(
                path,
                f"{n_levels} levels took {allocated:,} bytes on the device, more than "
                f"max_device_bytes={max_device_bytes:,} (a bound on the device arrays, not on host memory): "
                "use fewer levels or raise max_device_bytes",
            )
        return arrays, read.bundle

    return read_slide(
        path, n_levels, verify=verify, pixels=pixels, features=features, check=refuse_over_budget, use=pack
    )


def check_alike(paths, features: bool | None = None) -> None:
    """Refuse, before any array is read, bundles that cannot make one dataset, naming two of them: different
    tile sizes; feature grids of different dimensions (unless ``features`` is False: not loaded); when
    ``features`` is True (observed), grids of different encoders (recorded in each bundle's metadata) or a
    bundle without one. ``BundleError`` naming the bundle that differs and the first."""
    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        return
    metas = [read_metadata(p) for p in paths]
    first, m0 = paths[0], metas[0]
    for path, m in zip(paths[1:], metas[1:]):
        if int(m["tile_size"]) != int(m0["tile_size"]):
            raise BundleError(
                path,
                f"built with tile size {int(m['tile_size'])} px, but {first} with "
                f"{int(m0['tile_size'])} px: a dataset's bundles need one tile size; rebuild them alike "
                "(--tile-size)",
            )
    if features is False:
        return
    grids = [(p, m.features) for p, m in zip(paths, metas)]
    with_grid = [(p, f) for p, f in grids if f]
    if features and len(with_grid) != len(grids):
        lacking = next(p for p, f in grids if not f)
        raise BundleError(
            lacking,
            f"has no feature grid, but {with_grid[0][0] if with_grid else 'none'} has one: "
            "every slide of a dataset observed through features needs one (`histojax features "
            f"{lacking}`)",
        )
    if not with_grid:
        return
    (p0, f0) = with_grid[0]

    def encoder_of(f):  # imported grids record their file ("imported:NAME.h5"): one dataset's files are one encoder
        name = str(f.get("encoder"))
        return "imported" if f.get("source") == "imported" or name.startswith("imported:") else name

    describe = lambda f: f"encoder {f.get('encoder')!r}, {f.get('dim')}-d"  # noqa: E731
    for path, f in with_grid[1:]:  # grids not observed (features None) load too: their dimensions must agree
        if f.get("dim") != f0.get("dim") or (features and encoder_of(f) != encoder_of(f0)):
            raise BundleError(
                path,
                f"its feature grid ({describe(f)}) is not of the same encoder as {p0}'s "
                f"({describe(f0)}): one env observes one encoder's features; recompute one of them "
                f"with the other's encoder (`histojax features BUNDLE --encoder NAME`)",
            )


def with_features(arrays: SlideArrays, path, grids: list[np.ndarray], stride: int) -> SlideArrays:
    """``arrays`` with the feature grids ``grids`` (one ``(gh, gw, D)`` array per level, coarsest first, as
    :meth:`~data_tools.bundle_files.reading.SlideRead.feature_levels` returns them; ``stride`` px of a level
    between grid positions) packed in: ``features`` ``(F, D)`` (dtype as stored) plus per-level offsets and grid
    sizes. ``path`` names the bundle in a refusal."""
    sizes = np.array([g.shape[0] * g.shape[1] for g in grids], dtype=np.int64)
    if sizes.sum() >= 2**31:
        raise BundleError(path, "feature grid too large for int32 indexing; use a larger --stride")
    flat = np.concatenate([g.reshape(-1, g.shape[2]) for g in grids])
    return arrays.replace(
        features=jnp.asarray(flat),
        feature_offset=jnp.asarray(np.concatenate([[0], np.cumsum(sizes)[:-1]]), dtype=jnp.int32),
        feature_grid_width=jnp.asarray([g.shape[1] for g in grids], dtype=jnp.int32),
        feature_grid_height=jnp.asarray([g.shape[0] for g in grids], dtype=jnp.int32),
        feature_stride=jnp.asarray(stride, dtype=jnp.int32),
    )
