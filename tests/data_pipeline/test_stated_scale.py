"""A slide's scale stated by the user (``--mpp`` on ``build``, ``features`` and ``dataset``) for files without (or with
wrong) µm/px, recorded in the bundle; ``build --encoder`` / ``--features`` (one command for a slide with features);
and an encoder-scale warning that names the level whose µm/px matches the encoder instead of calling the whole slide
off scale. Before: none of the three commands took ``--mpp`` (a TCGA SVS without MPP stayed ``mpp: unknown``),
``build`` took no ``--encoder``, and the warning said "the slide is at 0.25 µm/px, 7.8x from ..." although its level
at downsample 8 is at 2 µm/px."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.__main__ import main
from data_tools.bundle_files.reading import load_bundle, read_metadata
from data_tools.features.encoders import encoder_scale

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"  # states 0.499 µm/px


@pytest.fixture(scope="module")
def unscaled_slide(tmp_path_factory) -> Path:
    """A 512 × 384 px TIFF stating no µm/px, with a tissue blob."""
    root = tmp_path_factory.mktemp("unscaled")
    image = np.full((384, 512, 3), 240, np.uint8)
    image[60:300, 80:420] = [200, 90, 160]
    tifffile.imwrite(root / "s.tif", image, photometric="rgb")
    return root / "s.tif"


def _run(capsys, *argv):
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # a usage error: argparse's one line, exit 2
        rc = e.code
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_build_mpp_and_encoder_in_one_command(capsys, tmp_path, unscaled_slide):
    rc, out, err = _run(
        capsys,
        "build",
        unscaled_slide,
        "--out",
        tmp_path / "b",
        "--levels",
        "3",
        "--tile-size",
        "64",
        "--quiet",
        "--mpp",
        "0.5",
        "--encoder",
        "colour-stats",
    )
    assert rc == 0, err
    assert out.strip() == f"wrote {tmp_path / 'b'}: 3 levels, 0.5 µm/px (given), colour-stats feature grid"
    meta = read_metadata(tmp_path / "b")
    assert meta.source["mpp"] == 0.5 and meta.source["mpp_from"] == "given" and meta.source["mpp_in_file"] is None
    assert [lv["mpp"] for lv in meta["levels"]] == [0.5 * lv["downsample"] for lv in meta["levels"]]
    assert meta.features["encoder"] == "colour-stats"
    load_bundle(tmp_path / "b", verify=True)  # sealed with the stated scale


def test_build_refuses_a_bad_mpp_or_encoder_before_building(capsys, tmp_path, unscaled_slide):
    for argv, said in (
        (["--mpp", "250"], "not a µm per level-0 px between 0.01 and 100"),
        (["--mpp", "nan"], "not a finite number"),
        (["--encoder", "no-such-encoder"], "no-such-encoder"),
    ):
        rc, _, err = _run(capsys, "build", unscaled_slide, "--out", tmp_path / "b", "--quiet", *argv)
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert re.search(said, err), err
        assert not (tmp_path / "b").exists()


def test_features_mpp_restates_a_bundles_scale(capsys, tmp_path, unscaled_slide):
    from data_tools.bundle import build_bundle

    bundle = build_bundle(SVS, tmp_path / "b", level_sets=(3,), tile_size=128, progress=False)
    rc, _, err = _run(capsys, "features", bundle, "--encoder", "colour-stats", "--mpp", "0.25", "--quiet")
    assert rc == 0, err
    meta = read_metadata(bundle)
    assert meta.source["mpp"] == 0.25 and meta.source["mpp_in_file"] == pytest.approx(0.499)
    assert meta["levels"][1]["mpp"] == pytest.approx(0.25 * meta["levels"][1]["downsample"])
    load_bundle(bundle, verify=True)
    before = (bundle / "metadata.json").read_bytes()
    rc, _, err = _run(capsys, "features", bundle, "--encoder", "colour-stats", "--mpp", "-1", "--quiet")
    assert rc == 2 and "--mpp -1" in err and (bundle / "metadata.json").read_bytes() == before


def test_dataset_mpp_states_every_slides_scale(capsys, tmp_path, unscaled_slide):
    slides = tmp_path / "S"
    slides.mkdir()
    (slides / "a.tif").symlink_to(unscaled_slide)
    rc, _, err = _run(
        capsys,
        "dataset",
        slides,
        "--out",
        tmp_path / "o",
        "--levels",
        "3",
        "--tile-size",
        "64",
        "--quiet",
        "--test-fraction",
        "0",
        "--mpp",
        "0.5",
    )
    assert rc == 0, err
    ds = json.loads((tmp_path / "o" / "dataset.json").read_text())
    assert ds["options"]["mpp"] == 0.5 and [s.get("mpp") for s in ds["slides"]] == [0.5]
    assert read_metadata(tmp_path / "o" / "bundles" / "a").source["mpp_from"] == "given"


def test_the_scale_warning_names_the_level_on_the_encoders_scale(tmp_path, monkeypatch):
    far = encoder_scale("pcam-cnn", 0.25, [1, 2, 4, 8, 16])
    assert not far["ok"] and far["level_on_scale"] == 3
    assert "its level 3 (downsample 8) is at 2 µm/px, on that scale: use the features of level 3" in far["warning"]
    assert encoder_scale("pcam-cnn", 0.25, [1, 4, 16])["level_on_scale"] is None  # 1 and 4 µm/px: none within 1.5x
    assert "--mpp" in encoder_scale("pcam-cnn", None)["warning"]

    from data_tools.bundle import build_bundle
    from data_tools.errors import BundleError
    from data_tools.features.grid import compute_features

    bundle = build_bundle(
        SVS, tmp_path / "b", level_sets=(5,), tile_size=64, progress=False, mpp=0.25, region=(0, 0, 1024, 1024)
    )
    import types

    import data_tools.features.efficientnet as efficientnet

    # the warning comes from the encoder's name and the bundle's levels: a stand-in spares loading pcam-cnn
    monkeypatch.setattr(efficientnet, "load_encoder", lambda name, **kw: types.SimpleNamespace(name=name, dim=64))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(BundleError):  # dim 0: refused just after the warning, nothing encoded
            compute_features(bundle, encoder_name="pcam-cnn", dim=0, progress=False)
    said = [str(w.message) for w in caught if "µm/px" in str(w.message)]
    assert len(said) == 1 and "its level 3 (downsample 8) is at 2 µm/px" in said[0], said
