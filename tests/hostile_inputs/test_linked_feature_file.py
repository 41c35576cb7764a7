"""Every head fit and bundle reader of ``baselines.reading`` refuses a feature file that is a symbolic link out
of its bundle, in one line naming the bundle and the entry, through the one checked loader
(:func:`baselines.reading.slides.read_bundle`)."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from fold_helpers import build_folded

from data_tools.errors import BundleError


@pytest.fixture(scope="module")
def linked(tmp_path_factory):
    """A 7-slide dataset with colour-stats features whose bundle ``t0`` has its finest feature grid replaced by a
    link to a copy outside the bundle."""
    root = tmp_path_factory.mktemp("linked")
    ds = build_folded(root, folds=2, encoder="colour-stats")
    bundle = ds / "bundles" / "t0"
    name = json.loads((bundle / "metadata.json").read_text())["features"]["levels"][0]["file"]
    shutil.copy(bundle / name, root / "outside.npy")
    os.unlink(bundle / name)
    os.symlink(root / "outside.npy", bundle / name)
    return ds, name


def _readers():
    from baselines.reading import head_mil_fit, learned_head_fit, pipeline, slides

    return {
        "slides.load_slides (the logit fit)": lambda ds: slides.load_slides(ds, ["bundles/t0"], dim=0),
        "head_mil_fit.load_grid": lambda ds: head_mil_fit.load_grid(ds / "bundles" / "t0", 0, dim=0),
        "learned_head_fit.load_split": lambda ds: learned_head_fit.load_split(ds, ["bundles/t0"], {}, progress=False),
        "pipeline.load_feature_slides (readers, budget curve)": lambda ds: pipeline.load_feature_slides(
            ds, ["bundles/t0"], slides.read_spec(ds), None, 1
        ),
    }


@pytest.mark.parametrize("reader", list(_readers()))
def test_a_feature_file_linked_out_of_its_bundle_is_refused(linked, reader):
    ds, name = linked
    with pytest.raises(BundleError, match=rf"t0: entry '{name}' is a symbolic link .*not the bundle's own file"):
        _readers()[reader](ds)
