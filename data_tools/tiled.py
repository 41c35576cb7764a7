"""Tiled (sparse) bundle levels for gigapixel slides: tile pools with an index grid.

A *tiled* bundle (``build_bundle(..., storage="tiled")``, format version 2) stores each env level
of ``W × H`` px (``T = tile_size``; the grid is ``gh × gw = ceil(H / T) × ceil(W / T)``) as:

  * ``tiles_KK.npy``      — ``(N, T, T, 3)`` uint8 pool of RGB tiles; tile 0 is blank white (255),
    shared by every *background* tile (no tissue and no tumour);
  * ``tile_index_KK.npy`` — ``(gh, gw)`` int32, the pool tile of each grid cell;
  * ``sat_tiles_KK.npy``  — ``(M, T+1, T+1)`` uint32 pool of *local* summed-area tables of the
    tumour mask of one tile; tile 0 is all zeros (no tumour), tile 1 the SAT of a tile that is all
    tumour (``S[i, j] = i * j``), shared by every such cell;
  * ``sat_index_KK.npy``  — ``(gh, gw)`` int32, the SAT pool tile of each grid cell.

Pixels right of / below the level (the last partial column / row of tiles) are white and never
seen (views are clamped inside the level). A tile is background when no tumour pixel falls in it,
the coarsest level's Otsu tissue mask (dilated by one px) has no tissue over its footprint, and
fewer than ``SATURATED_FRACTION`` of its pixels (sampled every 4th px) are more saturated than the
Otsu threshold; ``share_background=False`` keeps every tile (an exact copy of the dense level).

The build streams: each level is made in bands of tile rows read with ``SlideReader.read_region``
from the best source pyramid level and resampled with PIL (:func:`data_tools.raster.resample`), the tumour is
rasterised per band (pixel-centre rule, tiles wholly inside or outside the polygons decided
geometrically, only boundary tiles tested pixel by pixel), and the pools are appended to ``.npy``
files whose header is rewritten with the final count, so memory stays bounded by the band size.
"""

from __future__ import annotations

import math
import struct as _struct
from pathlib import Path

import numpy as np

from data_tools.bundle_files.format import REGION, TISSUE, tiled_level_files  # noqa: F401  (TiledLevel: the reader side)
from data_tools.bundle_files.reading import TiledLevel

BAND_BYTES = 96 * 2**20  # RGB bytes of one band of a level (plus the source window and copies)
MAX_WINDOW_BYTES = 64 * 2**20  # source RGB bytes read at once for a band (a band is read in strips below it)
SATURATED_FRACTION = 0.005  # a tile with more saturated px than this (sampled) counts as tissue
HEADER_BYTES = 128  # fixed .npy header size of the appended pools (rewritten at the end)
AUTO_TILED_BYTES = 256 * 2**20  # storage="auto": tiled when the dense levels would need more device bytes


# ---------------------------------------------------------------------------- .npy appending


def _npy_header(shape, dtype) -> bytes:
    """A version-1.0 .npy header of exactly ``HEADER_BYTES`` bytes (padded with spaces)."""
    text = "{'descr': %r, 'fortran_order': False, 'shape': %r, }" % (np.dtype(dtype).str, tuple(shape))
    body_len = HEADER_BYTES - 10
    if len(text) + 1 > body_len:
        raise ValueError(f"npy header too long for shape {shape}")
    return b"\x93NUMPY\x01\x00" + _struct.pack("<H", body_len) + (text.ljust(body_len - 1) + "\n").encode("latin1")


class PoolWriter:
    """Append fixed-shape items (one tile each) to a ``.npy`` file; :meth:`close` writes the count."""

    def __init__(self, path: Path, item_shape, dtype):
        self.path, self.item_shape, self.dtype = Path(path), tuple(item_shape), np.dtype(dtype)
        self.count = 0
        self._f = open(self.path, "wb")
        self._f.write(_npy_header((0, *self.item_shape), self.dtype))

    def append(self, items: np.ndarray) -> int:
        """Append ``items`` ``(k, *item_shape)``; returns the pool index of the first one."""
        items = np.ascontiguousarray(items, dtype=self.dtype)
        assert items.shape[1:] == self.item_shape, (items.shape, self.item_shape)
        first = self.count
        self._f.write(items.tobytes())
        self.count += items.shape[0]
        return first

    def close(self) -> None:
        self._f.seek(0)
        self._f.write(_npy_header((self.count, *self.item_shape), self.dtype))
        self._f.close()


