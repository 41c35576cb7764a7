"""Read tumour annotations (ASAP XML, GeoJSON) into shapely geometry.

All coordinates are LEVEL-0 PIXELS of the slide: x grows to the right, y grows
down, origin at the top-left corner of the level-0 image. Nothing here rescales.

Each polygon carries one of four labels:

* ``tumour``    - rewarded region;
* ``exclusion`` - hole cut out of the tumour (e.g. CAMELYON16 group ``negative``
  or ``_2``: normal tissue inside a metastasis);
* ``tissue``    - tissue outline (kept, not used for reward);
* ``ignore``    - read and dropped (background, artefacts, ...).

A group/class name not in the label map gives the label ``unknown:<name>``; such
polygons are dropped by :func:`load_annotations` with one warning per file.
All bad input raises :class:`~data_tools.errors.AnnotationError` naming the file.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass
from xml.etree.ElementTree import ParseError

import defusedxml
import defusedxml.ElementTree as SafeET
import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box, mapping

from data_tools.errors import AnnotationError, HistojaxDataError

__all__ = [
    "DEFAULT_LABEL_MAP",
    "LABELS",
    "MAX_ANNOTATION_BYTES",
    "MAX_COORDINATE",
    "MAX_FILE_REPAIR_CROSSINGS",
    "MAX_REPAIR_CROSSINGS",
    "Annotations",
    "annotations_to_geojson",
    "load_annotations",
    "parse_asap_xml",
    "parse_geojson",
]

LABELS = ("tumour", "exclusion", "tissue", "ignore")
MAX_ANNOTATION_BYTES = 512 * 1024 * 1024  # refuse larger annotation files
MAX_COORDINATE = 2.0**31  # level-0 px: coordinates beyond ±2**31 are refused (no slide is that large)
MAX_REPAIR_CROSSINGS = 50_000  # an invalid polygon whose edges cross more often than this is refused
MAX_FILE_REPAIR_CROSSINGS = 100_000  # edge crossings of all invalid polygons of one file; more is refused

DEFAULT_LABEL_MAP: dict[str, str] = {
    **{k: "tumour" for k in ("metastasis", "metastases", "tumor", "tumour", "_0", "_1", "carcinoma")},
    **{k: "exclusion" for k in ("negative", "_2", "exclusion")},
    "tissue": "tissue",
    **{k: "ignore" for k in ("background", "artifact", "artefact", "trash", "ignore")},
}

_POLYGON_TYPES = {"polygon", "spline", "rectangle"}
_POINT_TYPES = {"pointset", "dot", "point", "measurement"}  # ASAP types without area: skipped (warned if tumour)
_AREA_LABELS = ("tumour", "exclusion")  # labels whose lost geometry changes the reward: every loss is warned
_GEOMETRY_TYPES = {
    "Polygon",
    "MultiPolygon",
    "GeometryCollection",
    "Point",
    "MultiPoint",
    "LineString",
    "MultiLineString",
}
_EMPTY = MultiPolygon()


@dataclass(frozen=True)
class Annotations:
    """Labelled annotation geometry of one slide, in level-0 pixels (x right, y down).

    ``tumour`` is the union of tumour polygons minus the union of exclusion
    polygons; ``exclusion`` and ``tissue`` are unions of their polygons. All three
    are valid (possibly empty) MultiPolygons. ``n_polygons`` counts the polygons
    in the file per label (``tumour``, ``exclusion``, ``tissue``, ``ignore``,
    ``unknown``) before any union or clipping: one per ASAP annotation or
    GeoJSON polygon, however many pieces a repair splits it into; zero-area
    polygons (dropped) are not counted.
    """

    tumour: MultiPolygon
    exclusion: MultiPolygon
    tissue: MultiPolygon
    n_polygons: dict[str, int]
    unknown_groups: tuple[str, ...]
    source: str

    def bounds(self) -> tuple[float, float, float, float]:
        """(min_x, min_y, max_x, max_y) of the tumour in level-0 pixels; ValueError if there is no tumour."""
        if self.tumour.is_empty:
            raise ValueError(f"{self.source}: no tumour geometry, bounds undefined")
        return tuple(float(v) for v in self.tumour.bounds)


def _resolve_label_map(label_map: dict[str, str] | None) -> dict[str, str]:
    merged = {label: label for label in LABELS}
    merged.update(DEFAULT_LABEL_MAP)
    for key, value in (label_map or {}).items():
        if value not in LABELS:
            raise ValueError(f"label_map[{key!r}] = {value!r}; expected one of {LABELS}")
        merged[str(key).strip().lower()] = value
    return merged


def _map_label(name: str, lmap: dict[str, str]) -> str:
    return lmap.get(name.strip().lower(), f"unknown:{name}")


def _check_size(path) -> int:
    """Size of the file at ``path`` in bytes; AnnotationError if it cannot be read or is over the limit."""
    try:
        size = os.path.getsize(path)
    except OSError as e:
        raise AnnotationError(path, f"cannot read annotation file ({e.strerror or e})") from e
    if size > MAX_ANNOTATION_BYTES:
        raise AnnotationError(path, f"file is {size} bytes, over the {MAX_ANNOTATION_BYTES}-byte limit")
    return size


def _blank(path, limit: int = 1 << 20) -> bool:
    """Whether the file holds only white space (checked on files up to ``limit`` bytes)."""
    try:
        with open(path, "rb") as f:
            head = f.read(limit + 1)
    except OSError:
        return False
    return len(head) <= limit and not head.strip()


def _read_bytes(path) -> bytes:
    size = _check_size(path)
    try:
        with open(path, "rb") as f:
            data = f.read(min(size, MAX_ANNOTATION_BYTES) + 1)  # not a 512 MiB buffer for a small file
    except OSError as e:
        raise AnnotationError(path, f"cannot read annotation file ({e.strerror or e})") from e
    if len(data) > MAX_ANNOTATION_BYTES:
        raise AnnotationError(path, f"file is larger than the {MAX_ANNOTATION_BYTES}-byte limit")
    if not data.strip():
        raise AnnotationError(path, "empty file")
    return data


def _short(v, limit: int = 40) -> str:
    """``repr`` of a coordinate cut to ``limit`` characters (a JSON integer may have thousands of digits)."""
    text = f"{v:g}" if isinstance(v, float) else repr(v)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _polygon(path, what: str, shell, holes, notes: dict[str, list[str]]) -> list[Polygon]:
    """Check raw rings and build valid polygon piece(s); invalid ones are repaired, zero-area ones dropped.

    Repairs and drops are recorded in ``notes`` and reported in one warning per file by :func:`_finish`.
    """
    rings = []
    for ring in (shell, *holes):
        if not isinstance(ring, (list, tuple)):
            raise AnnotationError(path, f"{what}: a ring is not a list of coordinates")
        pts = []
        for p in ring:
            if not isinstance(p, (list, tuple)) or len(p) < 2:
                raise AnnotationError(path, f"{what}: coordinate {p!r} is not an (x, y) pair")
            x, y = p[0], p[1]
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (x, y)):
                raise AnnotationError(path, f"{what}: non-numeric coordinate {_short(p)}")
            if any(isinstance(v, float) and not math.isfinite(v) for v in (x, y)):
                raise AnnotationError(path, f"{what}: non-finite coordinate ({x}, {y})")
            if abs(x) > MAX_COORDINATE or abs(y) > MAX_COORDINATE:  # exact for ints of any size (JSON 10**400)
                raise AnnotationError(
                    path,
                    f"{what}: coordinate ({_short(x)}, {_short(y)}) is beyond ±2^31 "
                    "level-0 px, outside any slide (wrong units?)",
                )
            pts.append((float(x), float(y)))
        if len(pts) > 1 and pts[0] == pts[-1]:
            pts.pop()
        if len(pts) < 3:
            raise AnnotationError(path, f"{what}: a ring has {len(pts)} vertices, at least 3 needed")
        rings.append(pts)
    poly = Polygon(rings[0], rings[1:])
    pieces = [poly] if poly.is_valid else _repair(path, what, poly, rings, notes)
    pieces = [g for g in pieces if g.area > 0]
    if not pieces:
        notes["dropped"].append(what)
    elif not poly.is_valid:
        notes["repaired"].append(what)
    return pieces


def _edge_crossings(rings: list[list[tuple[float, float]]], limit: int) -> int:
    """Number of pairs of edges of ``rings`` (vertex lists, not closed) that meet (edges sharing a vertex
    of the ring excepted), counted up to just past ``limit``: any result > ``limit`` means "more". Bounded
    work: edges are queried against an STR tree in chunks that grow while they find little and stop as
    soon as ``limit`` is passed."""
    starts = np.concatenate([np.asarray(r, dtype=np.float64) for r in rings])
    ends = np.concatenate([np.roll(np.asarray(r, dtype=np.float64), -1, axis=0) for r in rings])
    ring_of = np.concatenate([np.full(len(r), i) for i, r in enumerate(rings)])
    pos = np.concatenate([np.arange(len(r)) for r in rings])
    size = np.concatenate([np.full(len(r), len(r)) for r in rings])
    edges = shapely.linestrings(np.stack([starts, ends], axis=1))
    tree = shapely.STRtree(edges)
    count, first, chunk = 0, 0, 1
    while first < len(edges):
        rows = np.arange(first, min(len(edges), first + chunk))
        a, b = tree.query(edges[rows], predicate="intersects")
        a = rows[a]
        gap = np.abs(pos[a] - pos[b])
        neighbours = (ring_of[a] == ring_of[b]) & ((gap <= 1) | (gap == size[a] - 1))
        count += int(np.count_nonzero((b > a) & ~neighbours))
        if count > limit:
            return count
        first += chunk
        chunk = chunk * 2 if len(a) <= 8 * len(rows) else max(1, chunk // 2)
    return count


def _repair(path, what: str, poly: Polygon, rings, notes: dict) -> list[Polygon]:
    """Valid pieces of an invalid polygon: ``make_valid(method="structure")`` (the area its rings enclose,
    holes subtracted), whose time grows with the edge crossings. More than MAX_REPAIR_CROSSINGS in one
    polygon, or more than MAX_FILE_REPAIR_CROSSINGS summed over the file's invalid polygons, is refused."""
    spent = notes.setdefault("crossings", 0)
    left = MAX_FILE_REPAIR_CROSSINGS - spent
    count = _edge_crossings(rings, min(MAX_REPAIR_CROSSINGS, left))
    if count > MAX_REPAIR_CROSSINGS:
        raise AnnotationError(
            path,
            f"{what}: {sum(map(len, rings))} vertices whose edges cross each other more "
            f"than {MAX_REPAIR_CROSSINGS:,} times; too tangled to repair, redraw or simplify it",
        )
    if count > left:
        raise AnnotationError(
            path,
            f"{what}: the invalid polygons up to this one cross their own edges more than "
            f"{MAX_FILE_REPAIR_CROSSINGS:,} times in all ({len(notes['repaired'])} repaired "
            "before it); too tangled to repair in one file, redraw or simplify them",
        )
    notes["crossings"] = spent + count
    return _polygonal_parts(shapely.make_valid(poly, method="structure", keep_collapsed=False))


