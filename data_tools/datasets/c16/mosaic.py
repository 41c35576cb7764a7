"""Pixels of a true-scale CAMELYON16 slide: a mosaic of real PatchCamelyon patches, written as a
pyramidal JPEG-tiled TIFF tile by tile with bounded memory.

GEOMETRY IS REAL CAMELYON16, PIXELS ARE REAL PCam PATCHES ARRANGED BY US: not a scanned slide.

How the mosaic is made (:func:`compose`): each slide draws its own ``PER_CLASS`` normal and
``PER_CLASS`` tumour patches from the bank and gives them one stain of its own (every channel's
optical density scaled by a factor in ``STAIN_RANGE`` and the whole slide's density by one in
``DENSITY_RANGE``: slides differ in colour as scans of two centres do), and the tumour patches get a
per-channel gain that moves their mean RGB ``COLOUR_MATCH`` (70 %) of the way to that of the slide's
normal patches: a 128-px view averages about a dozen patches, so without it the mean colour of a
view alone would tell tumour from normal tissue (AUC 0.96 on our views, against 0.79 for single real
PCam patches; 0.69 with 70 %, 0.57 with 100 %, see docs/c16-benchmark.md); the cells, nuclei and
texture of every patch are kept. Patches are resized to their
true size at the slide's scale (96 px × 4 / downsample), laid on a regular grid with a step of 3/4 of
a patch, each in one of 8 orientations (90° turns, mirror), picked by a hash of the slide seed and
grid cell, and blended with separable tent weights, so neighbours overlap by a quarter patch and
seams fade. Tissue uses normal patches, tumour tumour patches; at the tumour's and tissue's edges
the two textures (and glass) are mixed by the pixel-centre masks of the polygons blurred over
``EDGE`` px. Tiles wholly on glass are one JPEG encoded once.

The pyramid (2×, 4×, … until the longer side is ≤ 512 px) is made by 2 × 2 averaging: each level
keeps one pending row of tiles, filled by the finer level's tile rows as they are made, so memory is
a few tile rows per level plus the (encoded) coarser levels.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter

from data_tools.datasets.c16.layout import SlideLayout
from data_tools.datasets.pcam_bank import PATCH, PatchBank

TIFF_TILE = 256
MIN_LEVEL_SIDE = 512
GLASS = np.array([255, 255, 255], np.uint8)  # as the blank tile of a tiled bundle
PER_CLASS = 256
STAIN_RANGE = (0.85, 1.15)  # per-channel optical-density factor of a slide
DENSITY_RANGE = (0.8, 1.2)  # whole-slide optical-density factor
EDGE = 5  # px over which tumour/tissue edges are blended
COLOUR_MATCH = 0.7  # fraction of the tumour/normal mean-colour gap removed per slide (see module doc)
PIXELS_NOTE = (
    "GEOMETRY IS REAL CAMELYON16 (NCRF polygons at true scale); PIXELS ARE REAL PatchCamelyon "
    "patches (CC0) ARRANGED BY histojax into a mosaic, NOT A SCANNED SLIDE. For training and testing "
    "navigation agents only, not for diagnosis."
)


def _stain(patches: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, list[float]]:
    """Patches (k, P, P, 3) uint8 with the slide's stain (see module doc): float32 in 0..255, and the factors."""
    gains = rng.uniform(*STAIN_RANGE, 3) * rng.uniform(*DENSITY_RANGE)
    od = -np.log((patches.astype(np.float32) + 1.0) / 256.0)
    out = np.clip(256.0 * np.exp(-od * gains.astype(np.float32)) - 1.0, 0, 255)
    return out.astype(np.float32), [round(float(g), 4) for g in gains]


def _resize(patches: np.ndarray, side: int) -> np.ndarray:
    from PIL import Image

    if side == patches.shape[1]:
        return patches
    return np.stack([np.asarray(Image.fromarray(p).resize((side, side), Image.Resampling.BOX)) for p in patches])


