"""The v1 ids' rebuild hint keeps the options a C16 dataset was built with (dataset.json), so following it
rebuilds the same set at the same scale instead of another one."""

import json
import shlex

import pytest

from data_tools.errors import BundleError
from histojax.datasets import check_dataset
from histojax.registry import spec_of


def _hint(tmp_path, **recorded) -> list[str]:
    ds = {
        "kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
        "format": 2,
        "encoder": None,
        "pixels_kept": True,
        "seed": 0,
        "test_fraction": 0.25,
        "annotations": "/data/ncrf.tar.gz",
        "patches": "/data/pcam.tar.gz",
        "scale": {"downsample_from_camelyon16_level0": 8.0},
        "patch_pools": {"test": {"source": "/data/pcam.tar.gz", "other_patch_set": False}},
        "variant": "full",
        "labels": {"Tumor_001": 1, "Normal_139": 0},
    }
    ds.update(recorded)
    (tmp_path / "dataset.json").write_text(json.dumps(ds))
    with pytest.raises(BundleError) as err:
        check_dataset(tmp_path, spec_of("HistoJAX-C16-Hard-v1").settings, "HistoJAX-C16-Hard-v1")
    message = str(err.value)
    assert "\n" not in message
    command = message.split("`")[1]
    assert command.startswith("python -m data_tools c16 "), message
    return shlex.split(command)


def test_small_set_hint_keeps_small(tmp_path):
    words = _hint(tmp_path, variant="small", scale={"downsample_from_camelyon16_level0": 32.0})
    assert "--small" in words and "--features" in words and "..." not in words
    assert words[words.index("--out") + 1] == str(tmp_path)


def test_full_set_hint_keeps_sources_scale_and_pixels(tmp_path):
    words = _hint(
        tmp_path,
        pixels_kept=False,
        scale={"downsample_from_camelyon16_level0": 4.0},
        seed=3,
        test_fraction=0.3,
        patch_pools={"test": {"source": "/data/heldout", "other_patch_set": True}},
    )
    assert "--small" not in words and "--no-pixels" in words
    for option, value in [
        ("--annotations", "/data/ncrf.tar.gz"),
        ("--patches", "/data/pcam.tar.gz"),
        ("--downsample", "4.0"),
        ("--seed", "3"),
        ("--test-fraction", "0.3"),
        ("--test-patches", "/data/heldout"),
    ]:
        assert words[words.index(option) + 1] == value, (option, words)


def test_subset_hint_names_its_slides(tmp_path):
    words = _hint(tmp_path, variant="subset")
    assert words[words.index("--slides") + 1 : words.index("--slides") + 3] == ["Normal_139", "Tumor_001"]


def test_hint_parses_with_the_c16_command(tmp_path):
    """The printed command is one the c16 command line accepts (parsed, not run)."""
    import argparse

    from data_tools.__main__ import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for recorded in ({"variant": "small"}, {"variant": "subset", "pixels_kept": False}):
        args = parser.parse_args(_hint(tmp_path, **recorded)[3:])
        assert args.command == "c16" and args.out == str(tmp_path)


def test_missing_dataset_hint_builds_what_the_id_needs(monkeypatch, tmp_path):
    """Without a dataset, a -v1 id names a build it accepts (with pcam-cnn features); -v0 the plain one."""
    import histojax

    monkeypatch.setenv("HISTOJAX_C16_DATASET", str(tmp_path / "nowhere"))
    with pytest.raises(BundleError, match=r"`python -m data_tools c16 --small --features --out DIR`") as err:
        histojax.make("HistoJAX-C16-Hard-v1")
    assert "--no-pixels --out DIR`" in str(err.value)
    with pytest.raises(BundleError, match=r"`python -m data_tools c16 --small --out DIR`"):
        histojax.make("HistoJAX-C16-Hard-v0")