def full_sat_tile(tile_size: int) -> np.ndarray:
    """Local SAT ``(T+1, T+1)`` uint32 of a tile that is all tumour: ``S[i, j] = i * j``."""
    i = np.arange(tile_size + 1, dtype=np.uint32)
    return i[:, None] * i[None, :]


def local_sats(masks: np.ndarray) -> np.ndarray:
    """Local SATs ``(k, T+1, T+1)`` uint32 of ``k`` tile masks ``(k, T, T)``."""
    k, t = masks.shape[0], masks.shape[1]
    out = np.zeros((k, t + 1, t + 1), dtype=np.uint32)
    np.cumsum(np.cumsum(masks, axis=1, dtype=np.uint32), axis=2, dtype=np.uint32, out=out[:, 1:, 1:])
    return out


# ---------------------------------------------------------------------------- geometry per band


def tumour_band(
    geometry, width: int, height: int, r0: int, r1: int, downsample: float, tile_size: int, n_cols: int
) -> tuple[np.ndarray, np.ndarray]:
    """Tumour mask ``(r1 - r0, n_cols * T)`` of level rows ``r0..r1`` (a band of whole tile rows; px
    outside the ``width × height`` content are 0) and the per-tile state ``(rows of tiles, n_cols)``
    int8: 0 no tumour, 1 every px tumour, 2 mixed.

    Same pixel-centre rule and float coordinates as :func:`data_tools.masks.rasterize` (centre of
    px ``(i, j)`` at level-0 ``((j + .5) d, (i + .5) d)``), so it equals that function's rows;
    tiles wholly inside (``contains_properly``) or outside a polygon skip the per-px test."""
    import shapely

    t = tile_size
    n_rows = (r1 - r0 + t - 1) // t
    mask = np.zeros((n_rows * t, n_cols * t), dtype=bool)
    rows_valid = np.clip(
        np.minimum(r0 + (np.arange(n_rows) + 1) * t, min(r1, height)) - (r0 + np.arange(n_rows) * t), 0, t
    )
    cols_valid = np.clip(np.minimum((np.arange(n_cols) + 1) * t, width) - np.arange(n_cols) * t, 0, t)
    state = np.zeros((n_rows, n_cols), dtype=np.int8)
    if geometry is None or geometry.is_empty:
        return mask[: r1 - r0], state
    ty, tx = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    valid = (rows_valid[ty] > 0) & (cols_valid[tx] > 0)
    # the hull of each tile's (content) pixel centres, in level-0 px
    x0 = (tx * t + 0.5) * downsample
    x1 = (tx * t + np.maximum(cols_valid[tx], 1) - 0.5) * downsample
    y0 = (r0 + ty * t + 0.5) * downsample
    y1 = (r0 + ty * t + np.maximum(rows_valid[ty], 1) - 0.5) * downsample
    degenerate = (x1 <= x0) | (y1 <= y0)
    for poly in shapely.get_parts(geometry):
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        minx, miny, maxx, maxy = poly.bounds
        near = valid & (x1 >= minx) & (x0 <= maxx) & (y1 >= miny) & (y0 <= maxy)
        if not near.any():
            continue
        shapely.prepare(poly)
        where = np.argwhere(near)
        deg = degenerate[near]
        boxes = shapely.box(x0[near], y0[near], x1[near], y1[near])
        inside = shapely.contains_properly(poly, boxes) & ~deg
        touch = ~inside & (deg | shapely.intersects(poly, boxes))
        for (a, b), full, mixed in zip(where, inside, touch):
            rows = slice(a * t, a * t + int(rows_valid[a]))
            cols = slice(b * t, b * t + int(cols_valid[b]))
            if full:
                mask[rows, cols] = True
            elif mixed:
                xs = (np.arange(cols.start, cols.stop) + 0.5) * downsample
                ys = (np.arange(r0 + rows.start, r0 + rows.stop) + 0.5) * downsample
                mask[rows, cols] |= shapely.contains_xy(poly, xs[None, :], ys[:, None])
    counts = mask.reshape(n_rows, t, n_cols, t).sum(axis=(1, 3))
    area = rows_valid[:, None] * cols_valid[None, :]
    state[:] = np.where(counts == 0, 0, np.where((counts == area) & (area == t * t), 1, 2))
    return mask[: r1 - r0], state


