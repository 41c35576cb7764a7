"""Semi-synthetic slides (data_tools.datasets.synth.dataset): synthetic pixels on real CAMELYON16 geometry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.annotations import load_annotations
from data_tools.bundle import build_bundle, load_bundle
from data_tools.datasets.synth.dataset import make_dataset, make_semisynthetic_slide, tissue_files, tumour_files
from data_tools.slide_files.open import open_slide

SIZE = (1024, 1024)


@pytest.fixture(scope="module")
def tumour_xml() -> Path:
    files = {p.stem: p for p in tumour_files()}
    assert len(files) == 5
    return files["tumor_009"]


@pytest.fixture(scope="module")
def slide(tmp_path_factory, tumour_xml):
    out = tmp_path_factory.mktemp("synth") / "slide.tif"
    prov = make_semisynthetic_slide(tumour_xml, out, size=SIZE, seed=3, progress=False)
    return out, prov


def test_tiff_is_a_jpeg_pyramid_with_provenance(slide):
    tiff, prov = slide
    with open_slide(tiff) as reader:
        assert reader.dimensions == SIZE
        assert len(reader.levels) >= 2
        assert all(lv.compression == "JPEG" and lv.tile_size == (256, 256) for lv in reader.levels)
        assert [lv.downsample for lv in reader.levels[:2]] == [1.0, 2.0]
        assert reader.mpp == pytest.approx(prov["mpp"], rel=1e-3)
    with tifffile.TiffFile(tiff) as tif:
        description = tif.pages[0].description
    assert "PIXELS ARE SYNTHETIC" in description and "GEOMETRY IS REAL" in description
    assert "tumor_009.xml" in description
    on_disk = json.loads(tiff.with_suffix(".provenance.json").read_text())
    assert on_disk["summary"] == "pixels synthetic, geometry real CAMELYON16 tumor_009.xml"
    assert on_disk["tumour_source"]["file"] == "tumor_009.xml"


def test_bundle_mask_matches_geojson_and_tumour_is_purple(slide, tmp_path):
    tiff, prov = slide
    geojson = tiff.with_suffix(".geojson")
    ann = load_annotations(geojson)
    assert not ann.tumour.is_empty and not ann.tissue.is_empty
    assert ann.tumour.area == pytest.approx(prov["tumour_area_px"], rel=1e-6)
    assert ann.tissue.contains(ann.tumour.buffer(-1))  # tumour lies on tissue
    bundle = load_bundle(build_bundle(tiff, tmp_path / "b", annotations_path=geojson, progress=False))
    assert bundle.downsamples[0] == 1.0
    tumour = bundle.tumour[0][: SIZE[1], : SIZE[0]].astype(bool)
    assert tumour.sum() == pytest.approx(ann.tumour.area, rel=0.02)
    # texture: tumour darker and more purple (blue over red) than normal tissue
    from data_tools.masks import rasterize

    tissue = rasterize(ann.tissue, SIZE[0], SIZE[1], 1.0)
    pixels = bundle.pixels[0][: SIZE[1], : SIZE[0]].astype(float)
    t, n = pixels[tumour].mean(axis=0), pixels[tissue & ~tumour].mean(axis=0)
    assert t.sum() < n.sum() - 60  # darker
    assert t[2] - t[0] > n[2] - n[0] + 10  # more blue than red: haematoxylin
    glass = pixels[~tissue].mean(axis=0)
    assert np.all(glass > 225)  # near-white background
    assert prov["tumour_mean_rgb"][0] < prov["normal_tissue_mean_rgb"][0]


def test_same_seed_same_pixels_other_seed_other_pixels(slide, tumour_xml, tmp_path):
    tiff, _ = slide
    again = tmp_path / "again.tif"
    make_semisynthetic_slide(tumour_xml, again, size=SIZE, seed=3, progress=False)
    other = tmp_path / "other.tif"
    make_semisynthetic_slide(tumour_xml, other, size=SIZE, seed=4, progress=False)
    with open_slide(tiff) as a, open_slide(again) as b, open_slide(other) as c:
        first = a.read_level(0)
        assert np.array_equal(first, b.read_level(0))
        assert not np.array_equal(first, c.read_level(0))
    # same geometry whatever the seed (the tissue blob may differ)
    assert load_annotations(tiff.with_suffix(".geojson")).tumour.equals(
        load_annotations(other.with_suffix(".geojson")).tumour
    )


def test_tissue_outline_of_another_slide_and_orientation(tumour_xml, tmp_path):
    tiff = tmp_path / "t.tif"
    prov = make_semisynthetic_slide(
        tumour_xml, tiff, size=(512, 384), seed=0, tissue_xml=tissue_files()[0], orientation=5, progress=False
    )
    assert prov["tissue_source"]["kind"] == "camelyon16"
    assert prov["tissue_source"]["same_slide_as_tumour"] is False
    assert "ANOTHER" in prov["tissue_source"]["how"]
    ann = load_annotations(tiff.with_suffix(".geojson"), slide_size=(512, 384))
    assert ann.tissue.area > ann.tumour.area > 0
    with open_slide(tiff) as reader:
        assert reader.dimensions == (512, 384)


def test_make_dataset_split_is_disjoint(tmp_path):
    ds = make_dataset(
        tmp_path / "ds",
        n_slides=3,
        size=(256, 256),
        seed=1,
        tile_size=32,
        level_sets=(3,),
        progress=False,
        previews=False,
    )
    assert len(ds["slides"]) == 3
    train, test = set(ds["train"]), set(ds["test"])
    assert train and test and not train & test
    assert train | test == {s["bundle"] for s in ds["slides"]}
    on_disk = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert on_disk["train"] == ds["train"] and "pixels synthetic, geometry real CAMELYON16" in on_disk["provenance"]
    sources = {s["bundle"]: s["tumour_source"] for s in ds["slides"]}
    assert not {sources[b] for b in train} & {sources[b] for b in test}
    for s in ds["slides"]:
        bundle = load_bundle(tmp_path / "ds" / s["bundle"])
        assert bundle.metadata["source"]["file"] == Path(s["tiff"]).name
        assert bundle.tumour[0].sum() > 0


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_cli_places_the_tumour_files_it_is_given(tmp_path, capsys):
    from data_tools.__main__ import main

    xml = Path(__file__).parents[1] / "data" / "annotations" / "tumor_039.xml"
    assert (
        main(
            [
                "synth",
                str(tmp_path / "ds"),
                "--slides",
                "2",
                "--size",
                "1024",
                "--tile-size",
                "32",
                "--tumour-xml",
                str(xml),
                "--quiet",
            ]
        )
        == 0
    )
    ds = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert [s["tumour_source"] for s in ds["slides"]] == ["tumor_039.xml", "tumor_039.xml"]
    assert [s["orientation"] for s in ds["slides"]] == [0, 5]  # the second is the file turned and mirrored
    assert "tumor_039" in capsys.readouterr().out
