"""CAMELYON16 polygons in NCRF's JSON form (baidu-research/NCRF ``jsons/train``; Apache-2.0 conversion
of the CC0 CAMELYON16 ground truth), read from a folder of ``*.json`` files or a ``.tar.gz`` of them.

Each file is ``{"positive": [{"name", "vertices": [[x, y], ...]}], "negative": [...]}`` in integer
level-0 px of the original slide (0.243 µm/px). On ``Tumor_*`` slides ``positive`` is tumour and
``negative`` exclusion holes; on ``Normal_*`` slides only ``negative`` polygons exist: machine-traced
tissue outlines (every vertex on a 128-px grid of level 0), which :mod:`data_tools.datasets.c16.dataset` uses as tissue.
"""

from __future__ import annotations

import json
import tarfile
from dataclasses import dataclass
from pathlib import Path

import shapely
from shapely.geometry import MultiPolygon, Polygon

from data_tools.errors import AnnotationError

SHIPPED_DIR = Path(__file__).resolve().parent / "camelyon16" / "ncrf"
"""A handful of NCRF files shipped with the package (3 tumour, 3 normal slides) for the small variant."""


@dataclass(frozen=True)
class NcrfSlide:
    """One slide's polygons in level-0 px: ``positive`` / ``negative`` unions (MultiPolygon)."""

    name: str  # e.g. "Tumor_001"
    positive: MultiPolygon
    negative: MultiPolygon
    source: str  # file name the polygons came from
    sha256: str

    @property
    def is_tumour_slide(self) -> bool:
        return self.name.lower().startswith("tumor")


def _union(polys) -> MultiPolygon:
    valid = [shapely.make_valid(p) for p in polys]
    parts = (
        [p for p in shapely.get_parts(shapely.union_all(valid)) if p.geom_type == "Polygon" and p.area > 0]
        if valid
        else []
    )
    return MultiPolygon(parts) if parts else MultiPolygon()


def parse_ncrf(name: str, raw: bytes, where) -> NcrfSlide:
    """Parse one NCRF JSON document (``raw`` bytes) into an :class:`NcrfSlide`; errors name ``where``."""
    from data_tools.bundle_files.format import text_digest

    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise AnnotationError(where, f"not valid NCRF JSON ({e})") from None
    if not isinstance(data, dict) or not set(data) <= {"positive", "negative"}:
        raise AnnotationError(where, "NCRF JSON must be an object with 'positive' and/or 'negative' lists")
    groups = {}
    for key in ("positive", "negative"):
        items = data.get(key, [])
        if not isinstance(items, list):
            raise AnnotationError(where, f"'{key}' must be a list of polygons")
        polys = []
        for i, item in enumerate(items):
            try:
                verts = [(float(x), float(y)) for x, y in item["vertices"]]
            except (KeyError, TypeError, ValueError):
                raise AnnotationError(where, f"{key}[{i}] has no list of [x, y] vertices") from None
            if len(verts) >= 3:
                polys.append(Polygon(verts))
        groups[key] = _union(polys)
    return NcrfSlide(
        name=name,
        positive=groups["positive"],
        negative=groups["negative"],
        source=f"{name}.json",
        sha256=text_digest(raw, 64),
    )


def read_ncrf(source, names=None) -> dict[str, NcrfSlide]:
    """All (or the ``names``) NCRF slides of a folder of ``NAME.json`` files or a ``.tar.gz`` holding
    them (any sub-folder), keyed by name, sorted. A missing source or name raises ``AnnotationError``."""
    source = Path(source)
    wanted = None if names is None else set(names)
    found: dict[str, NcrfSlide] = {}
    if source.is_dir():
        for f in sorted(source.rglob("*.json")):
            if wanted is None or f.stem in wanted:
                found[f.stem] = parse_ncrf(f.stem, f.read_bytes(), f)
    elif source.is_file():
        try:
            with tarfile.open(source, "r:*") as tar:
                for m in tar:
                    stem = Path(m.name).stem
                    if m.isfile() and m.name.endswith(".json") and (wanted is None or stem in wanted):
                        found[stem] = parse_ncrf(stem, tar.extractfile(m).read(), f"{source}:{m.name}")
        except (tarfile.TarError, OSError, EOFError) as e:
            raise AnnotationError(source, f"not a readable tar archive of NCRF JSON files ({e})") from None
    else:
        raise AnnotationError(source, "no such folder or archive of NCRF JSON files")
    if not found:
        raise AnnotationError(source, "holds no NCRF *.json files (expected Tumor_NNN.json / Normal_NNN.json)")
    if wanted is not None and wanted - set(found):
        raise AnnotationError(source, f"lacks {sorted(wanted - set(found))}")
    return dict(sorted(found.items()))


__all__ = ["NcrfSlide", "SHIPPED_DIR", "parse_ncrf", "read_ncrf"]