_NOTES = (
    ("repaired", "invalid (self-intersecting) polygon(s) repaired with make_valid(method='structure')"),
    ("dropped", "zero-area polygon(s) dropped"),
    ("untyped", "annotation(s) with no or an unknown Type read as polygons"),
    ("closed", "closed LineString(s) read as polygons"),
    ("skipped", "tumour / exclusion annotation(s) without area (points, open lines, no geometry) skipped"),
)


def _new_notes() -> dict:
    return {key: [] for key, _ in _NOTES}


def _finish(path, items: list[tuple[str, list[Polygon]]], notes: dict[str, list[str]]):
    """Warn once per file and kind about repaired / dropped / reinterpreted / skipped polygons; refuse a file
    without any polygon."""
    for key, problem in _NOTES:
        if notes[key]:
            names = ", ".join(notes[key][:10]) + (", ..." if len(notes[key]) > 10 else "")
            warnings.warn(f"{path}: {len(notes[key])} {problem}: {names}", stacklevel=3)
    items = [(label, pieces) for label, pieces in items if pieces]
    if not items:
        raise AnnotationError(path, "no polygons: nothing to reward")
    return items


def _flatten(items: list[tuple[str, list[Polygon]]]) -> list[tuple[str, Polygon]]:
    return [(label, p) for label, pieces in items for p in pieces]


