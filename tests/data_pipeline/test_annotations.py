"""Tests for data_tools.annotations on real CAMELYON / QuPath annotation files.

Expected values are computed here independently of the module: polygons are
re-read from the raw files with a regex (XML) or json + shapely (GeoJSON).
"""

from __future__ import annotations

import json
import math
import re
import tempfile
import time
import warnings
from pathlib import Path

import pytest
import shapely
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from shapely.geometry import MultiPoint, MultiPolygon, Polygon, shape

import data_tools.annotations as annotations_module
from data_tools.annotations import (
    DEFAULT_LABEL_MAP,
    Annotations,
    annotations_to_geojson,
    load_annotations,
    parse_asap_xml,
    parse_geojson,
)
from data_tools.errors import AnnotationError

DATA = Path(__file__).parents[1] / "data" / "annotations"
TUMOR_039 = DATA / "tumor_039.xml"
TUMOR_076 = DATA / "tumor_076.xml"
CAMELYON17 = DATA / "camelyon17_patient_004_node_4.xml"
TISSUE = DATA / "dtd_tumor_013.xml"
QUPATH = DATA / "qupath05.geojson"

_ANNOTATION_RE = re.compile(r'<Annotation Name="([^"]*)" Type="(\w+)" PartOfGroup="([^"]*)".*?</Annotation>', re.S)
_COORD_RE = re.compile(r'<Coordinate Order="(\d+)" X="([^"]+)" Y="([^"]+)"')


def _regex_polygons(path: Path) -> list[tuple[str, str, Polygon]]:
    """(type, group, repaired polygon) per annotation, read with plain regexes, not the module."""
    out = []
    for m in _ANNOTATION_RE.finditer(path.read_text()):
        coords = sorted((int(o), float(x), float(y)) for o, x, y in _COORD_RE.findall(m.group(0)))
        poly = shapely.make_valid(Polygon([(x, y) for _, x, y in coords]), method="structure", keep_collapsed=False)
        out.append((m.group(2), m.group(3), poly))
    return out


def _quiet_load(*args, **kwargs) -> Annotations:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # CAMELYON16 outlines self-intersect; repairs warn
        return load_annotations(*args, **kwargs)


def _asap_xml(annotations: list[tuple[str, str, list]], name_prefix: str = "A") -> str:
    """ASAP XML text for [(type, group, [(x, y), ...]), ...]; coordinates written in reverse order."""
    parts = ['<?xml version="1.0"?>\n<ASAP_Annotations>\n<Annotations>']
    for i, (kind, group, pts) in enumerate(annotations):
        parts.append(f'<Annotation Name="{name_prefix}{i}" Type="{kind}" PartOfGroup="{group}" Color="#F4FA58">')
        parts.append("<Coordinates>")
        for order in reversed(range(len(pts))):
            x, y = pts[order]
            parts.append(f'<Coordinate Order="{order}" X="{x}" Y="{y}" />')
        parts.append("</Coordinates></Annotation>")
    parts.append("</Annotations>\n<AnnotationGroups />\n</ASAP_Annotations>\n")
    return "\n".join(parts)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


SQUARE = [(0, 0), (100, 0), (100, 100), (0, 100)]


# ---------------------------------------------------------------- real files


def test_tumor_039_counts_and_exclusion_holes():
    raw = _regex_polygons(TUMOR_039)
    groups = [g for kind, g, _ in raw if kind in ("Polygon", "Spline")]
    assert (groups.count("metastasis"), groups.count("negative")) == (4, 144)

    ann = _quiet_load(TUMOR_039)
    assert ann.n_polygons == {"tumour": 4, "exclusion": 144, "tissue": 0, "ignore": 0, "unknown": 0}
    assert ann.unknown_groups == ()
    assert ann.source == str(TUMOR_039)

    tumour_union = shapely.union_all([p for _, g, p in raw if g == "metastasis"])
    negative_union = shapely.union_all([p for _, g, p in raw if g == "negative"])
    expected = tumour_union.area - tumour_union.intersection(negative_union).area
    assert ann.tumour.area == pytest.approx(expected, rel=1e-9)
    assert ann.tumour.area < tumour_union.area - 1e6  # the holes were really subtracted
    assert ann.exclusion.area == pytest.approx(negative_union.area, rel=1e-9)
    assert ann.tumour.intersection(ann.exclusion).area == pytest.approx(0, abs=1e-3)
    for geom in (ann.tumour, ann.exclusion, ann.tissue):
        assert isinstance(geom, MultiPolygon) and geom.is_valid
    assert ann.tissue.is_empty

    minx, miny, maxx, maxy = ann.bounds()
    assert (minx, miny, maxx, maxy) == pytest.approx(tumour_union.bounds, abs=1.0)


