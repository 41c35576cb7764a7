"""A built-in encoder run on slides far from the scale it was trained at, or of unknown scale, is warned about in one
line naming the bundle and recorded in its features metadata (``encoder_scale``); pcam-cnn: 1.944 µm/px, tolerance
1.5x either way."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from data_tools.bundle_files.reading import read_metadata
from data_tools.features.encoders import ENCODER_MPP, SCALE_TOLERANCE, encoder_scale


def test_encoder_scale_tolerance():
    assert ENCODER_MPP["pcam-cnn"] == pytest.approx(1.944) and SCALE_TOLERANCE == 1.5
    assert encoder_scale("pcam-cnn", 1.944)["ok"] and encoder_scale("pcam-cnn", 2.8)["ok"]
    far = encoder_scale("pcam-cnn", 0.5)
    assert not far["ok"] and far["factor"] == pytest.approx(3.888, abs=1e-3) and "0.5 µm/px" in far["warning"]
    assert not encoder_scale("pcam-cnn", 1.944 * 1.6)["ok"]
    for unknown in (None, 0, -1.0, float("nan"), "x"):
        r = encoder_scale("pcam-cnn", unknown)
        assert not r["ok"] and r["slide_mpp"] is None and "unknown" in r["warning"]
    assert encoder_scale("colour-stats", 0.25) is None  # no training scale: nothing to warn about


def test_features_warn_and_record(tmp_path):
    import tifffile

    from data_tools.bundle import build_bundle
    from data_tools.features.grid import compute_features

    image = np.full((256, 256, 3), 245, np.uint8)
    image[32:224, 32:224] = [230, 160, 200]
    tifffile.imwrite(tmp_path / "s.tif", image, photometric="rgb")  # no µm/px recorded: unknown scale
    bundle = build_bundle(tmp_path / "s.tif", tmp_path / "b", level_sets=(3,), tile_size=32, progress=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compute_features(bundle, encoder_name="pcam-cnn", image_size=None, progress=False)
    lines = [str(w.message) for w in caught if "µm/px" in str(w.message)]
    assert len(lines) == 1 and lines[0].startswith(str(bundle / "metadata.json")) and "\n" not in lines[0]
    rec = read_metadata(bundle)["features"]["encoder_scale"]
    assert rec["ok"] is False and rec["encoder_mpp"] == pytest.approx(1.944)


def test_dataset_scale_warns_on_mixed_and_far_slides():
    from data_tools.features.encoders import dataset_scale

    rec, lines = dataset_scale("pcam-cnn", {"a": 1.9, "b": 0.5, "c": None})
    assert len(lines) == 2 and "mix scales" in lines[0]
    assert "a is 1.9 µm/px, b 0.5 µm/px" in lines[0] and "2 of 3 slides" in lines[1]
    assert rec["slides_out_of_scale"] == {"b": 0.5, "c": None} and rec["tolerance"] == 1.5
    rec, lines = dataset_scale("pcam-cnn", {"a": 1.9, "b": 2.2})
    assert lines == [] and rec["slides_out_of_scale"] == {}
    rec, lines = dataset_scale("imported", {"a": 0.25, "b": 0.5})  # no training scale; the mix still warned
    assert rec is None and len(lines) == 1 and "mix scales" in lines[0]


def test_dataset_json_records_the_encoder_scale(tmp_path):
    from data_tools.datasets.build import write_dataset_json

    plan = {
        "options": {"encoder": "pcam-cnn"},
        "slides": {"a": {"split": "train", "label": 1, "mpp": 0.5}, "b": {"split": "test", "label": 0, "mpp": 1.944}},
    }
    ds = write_dataset_json(tmp_path, plan, {"a": {"name": "a"}, "b": {"name": "b"}}, {})
    assert ds["encoder_scale"]["slides_out_of_scale"] == {"a": 0.5}
    assert (tmp_path / "dataset.json").read_text().count("encoder_scale") == 1


def test_the_c16_scale_warning_offers_its_downsample_not_mpp():
    """Was: the scale warning of a ``c16 --small`` slide (downsample 32: 7.78 µm/px) offered ``--mpp``, an option c16
    does not have (its µm/px is CAMELYON16's times --downsample, known): it offers the --downsample on scale."""
    from data_tools.datasets.c16.dataset import scale_remedy
    from data_tools.datasets.c16.layout import C16_MPP

    said = encoder_scale("pcam-cnn", C16_MPP * 32, [1.0, 4.0], scale_remedy("pcam-cnn", 32))["warning"]
    assert "--mpp" not in said and "build them with --downsample 8 for pcam-cnn's 1.944 µm/px" in said
    unknown = encoder_scale("pcam-cnn", None, remedy=scale_remedy("pcam-cnn", 32))["warning"]
    assert "--mpp" not in unknown
    assert "--mpp" in encoder_scale("pcam-cnn", 0.5)["warning"]  # a file's scale: --mpp stays the remedy