def _polygonal_parts(geom) -> list[Polygon]:
    if isinstance(geom, Polygon):
        return [] if geom.is_empty else [geom]
    if hasattr(geom, "geoms"):  # MultiPolygon, GeometryCollection
        return [p for g in geom.geoms for p in _polygonal_parts(g)]
    return []


def parse_asap_xml(path, label_map: dict[str, str] | None = None) -> list[tuple[str, Polygon]]:
    """Read an ASAP XML file into ``(label, polygon)`` pairs, coordinates in level-0 pixels (x right, y down).

    Layout: ``<ASAP_Annotations><Annotations><Annotation Name Type PartOfGroup>
    <Coordinates><Coordinate Order X Y/>``. Vertices are sorted by ``Order``.
    Types ``Polygon``, ``Rectangle`` and ``Spline`` become polygons; a Spline's
    control vertices are used as the polygon's vertices (ASAP's smooth curve
    through them is not reproduced). An annotation without a ``Type``, or with
    one ASAP does not write (``Freehand``), is read as a polygon with a warning
    (skipped with a warning if it has fewer than 3 distinct vertices);
    ``PointSet``/``Dot``/``Measurement`` have no area and are skipped, with one
    warning counting them if they are labelled tumour or exclusion. The label is ``PartOfGroup`` mapped through ``label_map`` (on top of
    DEFAULT_LABEL_MAP, case-insensitive), else ``unknown:<group>``; a missing
    group is the group ``None``. The XML is parsed with defusedxml: DTDs and
    entities are refused. Raises AnnotationError for unsafe, malformed or
    polygon-free files and for bad vertices.
    """
    return _flatten(_read_asap_xml(path, label_map))