def saturation_threshold(tissue_reference: np.ndarray) -> float:
    """The tissue threshold of :func:`data_tools.masks.tissue_mask` on a (coarse) RGB image."""
    from skimage.color import rgb2hsv
    from skimage.filters import threshold_otsu

    s = rgb2hsv(tissue_reference[..., :3])[..., 1]
    if float(s.max() - s.min()) < 1e-6:
        return 1.0
    return max(float(threshold_otsu(s)), 0.05)


def sampled_saturation(tiles: np.ndarray) -> np.ndarray:
    """HSV saturation ``(max - min) / max`` of every 4th px (rows and columns) of tiles ``(k, T, T, 3)``:
    ``(k, ceil(T/4), ceil(T/4))`` float32, for the caller to threshold."""
    s = tiles[:, ::4, ::4].astype(np.float32)
    hi, lo = s.max(axis=-1), s.min(axis=-1)
    return np.where(hi > 0, (hi - lo) / np.maximum(hi, 1), 0.0)


# ---------------------------------------------------------------------------- streaming build


def tiled_level_bytes(n_tiles: int, n_sat_tiles: int, grid: tuple[int, int], tile_size: int) -> int:
    """Device bytes of one tiled level: the RGB pool, the SAT pool and the two int32 index grids."""
    t = tile_size
    return n_tiles * t * t * 3 + n_sat_tiles * (t + 1) ** 2 * 4 + 2 * 4 * grid[0] * grid[1]


def _source_level(reader, d: float) -> int:
    """The coarsest source level that is still at least as fine as downsample ``d``."""
    return max(
        (i for i, lv in enumerate(reader.levels) if lv.downsample <= d * (1 + 1e-6)),
        key=lambda i: reader.levels[i].downsample,
    )


