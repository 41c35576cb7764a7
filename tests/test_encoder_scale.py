"""A built-in encoder run on slides far from the scale it was trained at, or of unknown scale, is warned about in one
line naming the bundle and recorded in its features metadata (``encoder_scale``); pcam-cnn: 1.944 µm/px, tolerance
1.5x either way."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from data_tools.bundle_format import read_metadata
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