def _read_asap_xml(path, label_map) -> list[tuple[str, list[Polygon]]]:
    """One (label, valid pieces) item per ASAP polygon annotation.

    Streamed with defusedxml's ``iterparse`` (DTDs, entities and external references refused): each
    ``<Annotation>`` is turned into polygons and cleared as soon as it ends, so the memory held is the
    polygons read, not the XML tree of the whole file."""
    lmap = _resolve_label_map(label_map)
    _check_size(path)
    items, notes = [], _new_notes()
    stack: list = []
    index = 0
    try:
        with open(path, "rb") as f:
            for event, elem in SafeET.iterparse(
                f, events=("start", "end"), forbid_dtd=True, forbid_entities=True, forbid_external=True
            ):
                if event == "start":
                    if not stack and elem.tag != "ASAP_Annotations":
                        raise AnnotationError(path, f"not ASAP XML (root element <{elem.tag}>)")
                    stack.append(elem)
                    continue
                stack.pop()
                depth = len(stack)
                if depth == 2 and elem.tag == "Annotation" and stack[1].tag == "Annotations":
                    item = _asap_annotation(path, index, elem, lmap, notes)
                    if item is not None:
                        items.append(item)
                    index += 1
                    stack[1].remove(elem)  # free the annotation's coordinates as soon as they are read
                elif depth == 1:
                    elem.clear()  # <Annotations>, <AnnotationGroups>, ...: children already handled or unused
    except OSError as e:
        raise AnnotationError(path, f"cannot read annotation file ({e.strerror or e})") from e
    except defusedxml.DefusedXmlException as e:
        raise AnnotationError(path, f"unsafe XML refused ({type(e).__name__})") from e
    except ParseError as e:
        if index == 0 and not items and _blank(path):
            raise AnnotationError(path, "empty file") from e
        raise AnnotationError(path, f"malformed XML ({e})") from e
    return _finish(path, items, notes)


