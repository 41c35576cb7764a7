"""Semi-synthetic training slides: REAL CAMELYON16 geometry, SYNTHETIC pixels.

What is real and what is not, said plainly (and written into every TIFF's
ImageDescription, a ``<name>.provenance.json`` beside it and the dataset's
``dataset.json``):

* **Geometry is real.** Tumour polygons are the CAMELYON16 ground-truth
  annotations (ASAP XML, exclusion holes subtracted, CC0 1.0), scaled uniformly
  (and, for repeats, rotated / flipped by multiples of 90°) onto a small canvas.
  Tissue outlines are either a smooth synthetic blob around the tumour (the
  dataset default) or a CAMELYON16 tissue annotation (pathml-tutorial). The tissue annotations shipped here
  belong to *other* CAMELYON16 slides than the tumour files, so a shipped tissue
  outline is fitted to the canvas on its own and joined with a rim around the
  tumour (the tumour always lies on tissue); the provenance says which.
* **Pixels are synthetic.** An H&E-like texture made procedurally with numpy:
  near-white glass, pink (eosin) normal tissue with sparse small purple nuclei,
  purple (haematoxylin-dense) tumour with larger, crowded nuclei. No scan is
  involved; the slides are for training and testing navigation agents, never for
  anything diagnostic. The texture is not at the physical scale the stated µm/px
  implies (that number describes the geometry: CAMELYON16 level 0 ≈ 0.243 µm/px
  divided by the canvas scale).

The slide is generated in strips of 256 rows (memory ~ canvas width × 300 × 12
bytes, plus the 2× level kept in memory), written as a pyramidal JPEG-tiled TIFF
(256 px tiles, SubIFD levels at 2×, 4×, … until the longer side is ≤ 512 px),
with the tumour (label ``tumour``) and tissue (label ``tissue``) in canvas pixels
as GeoJSON beside it, and goes into a bundle through :func:`data_tools.bundle.build_bundle`
like any other slide. Everything is deterministic given the seed.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import shapely
import tifffile
from scipy.ndimage import gaussian_filter
from shapely import affinity
from shapely.geometry import MultiPolygon, Polygon, box, mapping
from tqdm.auto import tqdm

from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.writes import atomic_file
from data_tools.errors import AnnotationError

__all__ = [
    "CAMELYON16_DIR",
    "CAMELYON16_MPP",
    "make_dataset",
    "make_semisynthetic_slide",
    "save_preview",
    "tissue_files",
    "tumour_files",
]

CAMELYON16_DIR = Path(__file__).resolve().parents[2] / "camelyon16"
"""Bundled CAMELYON16 annotations (see ``LICENSES.md`` there)."""
CAMELYON16_MPP = 0.243
"""Approximate µm per level-0 px of the CAMELYON16 scans (40×); used to state the canvas µm/px."""

TIFF_TILE = 256
STRIP = 256  # rows generated at a time (one TIFF tile row)
HALO = 16  # extra rows each side of a strip: mask blur and nuclei reaching across strips
MIN_LEVEL_SIDE = 512
SIMPLIFY_PX = 0.25  # geometry simplification on the canvas (sub-pixel, keeps topology)
MARGIN = 0.08  # canvas margin around the tumour, as a fraction of the tumour's longer side

# colours (RGB, 0..255) of the procedural stain
GLASS = np.array([241.0, 240.0, 244.0], dtype=np.float32)
EOSIN = np.array([232.0, 168.0, 206.0], dtype=np.float32)  # normal tissue background
TUMOUR_BASE = np.array([186.0, 128.0, 196.0], dtype=np.float32)  # tumour background: haematoxylin-dense
NUCLEUS_NORMAL = np.array([104.0, 70.0, 152.0], dtype=np.float32)
NUCLEUS_TUMOUR = np.array([72.0, 42.0, 128.0], dtype=np.float32)
# nuclei: (mean area per nucleus in px², min radius, max radius); radii in canvas px
NUCLEI_NORMAL = (260.0, 1.3, 2.4)
NUCLEI_TUMOUR = (55.0, 2.6, 5.0)
MAX_RADIUS = 6

PIXELS_NOTE = (
    "PIXELS ARE SYNTHETIC (procedural H&E-like texture made with numpy, not a scan); "
    "GEOMETRY IS REAL (CAMELYON16 annotations, scaled). For training navigation agents only, "
    "not for diagnosis."
)
LICENCE_NOTE = (
    "tumour geometry: CAMELYON16 ground truth, CC0 1.0 (as kept in markowetzlab/pathml-tutorial); "
    "tissue outlines: pathml-tutorial tissue annotations on CAMELYON16 slides"
)


def tumour_files() -> list[Path]:
    """The bundled CAMELYON16 tumour annotations (``tumor_NNN.xml``), sorted."""
    return sorted(CAMELYON16_DIR.glob("tumor_*.xml"))


def tissue_files() -> list[Path]:
    """The bundled CAMELYON16 tissue annotations (pathml-tutorial), largest tissue area first."""
    # fixed order (largest outlines first) so datasets are reproducible without loading every file
    preferred = [
        "bench_tumor_021",
        "bench_tumor_051",
        "bench_tumor_031",
        "dtd_tumor_001",
        "dtd_tumor_111",
        "bench_normal_004",
        "bench_tumor_092",
        "dtd_normal_002",
        "bench_normal_042",
        "dtd_tumor_013",
        "dtd_normal_008",
    ]
    found = {p.stem: p for p in CAMELYON16_DIR.glob("*.xml") if not p.stem.startswith("tumor_")}
    return [found.pop(s) for s in preferred if s in found] + sorted(found.values())


_sha256 = sha256  # the bundle format's checksum (older importers use this name)


def _rng(seed: int, *tags: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *tags])


# ---------------------------------------------------------------------------
# geometry


_ORIENTATIONS = [(1, 0, 0, 1), (0, -1, 1, 0), (-1, 0, 0, -1), (0, 1, -1, 0)]  # 0, 90, 180, 270 degrees


def _orient(geom, orientation: int):
    """Rotate by ``orientation % 4`` × 90° and mirror (x → −x) if ``orientation % 8 >= 4``."""
    a, b, d, e = _ORIENTATIONS[orientation % 4]
    if orientation % 8 >= 4:
        a, b = -a, -b
    return affinity.affine_transform(geom, [a, b, d, e, 0.0, 0.0])


def _fit(geom, size: tuple[int, int], margin: float) -> tuple[float, float, float]:
    """Uniform scale and offsets putting ``geom``'s bounding box (plus ``margin`` × its longer side on
    every side) centred in a ``size`` canvas."""
    minx, miny, maxx, maxy = geom.bounds
    bw, bh = maxx - minx, maxy - miny
    pad = margin * max(bw, bh)
    s = min(size[0] / (bw + 2 * pad), size[1] / (bh + 2 * pad))
    return s, size[0] / 2 - s * (minx + maxx) / 2, size[1] / 2 - s * (miny + maxy) / 2


def _polygonal(geom) -> MultiPolygon:
    parts = [p for p in shapely.get_parts(shapely.make_valid(geom)) if p.geom_type == "Polygon" and p.area > 0]
    if not parts:
        return MultiPolygon()
    return shapely.union_all(parts) if len(parts) > 1 else MultiPolygon(parts)


def _as_multi(geom) -> MultiPolygon:
    parts = [p for p in shapely.get_parts(geom) if p.geom_type == "Polygon" and not p.is_empty]
    return MultiPolygon(parts) if parts else MultiPolygon()


def _blob(core, radius: float, seed: int) -> Polygon:
    """A smooth irregular blob around ``core``: its convex hull buffered by ``radius``, the boundary
    pushed in and out by a random smooth periodic wobble (±35 % of ``radius``)."""
    hull = core.convex_hull.buffer(radius, quad_segs=32)
    ring = hull.exterior
    n = 512
    pts = np.array([ring.interpolate(t, normalized=True).coords[0] for t in np.linspace(0, 1, n, endpoint=False)])
    centre = np.array(hull.centroid.coords[0])
    direction = pts - centre
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
    rng = _rng(seed, 7)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    wobble = sum(rng.normal() / k * np.sin(k * t + rng.uniform(0, 2 * np.pi)) for k in range(2, 9))
    wobble = wobble / max(np.abs(wobble).max(), 1e-9) * 0.35 * radius
    return shapely.make_valid(Polygon(pts + direction * wobble[:, None])).buffer(0)


def _place_geometry(tumour_xml, size, seed, orientation, tissue_xml):
    """Tumour and tissue (MultiPolygons in canvas px), the tumour transform, and a provenance dict."""
    from data_tools.annotations import load_annotations

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ann = load_annotations(tumour_xml)
    notes = [str(w.message) for w in caught]
    if ann.tumour.is_empty:
        raise AnnotationError(tumour_xml, "no tumour polygons: cannot place a semi-synthetic tumour")
    src_tumour = _orient(ann.tumour, orientation)
    s, ox, oy = _fit(src_tumour, size, MARGIN)
    canvas = box(0, 0, *size)

    def to_canvas(g):
        g = affinity.affine_transform(g, [s, 0, 0, s, ox, oy])
        return _polygonal(shapely.intersection(shapely.simplify(g, SIMPLIFY_PX, preserve_topology=True), canvas))

    tumour = to_canvas(src_tumour)
    rim = tumour.buffer(0.01 * max(size), quad_segs=4)
    tissue_info: dict
    if tissue_xml is None:
        minx, miny, maxx, maxy = tumour.bounds
        blob = _blob(tumour, 0.8 * MARGIN * max(maxx - minx, maxy - miny), seed)
        tissue = _polygonal(shapely.intersection(shapely.union(blob, rim), canvas))
        tissue_info = {
            "kind": "synthetic",
            "how": "convex hull of the tumour, buffered, with a smooth random "
            "wobble; joined with a rim around the tumour",
        }
    else:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            tann = load_annotations(tissue_xml)
        notes += [str(w.message) for w in caught]
        if tann.tissue.is_empty:
            raise AnnotationError(tissue_xml, "no tissue polygons (group 'tissue')")
        same_slide = shapely.intersection(ann.tumour, tann.tissue).area >= 0.5 * ann.tumour.area
        src_tissue = _orient(tann.tissue, orientation)
        if same_slide:  # one frame: the tumour's transform
            placed = to_canvas(src_tissue)
            how = "tissue outline of the same slide, same transform as the tumour"
        else:  # another slide: fit its outline to the canvas on its own
            ts, tx, ty = _fit(src_tissue, size, 0.02)
            placed = affinity.affine_transform(src_tissue, [ts, 0, 0, ts, tx, ty])
            placed = shapely.simplify(placed, SIMPLIFY_PX, preserve_topology=True)
            how = (
                "tissue outline of ANOTHER CAMELYON16 slide, scaled uniformly to fit the canvas; joined with a "
                "rim around the tumour so the tumour lies on tissue"
            )
        tissue = _polygonal(shapely.intersection(shapely.union(placed, rim), canvas))
        tissue_info = {
            "kind": "camelyon16",
            "file": Path(tissue_xml).name,
            "sha256": _sha256(Path(tissue_xml)),
            "same_slide_as_tumour": bool(same_slide),
            "how": how,
        }
    transform = {
        "orientation": orientation,
        "scale": s,
        "offset": [ox, oy],
        "meaning": "canvas = scale * orient(source level-0 px) + offset; orient = rotation by "
        "(orientation % 4) * 90 degrees, mirrored in x if orientation % 8 >= 4",
    }
    return _as_multi(tumour), _as_multi(tissue), transform, tissue_info, notes


# ---------------------------------------------------------------------------
# pixels


def _rows_mask(parts, width: int, y0: int, y1: int) -> np.ndarray:
    """Rows ``y0..y1`` (may be outside the canvas) of the canvas-px mask of prepared polygons ``parts``
    (pixel-centre rule, as data_tools.masks.rasterize, evaluated in canvas coordinates)."""
    mask = np.zeros((y1 - y0, width), dtype=bool)
    for poly, (minx, miny, maxx, maxy) in parts:
        c0, c1 = max(0, int(np.floor(minx - 0.5))), min(width, int(np.ceil(maxx + 0.5)))
        r0, r1 = max(y0, int(np.floor(miny - 0.5))), min(y1, int(np.ceil(maxy + 0.5)))
        if c0 >= c1 or r0 >= r1:
            continue
        xs = np.arange(c0, c1) + 0.5
        ys = np.arange(r0, r1) + 0.5
        mask[r0 - y0 : r1 - y0, c0:c1] |= shapely.contains_xy(poly, xs[None, :], ys[:, None])
    return mask


def _prepared(geom):
    parts = []
    for p in shapely.get_parts(geom):
        if p.geom_type == "Polygon" and not p.is_empty:
            shapely.prepare(p)
            parts.append((p, p.bounds))
    return parts


class _Field:
    """Smooth noise on the whole canvas: a coarse random grid (one value per ``spacing`` px), blurred by
    ``sigma`` grid cells and normalised to unit std, read back bilinearly for any rows."""

    def __init__(self, size, spacing: int, sigma, rng: np.random.Generator):
        self.spacing = spacing
        gw, gh = size[0] // spacing + 3, size[1] // spacing + 3
        grid = gaussian_filter(rng.standard_normal((gh, gw)).astype(np.float32), sigma, mode="wrap")
        self.grid = grid / max(float(grid.std()), 1e-6)

    @staticmethod
    def _weights(coords: np.ndarray, spacing: int, n: int):
        g = (coords + 0.5) / spacing + 0.5
        i0 = np.clip(np.floor(g).astype(np.int64), 0, n - 2)
        return i0, (g - i0).astype(np.float32)

    def rows(self, y0: int, y1: int, width: int) -> np.ndarray:
        gh, gw = self.grid.shape
        iy, fy = self._weights(np.arange(y0, y1), self.spacing, gh)
        r = self.grid[iy] * (1 - fy[:, None]) + self.grid[iy + 1] * fy[:, None]
        ix, fx = self._weights(np.arange(width), self.spacing, gw)
        return r[:, ix] * (1 - fx) + r[:, ix + 1] * fx


def _hash_noise(seed: int, y0: int, y1: int, width: int) -> np.ndarray:
    """Standard-normal-ish white noise for canvas rows ``y0..y1``, a pure function of (seed, x, y), so
    overlapping strips agree and blurring it strip by strip (with a halo) has no seams."""
    y = np.arange(y0, y1, dtype=np.int64)[:, None] & 0xFFFFFFFF
    x = np.arange(width, dtype=np.int64)[None, :]
    h = (x * 374761393 + y * 668265263 + (int(seed) & 0xFFFF) * 2246822519) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = (h ^ (h >> 16)).astype(np.float32)
    return (h / np.float32(2**32) - 0.5) * np.float32(math.sqrt(12.0))


def _nuclei(seed: int, strip: int, kind: int, width: int, params) -> np.ndarray:
    """Candidate nuclei of one strip (rows ``strip*STRIP ..``), deterministic by (seed, strip, kind):
    columns cx, cy, rx, ry, shade, alpha."""
    area, rmin, rmax = params
    rng = _rng(seed, 11, kind, strip)
    n = rng.poisson(width * STRIP / area)
    cx = rng.uniform(0, width, n)
    cy = strip * STRIP + rng.uniform(0, STRIP, n)
    r = rng.uniform(rmin, rmax, n)
    aspect = rng.uniform(0.75, 1.0, n)
    swap = rng.random(n) < 0.5
    rx, ry = np.where(swap, r * aspect, r), np.where(swap, r, r * aspect)
    return np.stack([cx, cy, rx, ry, rng.uniform(0.85, 1.12, n), rng.uniform(0.7, 0.95, n)], axis=1)


def _draw_nuclei(img: np.ndarray, y0: int, nuclei: np.ndarray, colour: np.ndarray) -> None:
    """Paint elliptical nuclei onto ``img`` (rows from canvas row ``y0``), blending by each one's alpha."""
    if len(nuclei) == 0:
        return
    h, w = img.shape[:2]
    d = np.arange(-MAX_RADIUS, MAX_RADIUS + 1)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    dx, dy = dx.ravel(), dy.ravel()
    for chunk in np.array_split(nuclei, max(1, len(nuclei) // 4000)):  # bounds the temporaries
        cx, cy, rx, ry, shade, alpha = chunk.T
        ix = np.rint(cx).astype(np.int64)[:, None] + dx
        iy = np.rint(cy).astype(np.int64)[:, None] + dy - y0
        fx = (ix + 0.5 - cx[:, None]) / rx[:, None]
        fy = (iy + y0 + 0.5 - cy[:, None]) / ry[:, None]
        inside = (fx * fx + fy * fy <= 1.0) & (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        k = np.nonzero(inside)
        px, py = ix[k], iy[k]
        a = alpha[k[0]][:, None].astype(np.float32)
        col = (colour[None, :] * shade[k[0]][:, None]).astype(np.float32)
        img[py, px] = img[py, px] * (1 - a) + col * a


def _strips(size, seed, tumour, tissue, stats, progress, desc):
    """Yield ``(y0, rgb uint8 strip)`` for every STRIP rows of the canvas; fills ``stats``."""
    width, height = size
    tum_parts, tis_parts = _prepared(tumour), _prepared(tissue)
    low = _Field(size, 64, 1.5, _rng(seed, 1))  # stain intensity, slow
    fibre = _Field(size, 6, (0.6, 2.5), _rng(seed, 2))  # fibrous stroma, streaky
    n_strips = math.ceil(height / STRIP)
    for s in tqdm(range(n_strips), desc=desc, unit="strip", disable=not progress):
        y0, y1 = s * STRIP, min(height, (s + 1) * STRIP)
        a0, a1 = y0 - HALO, y1 + HALO  # with halo
        tum = _rows_mask(tum_parts, width, a0, a1)
        tis = _rows_mask(tis_parts, width, a0, a1) | tum
        tis_soft = gaussian_filter(tis.astype(np.float32), 1.2)[..., None]
        tum_soft = gaussian_filter(tum.astype(np.float32), 2.0)[..., None]
        lo = low.rows(a0, a1, width)[..., None]
        fi = fibre.rows(a0, a1, width)[..., None]
        gr = gaussian_filter(_hash_noise(seed, a0, a1, width), 1.6)[..., None] * 5.7  # fine grain, ~unit std
        iid = _rng(seed, 4, s).standard_normal((a1 - a0, width, 1)).astype(np.float32)
        glass = GLASS + lo * np.float32(1.5) + iid * np.float32(1.5)
        f32 = lambda *v: np.array(v, dtype=np.float32)  # noqa: E731
        normal = EOSIN + lo * f32(6, 14, 8) + fi * f32(7, 12, 6) + gr * f32(4) + iid * f32(3)
        tumour_bg = TUMOUR_BASE + lo * f32(8, 10, 6) + gr * f32(8, 8, 6) + iid * f32(4)
        img = glass * (1 - tis_soft) + tis_soft * (normal * (1 - tum_soft) + tumour_bg * tum_soft)
        img = img.astype(np.float32)
        for kind, params, colour, where in (
            (0, NUCLEI_NORMAL, NUCLEUS_NORMAL, tis & ~tum),
            (1, NUCLEI_TUMOUR, NUCLEUS_TUMOUR, tum),
        ):
            cand = np.concatenate(
                [_nuclei(seed, t, kind, width, params) for t in (s - 1, s, s + 1) if 0 <= t < n_strips]
            )
            cand = cand[(cand[:, 1] >= a0) & (cand[:, 1] < a1)]
            keep = where[
                np.clip(cand[:, 1].astype(np.int64) - a0, 0, a1 - a0 - 1),
                np.clip(cand[:, 0].astype(np.int64), 0, width - 1),
            ]
            _draw_nuclei(img, a0, cand[keep], colour)
        out = np.clip(np.rint(img[HALO : HALO + (y1 - y0)]), 0, 255).astype(np.uint8)
        core_tum, core_tis = tum[HALO : HALO + (y1 - y0)], tis[HALO : HALO + (y1 - y0)]
        core_norm = core_tis & ~core_tum
        stats["tumour_px"] += int(core_tum.sum())
        stats["normal_px"] += int(core_norm.sum())
        stats["tumour_rgb_sum"] += out[core_tum].sum(axis=0, dtype=np.float64)
        stats["normal_rgb_sum"] += out[core_norm].sum(axis=0, dtype=np.float64)
        yield y0, out


def _halve(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    q = img[:h, :w].astype(np.uint16)
    return ((q[0::2, 0::2] + q[1::2, 0::2] + q[0::2, 1::2] + q[1::2, 1::2] + 2) // 4).astype(np.uint8)


def _tiles(img: np.ndarray):
    """Full TIFF_TILE × TIFF_TILE tiles of ``img`` in row-major order (edges padded with glass white)."""
    for y in range(0, img.shape[0], TIFF_TILE):
        for x in range(0, img.shape[1], TIFF_TILE):
            t = img[y : y + TIFF_TILE, x : x + TIFF_TILE]
            if t.shape[:2] != (TIFF_TILE, TIFF_TILE):
                t = np.pad(t, ((0, TIFF_TILE - t.shape[0]), (0, TIFF_TILE - t.shape[1]), (0, 0)), constant_values=240)
            yield t


def _geojson(tumour, tissue, provenance_line: str) -> dict:
    feats = [
        {"type": "Feature", "properties": {"label": label, "provenance": provenance_line}, "geometry": mapping(g)}
        for label, g in (("tumour", tumour), ("tissue", tissue))
        if not g.is_empty
    ]
    return {"type": "FeatureCollection", "features": feats}


def make_semisynthetic_slide(
    tumour_xml,
    out_tiff,
    size=(4096, 4096),
    seed: int = 0,
    tissue_xml=None,
    orientation: int = 0,
    jpeg_quality: int = 90,
    progress: bool = True,
    negative: bool = False,
) -> dict:
    """Write a semi-synthetic slide: real CAMELYON16 tumour geometry, synthetic H&E-like pixels.

    ``tumour_xml``: an ASAP XML with tumour polygons (exclusion holes are subtracted). Its tumour,
    rotated/mirrored by ``orientation`` (0..7, multiples of 90°), is scaled uniformly so the tumour's
    bounding box plus a margin of 8 % of its longer side fits centred in the ``size = (W, H)`` canvas
    (level-0 px). ``tissue_xml``: an ASAP XML with ``tissue`` polygons; used in the tumour's frame if it
    covers the tumour (same slide), else fitted to the canvas on its own; joined with a rim around the
    tumour. Without it the tissue is a smooth random blob around the tumour.

    Writes ``out_tiff`` (pyramidal JPEG-tiled TIFF, 256-px tiles, SubIFD levels at 2×, 4×, … until the
    longer side is ≤ 512 px, provenance in ImageDescription, µm/px in the resolution tags),
    ``<stem>.geojson`` (tumour and tissue in canvas px, labels ``tumour`` / ``tissue``) and
    ``<stem>.provenance.json`` beside it. Deterministic given ``seed``. Returns the provenance dict
    (it includes the paths, tumour area, mean colours of tumour and normal tissue, seconds taken).
    ``negative=True`` makes a tumour-free slide: the tumour geometry only places the tissue, and
    only normal tissue is drawn (a slide of label 0 for diagnosis tasks).
    """
    t_start = time.perf_counter()
    out_tiff = Path(out_tiff)
    width, height = int(size[0]), int(size[1])
    if width < 64 or height < 64:
        raise ValueError(f"canvas {width}x{height} px is too small (minimum 64 a side)")
    out_tiff.parent.mkdir(parents=True, exist_ok=True)
    tumour, tissue, transform, tissue_info, notes = _place_geometry(
        tumour_xml, (width, height), seed, orientation, tissue_xml
    )
    if negative:  # the tumour only shaped the tissue; none is drawn
        tissue, tumour = tissue.union(tumour), MultiPolygon()
        notes = list(notes) + ["negative slide: no tumour drawn (the tumour geometry only placed the tissue)"]
    mpp = CAMELYON16_MPP / transform["scale"]
    source_line = f"pixels synthetic, geometry real CAMELYON16 {Path(tumour_xml).name}"
    provenance = {
        "kind": "semi-synthetic slide (histojax data_tools.datasets.synth)",
        "pixels": "SYNTHETIC: procedural H&E-like texture (numpy noise fields, random elliptical nuclei), not a scan",
        "geometry": "REAL: CAMELYON16 annotations, transformed to canvas px (uniform scale, 90-degree rotations/"
        f"mirroring, simplified by {SIMPLIFY_PX} px)",
        "summary": source_line,
        "note": PIXELS_NOTE,
        "licence": LICENCE_NOTE,
        "tumour_source": {
            "file": Path(tumour_xml).name,
            "sha256": _sha256(Path(tumour_xml)),
            "dataset": "CAMELYON16 ground truth (CC0 1.0)",
        },
        "tissue_source": tissue_info,
        "transform": transform,
        "seed": int(seed),
        "canvas": [width, height],
        "mpp": mpp,
        "mpp_meaning": f"CAMELYON16 level 0 (~{CAMELYON16_MPP} um/px) divided by the scale: the physical size of "
        "the real geometry; the synthetic texture is not drawn to this scale",
        "annotation_warnings": notes,
    }
    description = (
        f"histojax semi-synthetic slide. {PIXELS_NOTE} Tumour geometry: CAMELYON16 "
        f"{Path(tumour_xml).name} (CC0 1.0), scale {transform['scale']:.6g}, orientation {orientation}. "
        f"Tissue: {tissue_info['how']}"
        + (f" ({tissue_info['file']})" if "file" in tissue_info else "")
        + f". Seed {seed}. mpp {mpp:.4g} (geometry scale; texture not to scale)."
    )
    description = description.encode("ascii", "replace").decode("ascii")

    stats = {"tumour_px": 0, "normal_px": 0, "tumour_rgb_sum": np.zeros(3), "normal_rgb_sum": np.zeros(3)}
    n_sub = 0
    w, h = width, height
    while max(w, h) > MIN_LEVEL_SIDE or n_sub == 0:
        w, h = max(1, w // 2), max(1, h // 2)
        n_sub += 1
    half = np.zeros((height // 2, width // 2, 3), dtype=np.uint8)

    def level0_tiles():
        for y0, strip in _strips((width, height), seed, tumour, tissue, stats, progress, f"synth {out_tiff.stem}"):
            if strip.shape[0] >= 2:
                hs = _halve(strip)
                half[y0 // 2 : y0 // 2 + hs.shape[0], : hs.shape[1]] = hs
            yield from _tiles(strip)

    px_per_cm = 1e4 / mpp
    options = dict(
        tile=(TIFF_TILE, TIFF_TILE),
        compression="jpeg",
        compressionargs={"level": int(jpeg_quality)},
        photometric="rgb",
        resolutionunit="CENTIMETER",
        metadata=None,
    )
    with atomic_file(out_tiff) as tmp:
        with tifffile.TiffWriter(tmp, bigtiff=width * height * 3 > 2**31) as tif:
            tif.write(
                level0_tiles(),
                shape=(height, width, 3),
                dtype=np.uint8,
                subifds=n_sub,
                description=description,
                resolution=(px_per_cm, px_per_cm),
                **options,
            )
            level, factor = half, 2
            for _ in range(n_sub):
                tif.write(level, subfiletype=1, resolution=(px_per_cm / factor, px_per_cm / factor), **options)
                level, factor = _halve(level), factor * 2

    geojson_path = out_tiff.with_suffix(".geojson")
    geojson_path.write_text(json.dumps(_geojson(tumour, tissue, source_line), allow_nan=False))
    area = width * height
    mean = lambda key, n: (stats[key] / n).round(1).tolist() if n else None  # noqa: E731
    provenance.update(
        {
            "tiff": out_tiff.name,
            "geojson": geojson_path.name,
            "levels": [[width >> k, height >> k] for k in range(n_sub + 1)],
            "tumour_area_px": float(tumour.area),
            "tumour_fraction": float(tumour.area) / area,
            "tissue_fraction": float(tissue.area) / area,
            "tumour_mean_rgb": mean("tumour_rgb_sum", stats["tumour_px"]),
            "normal_tissue_mean_rgb": mean("normal_rgb_sum", stats["normal_px"]),
            "seconds": round(time.perf_counter() - t_start, 2),
            "tiff_bytes": out_tiff.stat().st_size,
        }
    )
    out_tiff.with_suffix(".provenance.json").write_text(json.dumps(provenance, indent=1, allow_nan=False))
    return provenance


# ---------------------------------------------------------------------------
# previews and datasets


def save_preview(tiff, geojson, out_png, max_side: int = 1024) -> Path:
    """A PNG of the slide's coarsest level ≤ ``max_side`` px with the tumour outlined (green) and tissue
    outlined (blue), for looking at a slide."""
    from PIL import Image, ImageDraw

    from data_tools.annotations import load_annotations
    from data_tools.slide_files.open import open_slide

    with open_slide(tiff) as reader:
        k = next(
            (i for i, lv in enumerate(reader.levels) if max(lv.width, lv.height) <= max_side), len(reader.levels) - 1
        )
        rgb, d = reader.read_level(k), reader.levels[k].downsample
    ann = load_annotations(geojson)
    image = Image.fromarray(rgb)
    draw = ImageDraw.Draw(image)
    for geom, colour in ((ann.tissue, (40, 90, 230)), (ann.tumour, (0, 200, 0))):
        for poly in shapely.get_parts(geom):
            for ring in (poly.exterior, *poly.interiors):
                draw.line([(x / d, y / d) for x, y in ring.coords], fill=colour, width=2)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    image.save(out_png)
    return out_png


def _views_over(mask: np.ndarray, view: int, threshold: float) -> int:
    """Grid-aligned ``view × view`` windows of ``mask`` whose tumour fraction is ≥ ``threshold``."""
    h, w = mask.shape[0] // view * view, mask.shape[1] // view * view
    frac = mask[:h, :w].reshape(h // view, view, w // view, view).mean(axis=(1, 3))
    return int((frac >= threshold).sum())


def _split(names: list[str], groups: list[str], test_fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """Train/test by slide, keeping all slides made from the same tumour file on one side."""
    unique = list(dict.fromkeys(groups))
    order = [unique[i] for i in _rng(seed, 21).permutation(len(unique))]
    n_test = 0 if len(names) < 2 or test_fraction <= 0 else max(1, round(test_fraction * len(names)))
    test_groups: set[str] = set()
    for g in order:
        if sum(gr in test_groups for gr in groups) >= n_test:
            break
        if len(test_groups) + 1 >= len(unique):  # keep at least one group for training
            break
        test_groups.add(g)
    test = [n for n, g in zip(names, groups) if g in test_groups]
    return [n for n in names if n not in test], test


def make_dataset(
    out_dir,
    n_slides: int = 8,
    size=(4096, 4096),
    seed: int = 0,
    test_fraction: float = 0.25,
    tile_size: int = 128,
    level_sets=(3, 5, 7),
    tumour_xmls=None,
    tissue: str = "synthetic",
    progress: bool = True,
    previews: bool = True,
    negatives: int = 0,
) -> dict:
    """Make ``n_slides`` semi-synthetic slides and their bundles under ``out_dir``.

    One slide per tumour file (default: the bundled CAMELYON16 files, :func:`tumour_files`); when more
    slides than files are asked for, the files are cycled with other seeds and orientations (90° turns,
    mirroring). ``tissue="synthetic"`` (default) puts the tumour in a smooth random blob of tissue;
    ``"camelyon16"`` pairs slide ``i`` with the ``i``-th bundled tissue outline (:func:`tissue_files`).
    Those outlines belong to other CAMELYON16 slides than the tumour files, so they are fitted to the
    canvas on their own and joined with a rim around the tumour: real shapes, but the tumour visibly
    does not belong to them (a pink rim where it sticks out), hence not the default.
    Layout: ``slides/<name>.tif`` (+ ``.geojson``, ``.provenance.json``), ``bundles/<name>/`` (built
    by :func:`data_tools.bundle.build_bundle`), ``previews/<name>.png`` and ``dataset.json`` with the
    train/test split by slide (all slides of one tumour file on the same side), per-slide provenance
    and checks (tumour fraction, finest-level views ≥ 50 % tumour, mean colours). Returns that dict.
    ``negatives``: that many more slides without tumour (``negative=True``; tissue placed by the
    tumour files in turn, named ``synth_NN_normal_<file>``), for slide-level diagnosis.
    """
    from data_tools.bundle import build_bundle, load_bundle

    if isinstance(size, int):
        size = (size, size)
    if tissue not in ("camelyon16", "synthetic"):
        raise ValueError(f"tissue must be 'camelyon16' or 'synthetic', got {tissue!r}")
    out_dir = Path(out_dir)
    files = [Path(f) for f in (tumour_xmls or tumour_files())]
    if not files:
        raise ValueError("no tumour annotation files")
    tissues = tissue_files()
    slides = []
    t0 = time.perf_counter()
    for i in tqdm(range(n_slides + negatives), desc="semi-synthetic slides", unit="slide", disable=not progress):
        negative = i >= n_slides
        src, cycle = files[i % len(files)], i // len(files)
        orientation = (cycle * 5) % 8  # 0, then mirrored-90, 2 (180), ...: a different view of the same geometry
        slide_seed = int(seed) * 1000 + i
        name = f"synth_{i:02d}_{'normal_' if negative else ''}{src.stem}" + (f"_o{orientation}" if orientation else "")
        tiff = out_dir / "slides" / f"{name}.tif"
        tissue_xml = tissues[i % len(tissues)] if tissue == "camelyon16" and tissues else None
        prov = make_semisynthetic_slide(
            src,
            tiff,
            size=size,
            seed=slide_seed,
            tissue_xml=tissue_xml,
            orientation=orientation,
            progress=False,
            negative=negative,
        )
        t_b = time.perf_counter()
        bundle = build_bundle(
            tiff,
            out_dir / "bundles" / name,
            annotations_path=tiff.with_suffix(".geojson"),
            level_sets=level_sets,
            tile_size=tile_size,
            overwrite=True,
            progress=False,
            stated_scale_checked=False,  # its µm/px is a geometry scale: over 100 on a small canvas
        )
        bundle_seconds = time.perf_counter() - t_b
        b = load_bundle(bundle, verify=False, levels=[0])
        finest = b.tumour[0]
        if previews:
            save_preview(tiff, tiff.with_suffix(".geojson"), out_dir / "previews" / f"{name}.png")
        slides.append(
            {
                "name": name,
                "bundle": f"bundles/{name}",
                "tiff": f"slides/{tiff.name}",
                "geojson": f"slides/{tiff.with_suffix('.geojson').name}",
                "provenance": f"slides/{tiff.with_suffix('.provenance.json').name}",
                "summary": prov["summary"],
                "tumour_source": prov["tumour_source"]["file"],
                "tissue_source": prov["tissue_source"].get("file", "synthetic blob"),
                "seed": slide_seed,
                "orientation": orientation,
                "mpp": prov["mpp"],
                "tumour_fraction": round(prov["tumour_fraction"], 5),
                "finest_tumour_fraction": round(float(finest.mean()), 5),
                "finest_views": int((finest.shape[0] // tile_size) * (finest.shape[1] // tile_size)),
                "finest_views_ge50": _views_over(finest, tile_size, 0.5),
                "tumour_mean_rgb": prov["tumour_mean_rgb"],
                "normal_tissue_mean_rgb": prov["normal_tissue_mean_rgb"],
                "seconds_slide": prov["seconds"],
                "seconds_bundle": round(bundle_seconds, 2),
                "tiff_bytes": prov["tiff_bytes"],
            }
        )
    train, test = _split([s["name"] for s in slides], [s["tumour_source"] for s in slides], test_fraction, seed)
    by_name = {s["name"]: s for s in slides}
    dataset = {
        "kind": "histojax semi-synthetic slide set",
        "provenance": "pixels synthetic, geometry real CAMELYON16: " + PIXELS_NOTE,
        "licence": LICENCE_NOTE,
        "canvas": list(size),
        "seed": int(seed),
        "tile_size": tile_size,
        "level_sets": list(level_sets),
        "tissue": tissue,
        "test_fraction": test_fraction,
        "split_rule": "by slide; all slides made from the same tumour annotation file are on the same side",
        "train": [by_name[n]["bundle"] for n in train],
        "test": [by_name[n]["bundle"] for n in test],
        "slides": slides,
        "seconds": round(time.perf_counter() - t0, 2),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "dataset.json").write_text(json.dumps(dataset, indent=1, allow_nan=False))
    return dataset
