"""Where everything goes on one true-scale CAMELYON16 slide (geometry only, no pixels).

Coordinates: the output slide's level-0 px are CAMELYON16 level-0 px (0.243 µm/px) divided by one
``downsample`` for the whole set; nothing is rescaled per slide, so every tumour keeps its true size
relative to the tissue and to the view.

* **Normal slides** (``Normal_NNN``): tissue = NCRF's ``negative`` polygons (machine-traced tissue
  outlines, vertices on a 128-px grid of level 0), no tumour.
* **Tumour slides with their own tissue outline** (tumor_001, 013, 021, 031, 051, 092: the pathml-tutorial
  tissue annotations shipped in ``data_tools/camelyon16``): that outline, in the same frame, joined with
  the tumour.
* **Other tumour slides**: no tissue outline exists, so the tissue is *borrowed*: the tissue outline of
  a donor normal slide, mirrored left-right, with the tumour (``positive`` minus the ``negative`` holes,
  as one rigid group, never rescaled) translated so its bounding-box centre lies on the donor's most
  interior tissue point; the tissue is joined with the tumour grown by ``TUMOUR_RIM`` level-0 px so the
  tumour always lies on tissue.

The canvas is the tissue's bounding box grown by ``MARGIN`` level-0 px on every side.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import shapely
from shapely import affinity
from shapely.geometry import MultiPolygon

from data_tools.ncrf import NcrfSlide

C16_MPP = 0.243  # µm per CAMELYON16 level-0 px
MARGIN = 2048  # level-0 px of glass around the tissue's bounding box
TUMOUR_RIM = 512  # level-0 px of tissue kept around a placed tumour
SIMPLIFY = 0.25  # simplification tolerance in output px (sub-pixel, keeps topology)
OWN_TISSUE = {
    "Tumor_001": "dtd_tumor_001.xml",
    "Tumor_013": "dtd_tumor_013.xml",
    "Tumor_021": "bench_tumor_021.xml",
    "Tumor_031": "bench_tumor_031.xml",
    "Tumor_051": "bench_tumor_051.xml",
    "Tumor_092": "bench_tumor_092.xml",
}


@dataclass(frozen=True)
class SlideLayout:
    """One slide's geometry in output px (level 0 of the output slide): ``tumour`` and ``tissue``
    MultiPolygons, ``size = (W, H)``, and how it was made (``provenance``)."""

    name: str
    tumour: MultiPolygon
    tissue: MultiPolygon
    size: tuple[int, int]
    downsample: float
    provenance: dict = field(default_factory=dict)

    @property
    def mpp(self) -> float:
        return C16_MPP * self.downsample


def _multi(geom) -> MultiPolygon:
    parts = [p for p in shapely.get_parts(shapely.make_valid(geom)) if p.geom_type == "Polygon" and p.area > 0]
    if not parts:
        return MultiPolygon()
    merged = shapely.union_all(parts)
    return MultiPolygon([p for p in shapely.get_parts(merged) if p.geom_type == "Polygon"])


def own_tissue_outline(name: str):
    """The tissue outline (level-0 px, same frame) of a tumour slide that has one shipped, else None."""
    from data_tools.annotations import load_annotations
    from data_tools.datasets.synth.dataset import CAMELYON16_DIR

    file = OWN_TISSUE.get(name)
    if file is None or not (CAMELYON16_DIR / file).is_file():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tissue = load_annotations(CAMELYON16_DIR / file).tissue
    return None if tissue.is_empty else (tissue, file)


def interior_point(tissue) -> tuple[float, float]:
    """The most interior point of the largest tissue piece (pole of inaccessibility), level-0 px."""
    from shapely.ops import polylabel

    largest = max(shapely.get_parts(tissue), key=lambda p: p.area)
    p = polylabel(largest, tolerance=256.0)
    return float(p.x), float(p.y)


def layout(slide: NcrfSlide, downsample: float, donor: NcrfSlide | None = None) -> SlideLayout:
    """The geometry of ``slide`` at ``downsample`` (output px = level-0 px / downsample), see the module
    doc. A tumour slide without its own tissue outline needs ``donor`` (a normal slide)."""
    tumour0 = _multi(shapely.difference(slide.positive, slide.negative)) if slide.is_tumour_slide else MultiPolygon()
    prov: dict = {
        "slide": slide.name,
        "polygons": slide.source,
        "polygons_sha256": slide.sha256,
        "downsample_from_camelyon16_level0": downsample,
    }
    if not slide.is_tumour_slide:
        tissue0 = slide.negative
        prov["tissue"] = "the slide's own NCRF 'negative' polygons (machine-traced tissue outlines)"
    else:
        own = own_tissue_outline(slide.name)
        if own is not None:
            tissue0 = _multi(shapely.union(own[0], tumour0.buffer(TUMOUR_RIM, quad_segs=4)))
            prov["tissue"] = f"the slide's own tissue outline ({own[1]}, pathml-tutorial), joined with the tumour"
        else:
            if donor is None:
                raise ValueError(f"{slide.name} has no tissue outline of its own: give a donor normal slide")
            tis = affinity.scale(donor.negative, -1.0, 1.0, origin=(0, 0))  # mirrored left-right
            cx, cy = interior_point(tis)
            minx, miny, maxx, maxy = tumour0.bounds
            moved = affinity.translate(tumour0, cx - (minx + maxx) / 2, cy - (miny + maxy) / 2)
            tumour0 = _multi(moved)
            tissue0 = _multi(shapely.union(tis, tumour0.buffer(TUMOUR_RIM, quad_segs=4)))
            prov["tissue"] = (
                f"BORROWED: the tissue outline of {donor.name} (NCRF 'negative' polygons), mirrored "
                "left-right; the tumour, unscaled, centred on its most interior point; joined with "
                f"the tumour grown by {TUMOUR_RIM} level-0 px"
            )
            prov["tissue_donor"] = donor.name
            prov["tumour_translation_level0"] = [cx - (minx + maxx) / 2, cy - (miny + maxy) / 2]
    if tissue0.is_empty:
        raise ValueError(f"{slide.name}: no tissue polygons")
    minx, miny, maxx, maxy = tissue0.bounds
    x0, y0 = math.floor(minx) - MARGIN, math.floor(miny) - MARGIN
    size = (math.ceil((maxx + MARGIN - x0) / downsample), math.ceil((maxy + MARGIN - y0) / downsample))
    g = 1.0 / downsample

    def out(geom):
        moved = affinity.affine_transform(geom, [g, 0, 0, g, -x0 * g, -y0 * g])
        return _multi(shapely.simplify(moved, SIMPLIFY, preserve_topology=True)) if not moved.is_empty else moved

    tumour, tissue = out(tumour0), out(tissue0)
    prov.update(
        {
            "canvas_origin_level0": [x0, y0],
            "canvas": list(size),
            "tumour_area_level0_px2": float(tumour0.area),
            "tissue_area_level0_px2": float(tissue0.area),
            "mpp": C16_MPP * downsample,
        }
    )
    return SlideLayout(
        name=slide.name,
        tumour=_multi(tumour) if not tumour.is_empty else MultiPolygon(),
        tissue=tissue,
        size=size,
        downsample=float(downsample),
        provenance=prov,
    )


def donor_for(tumour_name: str, tumours: list[str], normals: list[str]) -> str:
    """The normal slide lending its tissue to a tumour slide without its own outline: the ``j``-th of
    ``tumours`` (all tumour slides found, sorted) takes ``normals[-(1 + j % len(normals))]``, from the end
    of the list (with CAMELYON16's 100 tumour and 139 normal slides: Tumor_001 → Normal_139, …,
    Tumor_100 → Normal_040, each donor used once)."""
    j = sorted(tumours).index(tumour_name)
    return normals[-(1 + j % len(normals))]


__all__ = [
    "C16_MPP",
    "MARGIN",
    "OWN_TISSUE",
    "SlideLayout",
    "donor_for",
    "interior_point",
    "layout",
    "own_tissue_outline",
]
