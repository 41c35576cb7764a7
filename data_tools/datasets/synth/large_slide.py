"""A gigapixel test slide nobody has to download: a pyramidal JPEG-tiled TIFF of any size (100,000 ×
100,000 px by default), mostly glass, with a real CAMELYON16 tissue outline and a real CAMELYON16 tumour
inside it. PIXELS ARE SYNTHETIC, GEOMETRY IS REAL (as :mod:`data_tools.datasets.synth.dataset`, whose texture code
makes the tiles here).

Written tile by tile with bounded memory: a small bank of 256 × 256 texture tiles (normal tissue and
tumour, made once by :func:`data_tools.datasets.synth.dataset._strips` on a 1024 × 1024 canvas) and one constant glass
tile are JPEG-encoded once; every TIFF tile wholly on glass, wholly normal tissue or wholly tumour is
one of those encoded tiles (picked by a hash of its position), and only tiles crossing a boundary are
composed pixel by pixel (pixel-centre rule on the polygons clipped to the tile) and encoded. Every
pyramid level (2×, 4×, … until the longer side is ≤ 512 px) is drawn the same way from the scaled
geometry (the texture is not rescaled: it is not to scale at any level). The tumour and tissue are
written as GeoJSON (level-0 px, labels ``tumour`` / ``tissue``) beside the TIFF.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import shapely
import tifffile
from shapely import affinity
from shapely.geometry import box
from tqdm.auto import tqdm

from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.writes import atomic_file
from data_tools.datasets.synth.dataset import (
    CAMELYON16_MPP,
    GLASS,
    LICENCE_NOTE,
    MIN_LEVEL_SIDE,
    PIXELS_NOTE,
    TIFF_TILE,
    _geojson,
    _polygonal,
    _strips,
    tissue_files,
    tumour_files,
)

__all__ = ["make_large_slide"]

BANK = 16  # texture tiles per kind


def _texture_bank(seed: int, tumour: bool) -> list[np.ndarray]:
    """``BANK`` tiles (256 × 256 × 3 uint8) of normal tissue or tumour texture."""
    side = int(math.sqrt(BANK)) * TIFF_TILE
    everything = box(-64, -64, side + 64, side + 64)
    stats = {"tumour_px": 0, "normal_px": 0, "tumour_rgb_sum": np.zeros(3), "normal_rgb_sum": np.zeros(3)}
    from shapely.geometry import MultiPolygon

    strips = [
        s
        for _, s in _strips(
            (side, side),
            seed,
            MultiPolygon([everything]) if tumour else MultiPolygon(),
            MultiPolygon([everything]),
            stats,
            False,
            "",
        )
    ]
    canvas = np.concatenate(strips)
    return [
        np.ascontiguousarray(canvas[y : y + TIFF_TILE, x : x + TIFF_TILE])
        for y in range(0, side, TIFF_TILE)
        for x in range(0, side, TIFF_TILE)
    ]


def _place(size, tissue_fraction: float, tumour_xml, tissue_xml):
    """Tissue (a CAMELYON16 tissue outline scaled to ~``tissue_fraction`` of the canvas, centred) and
    tumour (a CAMELYON16 tumour centred on the tissue's most interior point, its longer side the larger of
    1.3 × the distance from there to the tissue's edge and 40 % of the tissue piece's shorter side; the tissue
    is joined with it) in canvas px."""
    import warnings

    from shapely.ops import polylabel

    from data_tools.annotations import load_annotations

    width, height = size
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tis = load_annotations(tissue_xml).tissue
        tum = load_annotations(tumour_xml).tumour
    minx, miny, maxx, maxy = tis.bounds
    s = math.sqrt(tissue_fraction * width * height / tis.area)
    s = min(s, 0.96 * width / (maxx - minx), 0.96 * height / (maxy - miny))
    tissue = affinity.affine_transform(
        tis, [s, 0, 0, s, width / 2 - s * (minx + maxx) / 2, height / 2 - s * (miny + maxy) / 2]
    )
    tissue = _polygonal(shapely.simplify(tissue, 1.0, preserve_topology=True))
    largest = max(shapely.get_parts(tissue), key=lambda p: p.area)
    pole = polylabel(largest, tolerance=max(width, height) / 2000)
    r = largest.exterior.distance(pole)
    r = min([r] + [ring.distance(pole) for ring in largest.interiors])
    tminx, tminy, tmaxx, tmaxy = tum.bounds
    pminx, pminy, pmaxx, pmaxy = largest.bounds  # at least 40 % of the tissue piece's shorter side
    ts = max(1.3 * r, 0.4 * min(pmaxx - pminx, pmaxy - pminy)) / max(tmaxx - tminx, tmaxy - tminy)
    tumour = affinity.affine_transform(
        tum, [ts, 0, 0, ts, pole.x - ts * (tminx + tmaxx) / 2, pole.y - ts * (tminy + tmaxy) / 2]
    )
    tumour = _polygonal(
        shapely.intersection(shapely.simplify(tumour, 1.0, preserve_topology=True), box(0, 0, width, height))
    )
    tissue = _polygonal(shapely.union(tissue, tumour))
    return tumour, tissue, {"tissue_scale": s, "tumour_scale": ts, "tumour_centre": [pole.x, pole.y]}


def _classify(geom, width: int, height: int, t: int):
    """Per tile of a ``width × height`` level: 0 outside ``geom``, 1 wholly inside, 2 crossing (decided on
    the hull of each tile's pixel centres)."""
    gw, gh = -(-width // t), -(-height // t)
    ty, tx = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
    x1 = np.minimum((tx + 1) * t, width) - 0.5
    y1 = np.minimum((ty + 1) * t, height) - 0.5
    boxes = shapely.box(tx * t + 0.5, ty * t + 0.5, np.maximum(x1, tx * t + 0.6), np.maximum(y1, ty * t + 0.6))
    state = np.zeros((gh, gw), dtype=np.int8)
    if geom.is_empty:
        return state
    shapely.prepare(geom)
    inside = shapely.contains_properly(geom, boxes)
    touch = shapely.intersects(geom, boxes) & ~inside
    state[inside] = 1
    state[touch] = 2
    return state


def _tile_mask(geom, tx: int, ty: int, t: int) -> np.ndarray:
    """Pixel-centre mask ``(t, t)`` of ``geom`` over tile ``(tx, ty)`` (``geom`` clipped to the tile first)."""
    x0, y0 = tx * t, ty * t
    part = shapely.clip_by_rect(geom, x0, y0, x0 + t, y0 + t)
    if part.is_empty:
        return np.zeros((t, t), dtype=bool)
    xs = x0 + np.arange(t) + 0.5
    ys = y0 + np.arange(t) + 0.5
    return shapely.contains_xy(part, xs[None, :], ys[:, None])


def make_large_slide(
    out_tiff,
    size=100_000,
    tissue_fraction: float = 0.1,
    seed: int = 0,
    tumour_xml=None,
    tissue_xml=None,
    jpeg_quality: int = 85,
    progress: bool = True,
) -> dict:
    """Write a large semi-synthetic pyramidal TIFF (default geometry: the tissue outline of
    ``bench_tumor_021`` and the tumour of ``tumor_044``) ``out_tiff`` (``size`` px a side, or ``(W, H)``) and its
    ``.geojson``; returns a provenance dict (sizes, fractions, bytes, seconds). Memory stays bounded
    (a few tiles plus the per-level tile classification); see the module doc."""
    import imagecodecs

    t_start = time.perf_counter()
    out_tiff = Path(out_tiff)
    width, height = (int(size), int(size)) if isinstance(size, (int, np.integer)) else (int(size[0]), int(size[1]))
    if min(width, height) < 1024:
        raise ValueError(f"canvas {width}×{height} px is too small for a large slide (minimum 1024 a side)")
    if not 0 < tissue_fraction <= 0.8:
        raise ValueError(f"tissue fraction {tissue_fraction} must be in (0, 0.8]")
    tumour_xml = Path(tumour_xml or next(f for f in tumour_files() if f.stem == "tumor_044"))
    tissue_xml = Path(tissue_xml or tissue_files()[0])
    out_tiff.parent.mkdir(parents=True, exist_ok=True)
    tumour, tissue, placement = _place((width, height), tissue_fraction, tumour_xml, tissue_xml)
    t = TIFF_TILE
    glass_tile = np.broadcast_to(np.rint(GLASS).astype(np.uint8), (t, t, 3)).copy()
    normal_bank, tumour_bank = _texture_bank(seed, False), _texture_bank(seed + 1, True)

    def encode(tile):
        return imagecodecs.jpeg8_encode(tile, level=jpeg_quality, colorspace="rgb", outcolorspace="ycbcr")

    glass_bytes = encode(glass_tile)
    normal_bytes = [encode(x) for x in normal_bank]
    tumour_bytes = [encode(x) for x in tumour_bank]
    counts = {"glass": 0, "normal": 0, "tumour": 0, "mixed": 0}

    def level_tiles(level: int, w: int, h: int):
        g = 0.5**level
        tum = affinity.scale(tumour, g, g, origin=(0, 0))
        tis = affinity.scale(tissue, g, g, origin=(0, 0))
        s_tum, s_tis = _classify(tum, w, h, t), _classify(tis, w, h, t)
        gh, gw = s_tum.shape
        bar = tqdm(
            total=gh * gw,
            desc=f"synth-large level {level} ({w}×{h})",
            unit="tile",
            disable=not progress,
            mininterval=2.0,
        )
        for ty in range(gh):
            for tx in range(gw):
                pick = (tx * 73856093 ^ ty * 19349663 ^ level * 83492791) % BANK
                a, b = s_tum[ty, tx], s_tis[ty, tx]
                if a == 1:
                    counts["tumour"] += 1
                    yield tumour_bytes[pick]
                elif a == 0 and b == 1:
                    counts["normal"] += 1
                    yield normal_bytes[pick]
                elif a == 0 and b == 0:
                    counts["glass"] += 1
                    yield glass_bytes
                else:
                    counts["mixed"] += 1
                    tile = glass_tile.copy()
                    m_tis = _tile_mask(tis, tx, ty, t) if b == 2 else np.full((t, t), b == 1)
                    tile[m_tis] = normal_bank[pick][m_tis]
                    if a == 2:
                        m_tum = _tile_mask(tum, tx, ty, t)
                        tile[m_tum] = tumour_bank[pick][m_tum]
                    yield encode(tile)
            bar.update(gw)
        bar.close()

    levels = [(width, height)]
    while max(levels[-1]) > MIN_LEVEL_SIDE:
        levels.append((max(1, levels[-1][0] // 2), max(1, levels[-1][1] // 2)))
    mpp = CAMELYON16_MPP
    px_per_cm = 1e4 / mpp
    source_line = f"pixels synthetic, geometry real CAMELYON16: tissue {tissue_xml.name}, tumour {tumour_xml.name}"
    description = (
        f"histojax large semi-synthetic slide {width}x{height}. {PIXELS_NOTE} Tissue outline: CAMELYON16 "
        f"{tissue_xml.name}; tumour: CAMELYON16 {tumour_xml.name} (CC0 1.0). Seed {seed}."
    )
    options = dict(tile=(t, t), compression="jpeg", photometric="rgb", resolutionunit="CENTIMETER", metadata=None)
    with atomic_file(out_tiff) as tmp:
        with tifffile.TiffWriter(tmp, bigtiff=width * height * 3 > 2**31 or width * height > 2**28) as tif:
            tif.write(
                level_tiles(0, width, height),
                shape=(height, width, 3),
                dtype=np.uint8,
                subifds=len(levels) - 1,
                description=description.encode("ascii", "replace").decode("ascii"),
                resolution=(px_per_cm, px_per_cm),
                **options,
            )
            for k, (w, h) in enumerate(levels[1:], start=1):
                f = 2**k
                tif.write(
                    level_tiles(k, w, h),
                    shape=(h, w, 3),
                    dtype=np.uint8,
                    subfiletype=1,
                    resolution=(px_per_cm / f, px_per_cm / f),
                    **options,
                )
    geojson_path = out_tiff.with_suffix(".geojson")
    geojson_path.write_text(json.dumps(_geojson(tumour, tissue, source_line), allow_nan=False))
    area = float(width) * height
    provenance = {
        "kind": "large semi-synthetic slide (histojax data_tools.datasets.synth.large_slide)",
        "note": PIXELS_NOTE,
        "licence": LICENCE_NOTE,
        "summary": source_line,
        "tumour_source": {"file": tumour_xml.name, "sha256": sha256(tumour_xml)},
        "tissue_source": {"file": tissue_xml.name, "sha256": sha256(tissue_xml)},
        "placement": placement,
        "seed": int(seed),
        "canvas": [width, height],
        "levels": [list(lv) for lv in levels],
        "tiff": out_tiff.name,
        "geojson": geojson_path.name,
        "tissue_fraction": float(tissue.area) / area,
        "tumour_fraction": float(tumour.area) / area,
        "tile_counts": counts,
        "tiff_bytes": out_tiff.stat().st_size,
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    out_tiff.with_suffix(".provenance.json").write_text(json.dumps(provenance, indent=1, allow_nan=False))
    return provenance