def _bands(reader, d: float, size, tile_size: int, reg, band_bytes: int):
    """Yield ``(r0, r1, rgb)`` for bands of whole tile rows of a level at downsample ``d`` with content
    ``size = (cw, ch)``: ``rgb`` is ``(r1 - r0, gw * T, 3)`` uint8, white outside the content."""
    from data_tools.raster import resample as _resample

    t = tile_size
    cw, ch = size
    width, height = max(cw, t), max(ch, t)
    gw, gh = -(-width // t), -(-height // t)
    src = _source_level(reader, d)
    ds = reader.levels[src].downsample
    scale = d / ds
    rx0 = 0.0 if reg is None else reg.box[0] / ds
    ry0 = 0.0 if reg is None else reg.box[1] / ds
    per_band = max(1, band_bytes // (gw * t * t * 3))
    # level rows per source window: a coarse level made from a much finer source (a single-level TIFF) is
    # read in strips of at most MAX_WINDOW_BYTES of source RGB, never as one window over the whole source
    step = max(1, int(MAX_WINDOW_BYTES // ((cw * scale + 2) * max(scale, 1.0) * 3)))
    for b0 in range(0, gh, per_band):
        r0, r1 = b0 * t, min(height, (b0 + per_band) * t)
        band = np.full((r1 - r0, gw * t, 3), 255, dtype=np.uint8)
        rows = min(r1, ch) - r0
        for a0 in range(0, max(rows, 0), step):
            n = min(step, rows - a0)
            sy0 = ry0 + (r0 + a0) * scale
            wx0, wy0 = math.floor(rx0), math.floor(sy0)
            wx1 = min(math.ceil(rx0 + cw * scale), reader.levels[src].width)
            wy1 = min(math.ceil(ry0 + (r0 + a0 + n) * scale), reader.levels[src].height)
            window = reader.read_region(src, wx0, wy0, wx1 - wx0, wy1 - wy0)
            band[a0 : a0 + n, :cw] = _resample(window, ds, d, (cw, n), (rx0 - wx0, sy0 - wy0))
            del window
        yield r0, r1, band


def build_tiled_levels(
    reader,
    tmp: Path,
    downsamples,
    sizes,
    tile_size: int,
    ann=None,
    reg=None,
    share_background: bool = True,
    band_bytes: int = BAND_BYTES,
    progress: bool = True,
    mpp=None,
) -> tuple[list[dict], dict]:
    """Write the tiled levels (``downsamples`` finest first, content ``sizes``) of a bundle into ``tmp``
    plus ``tissue.npy`` (and ``region.npy`` for a region bundle); returns ``(levels metadata, stats)``.
    The coarsest level is made first (it is small, held whole): its Otsu tissue mask decides, with a
    per-tile saturation test, which tiles of every level are background."""
    import resource

    from scipy.ndimage import binary_dilation
    from shapely.affinity import translate
    from tqdm.auto import tqdm

    from data_tools.errors import BundleError
    from data_tools.masks import tissue_mask

    t = tile_size
    n = len(downsamples)
    polygon = None if reg is None or reg.polygon is None else translate(reg.polygon, -reg.box[0], -reg.box[1])
    tumour_geom = None if ann is None else ann.tumour
    # -- the coarsest level, whole: tissue reference
    kc = n - 1
    dc, (cwc, chc) = downsamples[kc], sizes[kc]
    if max(cwc, t) * max(chc, t) * 3 > 4 * AUTO_TILED_BYTES:
        raise BundleError(
            reader.path,
            f"the coarsest level ({cwc}×{chc} px) is too large for a tiled bundle's "
            "tissue mask; use a larger --magnification-range",
        )
    coarse = np.concatenate([b for _, _, b in _bands(reader, dc, (cwc, chc), t, reg, band_bytes)])
    inside_c = None
    if polygon is not None:
        inside_c = np.zeros(coarse.shape[:2], dtype=bool)
        inside_c[:, :cwc] = tumour_band(polygon, cwc, chc, 0, coarse.shape[0], dc, t, coarse.shape[1] // t)[0][:, :cwc]
        coarse[~inside_c] = 255
    content_c = coarse[:chc, :cwc]
    tissue = tissue_mask(content_c)
    if inside_c is not None:
        tissue &= inside_c[:chc, :cwc]
    threshold = saturation_threshold(content_c)
    from data_tools.raster import pad as _pad

    np.save(tmp / TISSUE, _pad(tissue, t, False), allow_pickle=False)
    if reg is not None:
        allowed = inside_c[:chc, :cwc] if inside_c is not None else np.ones((chc, cwc), dtype=bool)
        np.save(tmp / REGION, _pad(allowed, t, False), allow_pickle=False)
    dilated = binary_dilation(tissue, iterations=1) if tissue.any() else tissue
    tissue_sat = np.zeros((chc + 1, cwc + 1), dtype=np.int64)
    np.cumsum(np.cumsum(dilated, axis=0, dtype=np.int64), axis=1, out=tissue_sat[1:, 1:])

    def coarse_tissue(d: float, ty0: int, n_rows: int, gw: int) -> np.ndarray:
        """Whether the dilated coarse tissue mask has tissue over each tile's footprint."""
        ratio = t * d / dc
        ys, xs = np.arange(ty0, ty0 + n_rows), np.arange(gw)
        a0 = np.clip(np.floor(ys * ratio).astype(np.int64), 0, chc)
        a1 = np.clip(np.ceil((ys + 1) * ratio).astype(np.int64), 0, chc)
        b0 = np.clip(np.floor(xs * ratio).astype(np.int64), 0, cwc)
        b1 = np.clip(np.ceil((xs + 1) * ratio).astype(np.int64), 0, cwc)
        s = tissue_sat
        total = s[a1][:, b1] - s[a0][:, b1] - s[a1][:, b0] + s[a0][:, b0]
        return total > 0

    levels_meta: list[dict | None] = [None] * n
    stats = {"seconds_per_level": [None] * n}
    import time

    for k in [kc] + list(range(n - 1)):
        t0 = time.perf_counter()
        d, (cw, ch) = downsamples[k], sizes[k]
        width, height = max(cw, t), max(ch, t)
        gw, gh = -(-width // t), -(-height // t)
        names = tiled_level_files(k)
        pool = PoolWriter(tmp / names["tiles"], (t, t, 3), np.uint8)
        sat_pool = PoolWriter(tmp / names["sat_tiles"], (t + 1, t + 1), np.uint32)
        try:
            pool.append(np.full((1, t, t, 3), 255, np.uint8))  # 0: blank white
            sat_pool.append(np.zeros((1, t + 1, t + 1), np.uint32))  # 0: no tumour
            sat_pool.append(full_sat_tile(t)[None])  # 1: all tumour
            index = np.zeros((gh, gw), dtype=np.int32)
            sat_index = np.zeros((gh, gw), dtype=np.int32)
            tumour_px = 0
            if k == kc:
                bands = (
                    (r0, min(height, r0 + 4096 * t), coarse[r0 : r0 + 4096 * t]) for r0 in range(0, height, 4096 * t)
                )
            else:
                bands = _bands(reader, d, (cw, ch), t, reg, band_bytes)
            per_band = max(1, band_bytes // (gw * t * t * 3))
            bar = tqdm(
                bands,
                total=-(-gh // per_band) if k != kc else 1,
                unit="band",
                disable=not progress,
                desc=f"level {k} (downsample {d:.4g}, {width}×{height} px, tiled)",
            )
            for r0, r1, band in bar:
                ty0, n_rows = r0 // t, -(-(r1 - r0) // t)
                if polygon is not None and k != kc:
                    inside = tumour_band(polygon, cw, ch, r0, r1, d, t, gw)[0]
                    band[~inside[:, : band.shape[1]]] = 255
                mask, state = tumour_band(tumour_geom, cw, ch, r0, r1, d, t, gw)
                tumour_px += int(mask.sum())
                if band.shape[0] < n_rows * t:  # the last band: pad to whole tiles
                    band = np.concatenate(
                        [band, np.full((n_rows * t - band.shape[0],) + band.shape[1:], 255, np.uint8)]
                    )
                    mask = np.concatenate([mask, np.zeros((n_rows * t - mask.shape[0], mask.shape[1]), bool)])
                tiles = band.reshape(n_rows, t, gw, t, 3).swapaxes(1, 2).reshape(n_rows * gw, t, t, 3)
                if share_background:
                    sat = sampled_saturation(tiles)
                    keep = ((sat > threshold).mean(axis=(1, 2)) > SATURATED_FRACTION).reshape(n_rows, gw)
                    keep |= coarse_tissue(d, ty0, n_rows, gw) | (state > 0)
                else:
                    keep = np.ones((n_rows, gw), dtype=bool)
                flat_keep = keep.ravel()
                if flat_keep.any():
                    first = pool.append(tiles[flat_keep])
                    index[ty0 : ty0 + n_rows].ravel()[flat_keep] = np.arange(first, first + int(flat_keep.sum()))
                mixed = (state == 2).ravel()
                sat_index[ty0 : ty0 + n_rows][state == 1] = 1
                if mixed.any():
                    masks = mask.reshape(n_rows, t, gw, t).swapaxes(1, 2).reshape(n_rows * gw, t, t)[mixed]
                    first = sat_pool.append(local_sats(masks))
                    sat_index[ty0 : ty0 + n_rows].ravel()[mixed] = np.arange(first, first + int(mixed.sum()))
                del band, tiles, mask
        finally:
            pool.close()
            sat_pool.close()
        if pool.count >= 2**31 // (t * t) or sat_pool.count * (t + 1) ** 2 >= 2**31:
            raise BundleError(
                reader.path,
                f"level {k} needs {pool.count:,} tiles, too many for int32 indexing; use a coarser finest level",
            )
        np.save(tmp / names["tile_index"], index, allow_pickle=False)
        np.save(tmp / names["sat_index"], sat_index, allow_pickle=False)
        nbytes = tiled_level_bytes(pool.count, sat_pool.count, (gh, gw), t)
        levels_meta[k] = {
            "downsample": d,
            "width": int(width),
            "height": int(height),
            "content_width": cw,
            "content_height": ch,
            "mpp": None if mpp is None else mpp * d,
            "tumour_pixels": tumour_px,
            "storage": "tiled",
            "grid": [gh, gw],
            "pool_tiles": pool.count,
            "sat_pool_tiles": sat_pool.count,
            "kept_tiles": int((index > 0).sum()),
            "device_bytes": nbytes,
            "dense_device_bytes": 3 * width * height + 4 * (width + 1) * (height + 1),
            **names,
        }
        stats["seconds_per_level"][k] = round(time.perf_counter() - t0, 2)
    stats["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return levels_meta, stats


__all__ = [
    "AUTO_TILED_BYTES",
    "BAND_BYTES",
    "MAX_WINDOW_BYTES",
    "PoolWriter",
    "TiledLevel",
    "build_tiled_levels",
    "full_sat_tile",
    "local_sats",
    "tiled_level_bytes",
    "saturation_threshold",
    "tumour_band",
]