def _asap_annotation(path, i: int, ann, lmap, notes) -> tuple[str, list[Polygon]] | None:
    """(label, valid pieces) of one ``<Annotation>`` element, or None for one without area (noted)."""
    what = f"annotation {i} ({ann.get('Name', '?')!r})"
    kind = (ann.get("Type") or "").strip().lower()
    label = _map_label(ann.get("PartOfGroup") or "None", lmap)
    if kind in _POINT_TYPES:
        if label in _AREA_LABELS:
            notes["skipped"].append(f"{what} ({ann.get('Type')})")
        return None
    coords = []
    for j, c in enumerate(ann.iterfind("./Coordinates/Coordinate")):
        try:
            order = int(c.get("Order", j))
            xy = (float(c.get("X")), float(c.get("Y")))
        except (TypeError, ValueError) as e:
            raise AnnotationError(path, f"{what}: non-numeric coordinate {dict(c.attrib)}") from e
        coords.append((order, xy))
    if kind not in _POLYGON_TYPES:  # no Type, or one ASAP does not write (Freehand, ...): read as a polygon
        if len({xy for _, xy in coords}) < 3:
            if label in _AREA_LABELS:
                notes["skipped"].append(f"{what} (Type {ann.get('Type')!r}, {len(coords)} vertices)")
            return None
        notes["untyped"].append(f"{what} (Type {ann.get('Type')!r})")
    if len({order for order, _ in coords}) != len(coords):
        warnings.warn(
            f"{path}: {what}: duplicate Order values; vertices with equal Order kept in file order", stacklevel=4
        )
    shell = [xy for _, xy in sorted(coords, key=lambda t: t[0])]  # stable: ties stay in file order
    if kind == "rectangle" and len(shell) == 2:
        (x0, y0), (x1, y1) = shell
        shell = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return label, _polygon(path, what, shell, (), notes)


def _geojson_label(props: dict, lmap: dict[str, str], default_label: str | None) -> str:
    if isinstance(props.get("label"), str):
        return _map_label(props["label"], lmap)
    cls = props.get("classification")
    cls_name = cls.get("name") if isinstance(cls, dict) else cls
    if isinstance(cls_name, str) and cls_name.strip():
        return _map_label(cls_name, lmap)
    name = props.get("name")
    if isinstance(name, str) and name.strip().lower() in lmap:
        return lmap[name.strip().lower()]
    if default_label is not None:
        return default_label
    return f"unknown:{name if isinstance(name, str) else 'unclassified'}"


def _features(path, doc) -> list[dict]:
    if not isinstance(doc, dict):
        raise AnnotationError(path, "GeoJSON must be an object")
    kind = doc.get("type")
    if kind == "FeatureCollection":
        feats = doc.get("features")
        if not isinstance(feats, list):
            raise AnnotationError(path, "FeatureCollection without a 'features' list")
        return feats
    if kind == "Feature":
        return [doc]
    if isinstance(kind, str) and kind in _GEOMETRY_TYPES:
        return [{"type": "Feature", "geometry": doc, "properties": {}}]
    raise AnnotationError(path, f"not GeoJSON (type {kind!r})")


def _geometry_polygons(geom, skipped: list[str], closed: list[str]) -> list[list]:
    """Polygon coordinate arrays ([shell, *holes]) in a GeoJSON geometry. A closed LineString (first
    position = last, at least 4) is a shell (its kind appended to ``closed``); the kinds of geometry
    without area (points, open lines, null, unknown types) are appended to ``skipped``."""
    if not isinstance(geom, dict):
        skipped.append("null geometry" if geom is None else "not a geometry")
        return []
    kind, coords = geom.get("type"), geom.get("coordinates")
    if kind == "Polygon":
        return [coords]
    if kind == "MultiPolygon":
        return list(coords) if isinstance(coords, list) else [coords]
    if kind == "GeometryCollection":
        members = geom.get("geometries")
        return [
            p for g in (members if isinstance(members, list) else []) for p in _geometry_polygons(g, skipped, closed)
        ]
    if kind in ("LineString", "MultiLineString"):
        lines = [coords] if kind == "LineString" else (coords if isinstance(coords, list) else [])
        out = []
        for line in lines:
            if isinstance(line, list) and len(line) >= 4 and line[0] == line[-1]:
                closed.append(kind)
                out.append([line])
            else:
                skipped.append(f"open {kind}")
        return out
    skipped.append(str(kind) if isinstance(kind, str) else "geometry without a type")
    return []