class Texture:
    """A slide's patch textures: ``normal`` / ``tumour`` float32 ``(k, P, P, 3)`` at the slide's scale."""

    def __init__(self, bank: PatchBank, downsample: float, seed: int, per_class: int = PER_CLASS):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 1601])
        self.side = max(4, int(round(PATCH * 4 / downsample)))
        self.step = max(3, self.side * 3 // 4)
        self.seed = int(seed)
        picked = {
            lab: rng.choice(bank.indices(lab), min(per_class, len(bank.indices(lab))), replace=False) for lab in (0, 1)
        }
        both = np.concatenate([picked[0], picked[1]])
        stained, self.stain = _stain(_resize(bank.decode(both), self.side), rng)
        self.normal, self.tumour = stained[: len(picked[0])], stained[len(picked[0]) :]
        gain = (self.normal.mean(axis=(0, 1, 2)) / np.maximum(self.tumour.mean(axis=(0, 1, 2)), 1.0)) ** COLOUR_MATCH
        self.tumour = np.clip(self.tumour * gain.astype(np.float32), 0, 255)
        self.patch_names = {lab: [str(bank.names[i]) for i in picked[lab]] for lab in (0, 1)}
        u = (np.arange(self.side) + 0.5) / self.side
        w = np.maximum(1.0 - np.abs(2.0 * u - 1.0), 0.05).astype(np.float32)
        self.weight = (w[:, None] * w[None, :])[..., None]

    def compose(self, x0: int, y0: int, width: int, height: int, tumour: bool) -> np.ndarray:
        """Texture float32 ``(height, width, 3)`` of the canvas window at ``(x0, y0)`` (level-0 px of the
        output slide), from tumour or normal patches (see the module doc)."""
        bank = self.tumour if tumour else self.normal
        p, s = self.side, self.step
        acc = np.zeros((height + 2 * p, width + 2 * p, 3), np.float32)
        wsum = np.zeros((height + 2 * p, width + 2 * p, 1), np.float32)
        cx0, cx1 = (x0 - p) // s + 1, (x0 + width - 1) // s
        cy0, cy1 = (y0 - p) // s + 1, (y0 + height - 1) // s
        cx = np.arange(cx0, cx1 + 1, dtype=np.int64)
        cy = np.arange(cy0, cy1 + 1, dtype=np.int64)
        h = (cx[None, :] * 73856093) ^ (cy[:, None] * 19349663) ^ (self.seed * 83492791 + (7 if tumour else 3))
        h = (h * 2654435761) & 0xFFFFFFFF
        pick, orient = (h >> 3) % len(bank), h & 7
        for a, yy in enumerate(cy):
            oy = int(yy * s - y0 + p)
            for b, xx in enumerate(cx):
                ox = int(xx * s - x0 + p)
                patch = bank[pick[a, b]]
                o = int(orient[a, b])
                if o & 4:
                    patch = patch[:, ::-1]
                patch = np.rot90(patch, o & 3)
                acc[oy : oy + p, ox : ox + p] += patch * self.weight
                wsum[oy : oy + p, ox : ox + p] += self.weight
        return acc[p : p + height, p : p + width] / np.maximum(wsum[p : p + height, p : p + width], 1e-6)


def _soft_mask(geom, x0: int, y0: int, t: int) -> np.ndarray:
    """Pixel-centre mask of ``geom`` over the ``t × t`` window at ``(x0, y0)``, blurred over ``EDGE`` px:
    float32 ``(t, t, 1)`` in [0, 1]."""
    import shapely

    e = EDGE
    part = shapely.clip_by_rect(geom, x0 - e, y0 - e, x0 + t + e, y0 + t + e)
    if part.is_empty:
        return np.zeros((t, t, 1), np.float32)
    xs = x0 - e + np.arange(t + 2 * e) + 0.5
    ys = y0 - e + np.arange(t + 2 * e) + 0.5
    m = shapely.contains_xy(part, xs[None, :], ys[:, None]).astype(np.float32)
    return uniform_filter(m, size=e, mode="nearest")[e : e + t, e : e + t, None]


def _halve(img: np.ndarray) -> np.ndarray:
    q = img.astype(np.uint16)
    return ((q[0::2, 0::2] + q[1::2, 0::2] + q[0::2, 1::2] + q[1::2, 1::2] + 2) // 4).astype(np.uint8)


def level_sizes(size: tuple[int, int]) -> list[tuple[int, int]]:
    """``(W, H)`` of every pyramid level: level 0, then halved (floor) until the longer side is ≤ 512."""
    levels = [tuple(size)]
    while max(levels[-1]) > MIN_LEVEL_SIDE:
        levels.append((max(1, levels[-1][0] // 2), max(1, levels[-1][1] // 2)))
    return levels


def write_slide_tiff(
    lay: SlideLayout, texture: Texture, out_tiff, description: str, jpeg_quality: int = 85, progress=None
) -> dict:
    """Write the mosaic of ``lay`` as a pyramidal JPEG-tiled TIFF at ``out_tiff`` (the caller makes it
    atomic); returns tile counts. ``progress(n)`` is called with the number of level-0 tiles done."""
    import imagecodecs
    import tifffile

    from data_tools.datasets.synth.large_slide import _classify

    t = TIFF_TILE
    width, height = lay.size
    levels = level_sizes(lay.size)
    grids = [(-(-h // t), -(-w // t)) for w, h in levels]
    gh0, gw0 = grids[0]
    s_tum, s_tis = _classify(lay.tumour, width, height, t), _classify(lay.tissue, width, height, t)

    def encode(tile):
        return imagecodecs.jpeg8_encode(tile, level=jpeg_quality, colorspace="rgb", outcolorspace="ycbcr")

    glass_tile = np.broadcast_to(GLASS, (t, t, 3)).copy()
    glass_bytes = encode(glass_tile)
    counts = {"glass": 0, "tissue": 0, "tumour": 0, "edge": 0}
    encoded: list[list[bytes]] = [[] for _ in levels[1:]]
    # one pending row of tiles per coarser level: pixels (t, gw*t, 3) and per-tile "all glass" flags
    pending = [np.broadcast_to(GLASS, (t, g[1] * t, 3)).copy() for g in grids[1:]]
    glass_flags = [np.ones(g[1], bool) for g in grids[1:]]
    filled = [0] * len(pending)  # half-rows received (0, 1 or 2)
    rows_done = [0] * len(pending)

    def push(k: int, row: np.ndarray, row_glass: np.ndarray, last: bool) -> None:
        """Give level ``k`` (1-based into pending) the halved tile row of level ``k - 1``."""
        if k > len(pending):
            return
        i = k - 1
        gw = grids[k][1]
        half = np.broadcast_to(GLASS, (t // 2, gw * t, 3)).copy()
        hg = np.ones(gw, bool)
        n = min(row.shape[1] // 2, gw * t)
        cols = row_glass.shape[0]
        for c in range(cols):
            if not row_glass[c] and c * t // 2 < n:
                half[:, c * t // 2 : (c + 1) * t // 2] = _halve(row[:, c * t : (c + 1) * t])
                hg[c // 2] = False
        r0 = filled[i] * (t // 2)
        pending[i][r0 : r0 + t // 2] = half
        glass_flags[i] &= hg
        filled[i] += 1
        if filled[i] == 2 or last:
            for c in range(gw):
                encoded[i].append(glass_bytes if glass_flags[i][c] else encode(pending[i][:, c * t : (c + 1) * t]))
            rows_done[i] += 1
            lastk = rows_done[i] == grids[k][0]
            push(k + 1, pending[i], glass_flags[i].copy(), lastk)
            pending[i][:] = GLASS
            glass_flags[i][:] = True
            filled[i] = 0

    def level0():
        for ty in range(gh0):
            row = np.broadcast_to(GLASS, (t, gw0 * t, 3)).copy()
            row_glass = np.ones(gw0, bool)
            out: list[bytes] = []
            for tx in range(gw0):
                a, b = s_tum[ty, tx], s_tis[ty, tx]
                x0, y0 = tx * t, ty * t
                if a == 0 and b == 0:
                    counts["glass"] += 1
                    out.append(glass_bytes)
                    continue
                if a == 1:
                    tile = texture.compose(x0, y0, t, t, tumour=True)
                    counts["tumour"] += 1
                elif a == 0 and b == 1:
                    tile = texture.compose(x0, y0, t, t, tumour=False)
                    counts["tissue"] += 1
                else:
                    counts["edge"] += 1
                    tile = texture.compose(x0, y0, t, t, tumour=False)
                    if a == 2:
                        alpha = _soft_mask(lay.tumour, x0, y0, t)
                        tile = tile * (1 - alpha) + texture.compose(x0, y0, t, t, tumour=True) * alpha
                    if b == 2:
                        alpha = np.maximum(_soft_mask(lay.tissue, x0, y0, t), _soft_mask(lay.tumour, x0, y0, t))
                        tile = tile * alpha + GLASS.astype(np.float32) * (1 - alpha)
                tile = np.clip(np.rint(tile), 0, 255).astype(np.uint8)
                row[:, x0 : x0 + t] = tile
                row_glass[tx] = False
                out.append(encode(tile))
            # the coarser levels first: tifffile stops pulling after the last tile of the page
            push(1, row, row_glass, ty == gh0 - 1)
            if progress is not None:
                progress(gw0)
            yield from out

    px_per_cm = 1e4 / lay.mpp
    options = dict(tile=(t, t), compression="jpeg", photometric="rgb", resolutionunit="CENTIMETER", metadata=None)
    with tifffile.TiffWriter(out_tiff, bigtiff=width * height * 3 > 2**31) as tif:
        tif.write(
            level0(),
            shape=(height, width, 3),
            dtype=np.uint8,
            subifds=len(levels) - 1,
            description=description.encode("ascii", "replace").decode("ascii"),
            resolution=(px_per_cm, px_per_cm),
            **options,
        )
        for k, (w, h) in enumerate(levels[1:], start=1):
            want = grids[k][0] * grids[k][1]
            if len(encoded[k - 1]) != want:
                raise RuntimeError(f"level {k}: {len(encoded[k - 1])} tiles made, {want} expected")
            tif.write(
                iter(encoded[k - 1]),
                shape=(h, w, 3),
                dtype=np.uint8,
                subfiletype=1,
                resolution=(px_per_cm / 2**k, px_per_cm / 2**k),
                **options,
            )
            encoded[k - 1] = []
    return {"tiles": counts, "levels": [list(lv) for lv in levels]}


__all__ = ["PIXELS_NOTE", "Texture", "level_sizes", "write_slide_tiff"]