def test_tumor_076_spline_is_read_as_polygon():
    raw = _regex_polygons(TUMOR_076)
    splines = [p for kind, _, p in raw if kind == "Spline"]
    assert len(splines) == 1
    ann = _quiet_load(TUMOR_076)
    assert ann.n_polygons["tumour"] == 39
    assert ann.tumour.intersection(splines[0]).area == pytest.approx(splines[0].area, rel=1e-9)
    assert ann.tumour.area == pytest.approx(shapely.union_all([p for *_, p in raw]).area, rel=1e-9)


def test_camelyon17_tumor_group():
    ann = load_annotations(CAMELYON17)
    assert ann.n_polygons["tumour"] == 3 and ann.unknown_groups == ()
    pairs = parse_asap_xml(CAMELYON17)
    assert [label for label, _ in pairs] == ["tumour"] * 3
    assert ann.tumour.area == pytest.approx(shapely.union_all([p for _, p in pairs]).area)
    assert ann.tumour.area > 0


def test_tissue_annotations_have_no_tumour():
    ann = load_annotations(TISSUE)
    assert ann.n_polygons == {"tumour": 0, "exclusion": 0, "tissue": 1, "ignore": 4, "unknown": 0}
    assert ann.tumour.is_empty and isinstance(ann.tumour, MultiPolygon)
    assert ann.tissue.area > 0
    with pytest.raises(ValueError):
        ann.bounds()


def test_qupath_geojson_count_and_area():
    doc = json.loads(QUPATH.read_text())
    geoms = [shape(f["geometry"]) for f in doc["features"]]
    n_expected = sum(len(getattr(g, "geoms", [g])) for g in geoms)
    ann = load_annotations(QUPATH)  # unclassified features -> default_label "tumour"
    assert ann.n_polygons["tumour"] == n_expected == 3
    assert ann.tumour.area == pytest.approx(shapely.union_all(geoms).area, rel=1e-9)
    assert len(parse_geojson(QUPATH)) == 3


def test_qupath_without_default_label_gives_unknown_groups():
    with pytest.warns(UserWarning, match="unknown group"):
        ann = load_annotations(QUPATH, default_label=None)
    assert ann.tumour.is_empty
    assert set(ann.unknown_groups) == {"UT", "I"}
    assert ann.n_polygons["unknown"] == 3


def test_label_map_override_and_case_insensitivity():
    assert DEFAULT_LABEL_MAP["metastasis"] == "tumour" and DEFAULT_LABEL_MAP["_2"] == "exclusion"
    ann = _quiet_load(TUMOR_039, label_map={"METASTASIS": "ignore"})
    assert ann.tumour.is_empty
    assert ann.n_polygons["ignore"] == 4 and ann.n_polygons["exclusion"] == 144
    ann = load_annotations(CAMELYON17, label_map={"tumor": "tissue"})
    assert ann.tumour.is_empty and ann.n_polygons["tissue"] == 3


def test_unknown_group_warns_and_can_be_mapped(tmp_path):
    path = _write(tmp_path, "lesion.xml", _asap_xml([("Polygon", "Lesion", SQUARE), ("Polygon", "None", SQUARE)]))
    assert [label for label, _ in parse_asap_xml(path)] == ["unknown:Lesion", "unknown:None"]
    with pytest.warns(UserWarning, match="lesion.xml"):
        ann = load_annotations(path)
    assert ann.unknown_groups == ("Lesion", "None") and ann.tumour.is_empty
    with pytest.warns(UserWarning):  # "None" is still unknown
        ann = load_annotations(path, label_map={"lesion": "tumour"})
    assert ann.tumour.area == pytest.approx(100 * 100)


def test_camelyon16_original_group_names(tmp_path):
    inner = [(25, 25), (75, 25), (75, 75), (25, 75)]
    path = _write(tmp_path, "orig.xml", _asap_xml([("Polygon", "_0", SQUARE), ("Rectangle", "_2", inner)]))
    ann = load_annotations(path)
    assert ann.n_polygons["tumour"] == 1 and ann.n_polygons["exclusion"] == 1
    assert ann.tumour.area == pytest.approx(100 * 100 - 50 * 50)


# ---------------------------------------------------------------- unsafe XML

BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE lolz [
 <!ENTITY lol "lol">
 <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
 <!ENTITY lol2 "&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;">
 <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
 <!ENTITY lol4 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">
 <!ENTITY lol5 "&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;">
 <!ENTITY lol6 "&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;">
 <!ENTITY lol7 "&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;">
 <!ENTITY lol8 "&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;">
 <!ENTITY lol9 "&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;">
]>
<ASAP_Annotations><Annotations>
<Annotation Name="&lol9;" Type="Polygon" PartOfGroup="metastasis"><Coordinates>
<Coordinate Order="0" X="0" Y="0" /><Coordinate Order="1" X="10" Y="0" /><Coordinate Order="2" X="10" Y="10" />
</Coordinates></Annotation></Annotations></ASAP_Annotations>
"""

EXTERNAL_ENTITY = """<?xml version="1.0"?>
<!DOCTYPE foo [ <!ENTITY xxe SYSTEM "file:///etc/passwd"> ]>
<ASAP_Annotations><Annotations>
<Annotation Name="&xxe;" Type="Polygon" PartOfGroup="metastasis"><Coordinates>
<Coordinate Order="0" X="0" Y="0" /><Coordinate Order="1" X="10" Y="0" /><Coordinate Order="2" X="10" Y="10" />
</Coordinates></Annotation></Annotations></ASAP_Annotations>
"""


def test_billion_laughs_is_refused_quickly(tmp_path):
    path = _write(tmp_path, "laughs.xml", BILLION_LAUGHS)
    start = time.perf_counter()
    with pytest.raises(AnnotationError, match="laughs.xml"):
        load_annotations(path)
    assert time.perf_counter() - start < 1.0


def test_external_entity_is_refused(tmp_path):
    path = _write(tmp_path, "xxe.xml", EXTERNAL_ENTITY)
    with pytest.raises(AnnotationError, match="xxe.xml") as info:
        load_annotations(path)
    assert "root:" not in str(info.value)  # /etc/passwd was not read into anything


def test_oversized_file_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(annotations_module, "MAX_ANNOTATION_BYTES", 100)
    with pytest.raises(AnnotationError, match="limit"):
        load_annotations(CAMELYON17)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("name", "text", "problem"),
    [
        ("two_vertices.xml", _asap_xml([("Polygon", "metastasis", [(0, 0), (10, 10)])], "Tiny"), "Tiny0"),
        ("nan.xml", _asap_xml([("Polygon", "metastasis", [(0, 0), ("nan", 0), (10, 10)])], "Nan"), "Nan0"),
        ("inf.xml", _asap_xml([("Polygon", "metastasis", [(0, 0), (10, "inf"), (10, 10)])]), "non-finite"),
        ("text.xml", _asap_xml([("Polygon", "metastasis", [(0, 0), ("abc", 0), (10, 10)])], "Txt"), "Txt0"),
        ("empty.xml", "", "empty"),
        ("blank.geojson", "  \n", "empty"),
        (
            "points.xml",
            _asap_xml([("PointSet", "metastasis", SQUARE), ("Dot", "metastasis", SQUARE[:1])]),
            "no polygons",
        ),
        ("broken.xml", "<ASAP_Annotations><Annotations>", "malformed"),
        ("other.xml", "<html><body/></html>", "not ASAP"),
        ("nothing.geojson", '{"type": "FeatureCollection", "features": []}', "no polygons"),
        ("nan.geojson", '{"type": "Polygon", "coordinates": [[[0, 0], [NaN, 0], [5, 5], [0, 0]]]}', "non-finite"),
        ("str.geojson", '{"type": "Polygon", "coordinates": [[[0, 0], ["1", 0], [5, 5], [0, 0]]]}', "non-numeric"),
        ("line.geojson", '{"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [0, 0]]]}', "vertices"),
        ("bad.geojson", '{"type": "Polygon", ', "malformed JSON"),
        ("topo.geojson", '{"type": "Topology"}', "not GeoJSON"),
        ("notes.txt", "hello", "unknown annotation format"),
    ],
)
def test_bad_input_raises_annotation_error_naming_file(tmp_path, name, text, problem):
    path = _write(tmp_path, name, text)
    with pytest.raises(AnnotationError) as info:
        load_annotations(path)
    assert name in str(info.value) and problem in str(info.value)
    assert info.value.path == str(path)


def test_missing_file(tmp_path):
    with pytest.raises(AnnotationError, match="missing.xml"):
        load_annotations(tmp_path / "missing.xml")


def test_self_intersecting_bow_tie_is_repaired(tmp_path):
    bow_tie = [(0, 0), (10, 10), (10, 0), (0, 10)]
    path = _write(tmp_path, "bowtie.xml", _asap_xml([("Polygon", "metastasis", bow_tie)], "Bow"))
    with pytest.warns(UserWarning, match=r"bowtie\.xml.*Bow0"):
        ann = load_annotations(path)
    assert ann.tumour.is_valid and ann.tumour.area == pytest.approx(50.0)
    assert ann.n_polygons["tumour"] == 1


def test_zero_area_polygon_is_dropped(tmp_path):
    flat = [(0, 0), (5, 0), (10, 0)]
    path = _write(tmp_path, "flat.xml", _asap_xml([("Polygon", "metastasis", flat), ("Polygon", "tumor", SQUARE)]))
    with pytest.warns(UserWarning, match="zero-area") as record:
        ann = load_annotations(path)
    assert len(record) == 1  # dropped, not also "repaired"
    assert ann.n_polygons["tumour"] == 1 and ann.tumour.area == pytest.approx(10_000)


def test_geojson_holes_and_multipolygon_kept(tmp_path):
    doc = {
        "type": "Feature",
        "properties": {"classification": {"name": "Tumor", "color": [255, 0, 0]}},
        "geometry": {
            "type": "MultiPolygon",
            "coordinates": [
                [[[0, 0], [100, 0], [100, 100], [0, 100], [0, 0]], [[25, 25], [75, 25], [75, 75], [25, 75], [25, 25]]],
                [[[200, 0], [210, 0], [210, 10], [200, 10], [200, 0]]],
            ],
        },
    }
    path = _write(tmp_path, "holes.geojson", json.dumps(doc))
    ann = load_annotations(path)
    assert ann.n_polygons["tumour"] == 2
    assert ann.tumour.area == pytest.approx(100 * 100 - 50 * 50 + 100)
    stroma = dict(doc, properties={"classification": {"name": "Stroma"}})
    path = _write(tmp_path, "stroma.geojson", json.dumps(stroma))
    with pytest.warns(UserWarning, match="Stroma"):
        assert load_annotations(path).tumour.is_empty


# ---------------------------------------------------------------- clipping


def test_slide_size_clips_with_warning(tmp_path):
    half_out = [(50, 0), (150, 0), (150, 100), (50, 100)]
    path = _write(tmp_path, "half.xml", _asap_xml([("Polygon", "metastasis", half_out)]))
    with pytest.warns(UserWarning, match="half.xml"):
        ann = load_annotations(path, slide_size=(100, 200))
    assert ann.tumour.area == pytest.approx(50 * 100)
    assert ann.bounds() == (50.0, 0.0, 100.0, 100.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # inside the slide: no warning
        assert load_annotations(path, slide_size=(1000, 1000)).tumour.area == pytest.approx(100 * 100)


def test_slide_size_fully_outside_raises(tmp_path):
    far = [(500, 500), (600, 500), (600, 600), (500, 600)]
    path = _write(tmp_path, "far.xml", _asap_xml([("Polygon", "metastasis", far)]))
    with pytest.warns(UserWarning), pytest.raises(AnnotationError, match=r"far\.xml.*outside the slide 100x200"):
        load_annotations(path, slide_size=(100, 200))


# ---------------------------------------------------------------- properties and round trip


@settings(deadline=None, max_examples=50)
@given(st.lists(st.tuples(st.integers(0, 200_000), st.integers(0, 200_000)), min_size=3, max_size=30))
def test_convex_polygon_area_survives_asap_xml(points):
    hull = MultiPoint(points).convex_hull
    assume(isinstance(hull, Polygon) and hull.area > 0)
    vertices = [(int(x), int(y)) for x, y in hull.exterior.coords[:-1]]
    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp), "hull.xml", _asap_xml([("Polygon", "metastasis", vertices)]))
        ann = load_annotations(path)
    assert math.isclose(ann.tumour.area, hull.area, rel_tol=1e-6)
    assert ann.n_polygons["tumour"] == 1


def test_geojson_round_trip_keeps_geometry(tmp_path):
    ann = _quiet_load(TUMOR_039)
    doc = annotations_to_geojson(ann)
    assert {f["properties"]["label"] for f in doc["features"]} == {"tumour", "exclusion"}
    path = tmp_path / "round.geojson"
    path.write_text(json.dumps(doc))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # our own output needs no repair
        back = load_annotations(path)
    assert back.tumour.area == pytest.approx(ann.tumour.area, rel=1e-9)
    assert back.exclusion.area == pytest.approx(ann.exclusion.area, rel=1e-9)
    assert back.tumour.symmetric_difference(ann.tumour).area < 1e-3


def test_overlapping_pieces_after_repair_give_one_valid_area(tmp_path):
    """`make fuzz` (GeoJSON hostile geometry): a repaired bow-tie tumour, clipped to the slide and cut by an exclusion,
    came back as a MultiPolygon whose parts overlapped: invalid, with a negative area (-20.5 px²)."""
    import json as _json
    import warnings as _warnings

    polygons = [[(0, 0), (0, 0), (0, 1)], [(0, 6), (-1, -1), (34, 241)], [(0, 64), (2, 0), (-1, -1), (34, 241)]]
    feats = [
        {
            "type": "Feature",
            "properties": {"label": "exclusion" if i == 2 else "tumour"},
            "geometry": {"type": "Polygon", "coordinates": [[list(p) for p in pts]]},
        }
        for i, pts in enumerate(polygons)
    ]
    path = tmp_path / "tangled.geojson"
    path.write_text(_json.dumps({"type": "FeatureCollection", "features": feats}))
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")  # repaired, dropped and clipped polygons are noted; not the point here
        ann = load_annotations(path, slide_size=(5000, 5000))
    for geom in (ann.tumour, ann.exclusion, ann.tissue):
        assert geom.is_valid and geom.area >= 0
    assert ann.tumour.area > 0 and ann.tumour.intersection(ann.exclusion).area <= 1e-6 * ann.exclusion.area


def _asap_file(path, polygons, groups):
    anns = "".join(
        f'<Annotation Name="g{i}" Type="Polygon" PartOfGroup="{g}"><Coordinates>'
        + "".join(f'<Coordinate Order="{j}" X="{x}" Y="{y}" />' for j, (x, y) in enumerate(pts))
        + "</Coordinates></Annotation>"
        for i, (pts, g) in enumerate(zip(polygons, groups))
    )
    path.write_text(f"<ASAP_Annotations><Annotations>{anns}</Annotations></ASAP_Annotations>")
    return path


FREE_HOLE = [
    [(0, 0)] * 4,
    [(0, 0), (0, 1627), (34, 0), (0, 321), (1, 0), (33, 1501)],
    [(0, 1627), (34, 0), (1, 0), (33, 1501)],
]


def test_overlay_that_geos_gets_wrong_is_redone(tmp_path):
    """`make fuzz` (XML hostile geometry, seed 62614382478421757572422210540857218608): GEOS's floating overlay
    of a repaired tumour part minus the exclusion returned an invalid polygon (a collapsed shell with a free hole,
    area -12,835 px²) where the snap-rounded answer is empty; the next union raised TopologyException ("unable
    to assign free hole to a shell"), a traceback. Redone with snap rounding: valid, and tumour + exclusion
    tile the union of what was drawn."""
    import warnings as _warnings

    import shapely

    path = _asap_file(tmp_path / "free_hole.xml", FREE_HOLE, ["_0", "_0", "_2"])
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")  # repaired and dropped polygons are noted; not the point here
        ann = load_annotations(path, slide_size=(5000, 5000))
    for geom in (ann.tumour, ann.exclusion, ann.tissue):
        assert geom.is_valid and geom.area >= 0
    drawn = shapely.union_all(
        [shapely.make_valid(Polygon(p), method="structure") for p in FREE_HOLE[1:]], grid_size=1e-6
    )
    assert ann.tumour.intersection(ann.exclusion).area <= 1e-6 * ann.exclusion.area
    assert ann.tumour.area + ann.exclusion.area == pytest.approx(drawn.area, rel=1e-6)


def test_overlay_geos_cannot_compute_is_one_line(tmp_path, monkeypatch):
    """Where no overlay (plain, snap-rounded, on repaired inputs) gives a valid result, one AnnotationError
    line naming the file, not a GEOS traceback."""
    import shapely

    def refuse(*args, **kwargs):
        raise shapely.errors.GEOSException("TopologyException: unable to assign free hole to a shell at 0 1627")

    path = _asap_file(
        tmp_path / "refused.xml",
        [[(0, 0), (10, 0), (10, 10), (0, 10)], [(5, 5), (15, 5), (15, 15), (5, 15)]],
        ["_0", "_0"],
    )
    monkeypatch.setattr(shapely, "union_all", refuse)
    with pytest.raises(AnnotationError, match=r"refused\.xml.*overlay GEOS cannot compute"):
        load_annotations(path, slide_size=(100, 100))