def parse_geojson(
    path, label_map: dict[str, str] | None = None, default_label: str | None = "tumour"
) -> list[tuple[str, Polygon]]:
    """Read GeoJSON into ``(label, polygon)`` pairs, coordinates in level-0 pixels (x right, y down).

    Accepts a FeatureCollection, a Feature or a bare geometry. Polygon and
    MultiPolygon (holes kept) are read, and a closed LineString (first position
    equal to the last) as a polygon, with a warning; points, open lines and
    ``null`` geometry are skipped, with one warning counting them if they are
    labelled tumour or exclusion. The label of a feature, first match wins:

    1. ``properties.label`` (what :func:`annotations_to_geojson` writes), mapped;
    2. ``properties.classification.name`` (QuPath class), mapped;
    3. ``properties.name`` if it is a key of the label map (e.g. ``"Tumor"``);
    4. ``default_label`` (``"tumour"``: an unclassified QuPath annotation is
       taken to outline tumour; pass ``None`` to make it ``unknown:<name>``).

    Names are mapped through ``label_map`` on top of DEFAULT_LABEL_MAP
    (case-insensitive); names not in it give ``unknown:<name>``.
    """
    return _flatten(_read_geojson(path, label_map, default_label))


def _read_geojson(path, label_map, default_label) -> list[tuple[str, list[Polygon]]]:
    """One (label, valid pieces) item per GeoJSON polygon (a MultiPolygon gives one item per member)."""
    if default_label is not None and default_label not in LABELS:
        raise ValueError(f"default_label {default_label!r}; expected one of {LABELS} or None")
    lmap = _resolve_label_map(label_map)
    data = _read_bytes(path)
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError) as e:
        raise AnnotationError(path, f"malformed JSON ({e})") from e
    items, notes = [], _new_notes()
    for i, feat in enumerate(_features(path, doc)):
        if not isinstance(feat, dict):
            raise AnnotationError(path, f"feature {i} is not an object")
        props = feat.get("properties")
        props = props if isinstance(props, dict) else {}  # GeoJSON allows null; anything else is ignored
        what = f"feature {i}" + (f" ({props['name']!r})" if isinstance(props.get("name"), str) else "")
        label = _geojson_label(props, lmap, default_label)
        skipped, closed = [], []
        polygons = _geometry_polygons(feat.get("geometry"), skipped, closed)
        if label in _AREA_LABELS:
            notes["skipped"].extend(f"{what} ({kind})" for kind in skipped)
        notes["closed"].extend(f"{what} ({kind})" for kind in closed)
        for rings in polygons:
            if not isinstance(rings, list) or not rings or not all(isinstance(r, list) for r in rings):
                raise AnnotationError(path, f"{what}: polygon coordinates are not a list of rings")
            items.append((label, _polygon(path, what, rings[0], rings[1:], notes)))
    return _finish(path, items, notes)


def _as_multipolygon(geom) -> MultiPolygon:
    """The polygonal parts of ``geom`` as one *valid* MultiPolygon. Parts picked out of a GeometryCollection may
    overlap or share an edge, which a MultiPolygon's parts may not: they are unioned then (and repaired once more
    if rounding still leaves the union invalid)."""
    parts = _polygonal_parts(geom)
    if not parts:
        return _EMPTY
    multi = MultiPolygon(parts)
    for repair in (
        lambda: _robust(shapely.union_all, parts),
        lambda: shapely.make_valid(multi),
        lambda: multi.buffer(0),
    ):
        if multi.is_valid:
            return multi
        try:
            parts = _polygonal_parts(repair())
        except shapely.errors.GEOSException:  # no valid union: the next repair
            continue
        multi = MultiPolygon(parts) if parts else _EMPTY
    return multi if multi.is_valid else _EMPTY


