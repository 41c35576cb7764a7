"""A slide file's own µm/px is range-checked as a given ``--mpp`` is (0.01 to 100 µm per level-0 px): outside it the
build is refused in one line naming the file and the value, and the true scale given with ``--mpp`` builds it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from data_tools.bundle import MPP_RANGE, build_bundle, check_stated_mpp
from data_tools.errors import SlideError


def _slide(tmp_path, mpp: float):
    from slide_helpers import pyramid

    rng = np.random.default_rng(0)
    return pyramid(tmp_path / f"s{mpp:g}.tif", rng.integers(0, 255, (256, 256, 3), np.uint8), mpp=mpp)


@pytest.mark.parametrize("mpp", [1e-4, 500.0])
def test_a_file_stating_an_out_of_range_scale_is_refused_in_one_line(tmp_path, mpp):
    path = _slide(tmp_path, mpp)
    with pytest.raises(SlideError) as e:
        build_bundle(path, tmp_path / "b", level_sets=(3,), tile_size=64, progress=False)
    text = str(e.value)
    assert text.startswith(str(path)) and "\n" not in text
    assert f"the file states {mpp:g} µm per level-0 px, not between 0.01 and 100" in text and "--mpp" in text
    assert not (tmp_path / "b").exists()


def test_the_true_scale_given_with_mpp_builds_it(tmp_path):
    path = _slide(tmp_path, 500.0)
    build_bundle(path, tmp_path / "b", level_sets=(3,), tile_size=64, progress=False, mpp=0.5)
    source = json.loads((tmp_path / "b" / "metadata.json").read_text())["source"]
    assert source["mpp"] == 0.5 and source["mpp_from"] == "given" and source["mpp_in_file"] == pytest.approx(500.0)


def test_the_range_is_the_one_a_given_mpp_must_lie_in():
    low, high = MPP_RANGE
    for ok in (None, low, 0.25, high):
        check_stated_mpp("s.svs", ok)
    for bad in (low / 2, high * 2, float("inf"), float("nan")):
        with pytest.raises(SlideError, match=r"^s\.svs: the file states"):
            check_stated_mpp("s.svs", bad)


def test_a_scale_stated_through_openslide_is_checked_too(tmp_path):
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    from mirax_fixture import mirax

    rng = np.random.default_rng(0)
    path, _ = mirax(tmp_path / "m.mrxs", rng.integers(0, 255, (256, 256, 3), np.uint8), mpp=0.001)
    with pytest.raises(SlideError, match=r"m\.mrxs: the file states 0\.001 µm per level-0 px, not between"):
        build_bundle(path, tmp_path / "b", level_sets=(3,), tile_size=64, progress=False)