def _is_xml(path) -> bool:
    """ASAP XML or GeoJSON? By extension, else by the first non-blank byte."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in (".xml", ".geojson", ".json"):
        return ext == ".xml"
    try:
        with open(path, "rb") as f:
            first = f.read(4096).lstrip(b"\xef\xbb\xbf \t\r\n")[:1]
    except OSError as e:
        raise AnnotationError(path, f"cannot read annotation file ({e.strerror or e})") from e
    if first not in (b"<", b"{"):
        raise AnnotationError(path, "unknown annotation format (expected ASAP XML or GeoJSON)")
    return first == b"<"


def load_annotations(
    path,
    label_map: dict[str, str] | None = None,
    slide_size: tuple[int, int] | None = None,
    default_label: str | None = "tumour",
) -> Annotations:
    """Load an ASAP XML or GeoJSON annotation file; all geometry in level-0 pixels (x right, y down).

    The format is chosen by extension (``.xml`` / ``.geojson``, ``.json``), else
    by the first byte. ``label_map`` entries override/extend DEFAULT_LABEL_MAP
    (keys case-insensitive). ``default_label`` is the label of GeoJSON features
    without a class (see :func:`parse_geojson`). Polygons of unknown groups are
    dropped with one warning listing the groups.

    ``slide_size=(width, height)`` in level-0 pixels clips every geometry to the
    slide box, warning if any polygon extends beyond it; if the tumour is
    non-empty before clipping and empty after, AnnotationError.
    """
    source = os.fspath(path)
    if _is_xml(path):
        items = _read_asap_xml(path, label_map)
    else:
        items = _read_geojson(path, label_map, default_label)

    by_label: dict[str, list[Polygon]] = {label: [] for label in LABELS}
    n_polygons = dict.fromkeys((*LABELS, "unknown"), 0)
    unknown: list[str] = []
    for label, pieces in items:
        if label in by_label:
            by_label[label].extend(pieces)
            n_polygons[label] += 1
        else:
            n_polygons["unknown"] += 1
            group = label.removeprefix("unknown:")
            if group not in unknown:
                unknown.append(group)
    if unknown:
        warnings.warn(
            f"{source}: {n_polygons['unknown']} polygon(s) in unknown group(s) {unknown} ignored; "
            "add them to label_map to use them",
            stacklevel=2,
        )

    # Clipped polygon by polygon, united by clusters of polygons that meet, subtracted part by part: GEOS's
    # overlay of a whole file's geometry at once peaked at ~150 bytes per vertex (a 37 MiB XML: +140 MiB).
    frame = None
    if slide_size is not None:
        w, h = slide_size
        frame = box(0, 0, w, h)
        outside = sum(not frame.contains(p) for label in LABELS for p in by_label[label])
        if outside:
            warnings.warn(
                f"{source}: {outside} polygon(s) extend beyond the slide {w}x{h}; clipped to it", stacklevel=2
            )
    try:
        exclusion = _union_parts(_clip(by_label["exclusion"], frame))
        tissue = _union_parts(_clip(by_label["tissue"], frame))
        # subtracted after clipping, from the very exclusion returned: tumour and exclusion never overlap
        tumour = _subtract(_union_parts(_clip(by_label["tumour"], frame)), exclusion)
        if (
            frame is not None
            and not tumour
            and _subtract(_union_parts(by_label["tumour"]), _union_parts(by_label["exclusion"]))
        ):
            raise AnnotationError(path, f"annotation lies outside the slide {w}x{h}")
        tumour_geom, exclusion_geom = _multipolygon(tumour), _multipolygon(exclusion)
        if not exclusion_geom.is_empty and _robust(shapely.intersection, tumour_geom, exclusion_geom).area > 0:
            # tangled parts whose repair re-united them over the exclusion (found by `make fuzz`): cut once more
            tumour_geom = _as_multipolygon(_robust(shapely.difference, tumour_geom, exclusion_geom))
        tissue_geom = _multipolygon(tissue)
    except shapely.errors.GEOSException as e:  # _robust found no valid overlay: one line, not a traceback
        raise AnnotationError(
            path, f"polygons whose overlay GEOS cannot compute ({e}); repair or simplify them in the annotation tool"
        ) from None
    return Annotations(
        tumour=tumour_geom,
        exclusion=exclusion_geom,
        tissue=tissue_geom,
        n_polygons=n_polygons,
        unknown_groups=tuple(unknown),
        source=source,
    )


def _clip(polys: list[Polygon], frame) -> list[Polygon]:
    """``polys`` clipped to ``frame`` (None: unchanged); only those not inside it are overlaid."""
    if frame is None:
        return polys
    return [
        q
        for p in polys
        for q in ([p] if frame.contains(p) else _polygonal_parts(_robust(shapely.intersection, p, frame)))
    ]


def _union_parts(polys: list[Polygon]) -> list[Polygon]:
    """Valid polygons, pairwise disjoint (or touching at points), covering the union of the valid ``polys``:
    a polygon that meets no other is kept as it is, the others are united with ``union_all``."""
    if len(polys) <= 1:
        return list(polys)
    a, b = shapely.STRtree(polys).query(polys, predicate="intersects")
    alone = np.ones(len(polys), bool)
    alone[a[a != b]] = False
    rest = [p for p, k in zip(polys, alone) if not k]
    return [p for p, k in zip(polys, alone) if k] + (_polygonal_parts(_robust(shapely.union_all, rest)) if rest else [])


def _subtract(parts: list[Polygon], cut: list[Polygon]) -> list[Polygon]:
    """``parts`` minus the union of ``cut`` (both from :func:`_union_parts`): only the parts that meet
    ``cut`` are overlaid."""
    if not parts or not cut:
        return parts
    a, _ = shapely.STRtree(cut).query(parts, predicate="intersects")
    hit = set(a.tolist())
    whole = _multipolygon(cut)
    return [p for i, p in enumerate(parts) if i not in hit] + [
        q for i in sorted(hit) for q in _polygonal_parts(_robust(shapely.difference, parts[i], whole))
    ]


def _multipolygon(parts: list[Polygon]) -> MultiPolygon:
    """The MultiPolygon of ``parts`` (from :func:`_union_parts` / :func:`_subtract`); united with
    ``union_all`` in the rare case rounding left two of them overlapping."""
    if not parts:
        return _EMPTY
    geom = MultiPolygon(parts)
    return geom if geom.is_valid else _as_multipolygon(_robust(shapely.union_all, parts))


def _robust(overlay, *args):
    """``overlay(*args)`` (a shapely overlay: union_all, difference, intersection) as a *valid* geometry. GEOS's
    floating-point overlay of near-degenerate repaired parts can raise (``TopologyException``) or, worse, return
    an invalid polygon (a collapsed shell with a "hole" outside it, area -12,835 px² where the true difference
    is empty; both found by ``make fuzz``). Either way the same overlay is redone with snap rounding to
    10⁻⁶ px, which GEOS computes robustly, and, where GEOS still refuses a part, on inputs each repaired with
    ``make_valid`` first. Raises ``shapely.errors.GEOSException`` when no way gives a valid result (the caller
    turns it into one :class:`AnnotationError` line)."""

    def valid_inputs():
        return [
            shapely.make_valid(a) if isinstance(a, shapely.Geometry) else [shapely.make_valid(g) for g in a]
            for a in args
        ]

    attempts = (
        lambda: overlay(*args),
        lambda: overlay(*args, grid_size=1e-6),
        lambda: overlay(*valid_inputs(), grid_size=1e-6),
    )
    problem = None
    for attempt in attempts:
        try:
            result = attempt()
        except shapely.errors.GEOSException as e:
            problem = e
            continue
        if result.is_valid:
            return result
        problem = shapely.errors.GEOSException(
            f"{overlay.__name__} gave an invalid geometry ({shapely.is_valid_reason(result)})"
        )
    raise problem


def annotations_to_geojson(ann: Annotations) -> dict:
    """GeoJSON FeatureCollection of ``ann`` (level-0 pixels, x right, y down), one feature per label.

    Each feature has ``properties.label`` in ``tumour``/``exclusion``/``tissue``
    and a MultiPolygon geometry; empty labels are left out. Written to a
    ``.geojson`` file, it loads back with :func:`load_annotations` to the same
    geometry.
    """
    features = [
        {"type": "Feature", "properties": {"label": label}, "geometry": mapping(geom)}
        for label, geom in (("tumour", ann.tumour), ("exclusion", ann.exclusion), ("tissue", ann.tissue))
        if not geom.is_empty
    ]
    return {"type": "FeatureCollection", "features": features}


def check_label_map(label_map) -> None:
    """Refuse a ``--label-map`` (parsed JSON) that is not an object mapping group names to one of :data:`LABELS`:
    ``HistojaxDataError``, one line."""
    if not isinstance(label_map, dict):
        raise HistojaxDataError(None, f"--label-map must be a JSON object mapping group names to one of {LABELS}")
    for key, value in label_map.items():
        if value not in LABELS:
            raise HistojaxDataError(None, f"--label-map: {key!r} maps to {value!r}; expected one of {LABELS}")
