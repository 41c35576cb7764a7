"""Messages name the bundle a user will see, never the hidden temporary it is built in (``bundles/.NAME.tmp-XXXXXXXX``
is renamed to ``bundles/NAME`` when the build is done). Before: ``dataset --encoder pcam-cnn`` warned about
``bundles/.Tumor_094.tmp-3e5f6d9c/metadata.json``."""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest

from data_tools.cli_output import one_line, without_temporaries


def test_paths_inside_a_temporary_are_named_by_the_bundle():
    assert (
        one_line("bundles/.Tumor_094.tmp-3e5f6d9c/metadata.json: the slide's µm/px is unknown")
        == "bundles/Tumor_094/metadata.json: the slide's µm/px is unknown"
    )
    assert without_temporaries("/d/bundles/.a.b.tmp-0123abcd/tissue.npy") == "/d/bundles/a.b/tissue.npy"
    # the temporary itself (a message about it, e.g. a dead build's leftover) keeps its name
    assert one_line("removed bundles/.Tumor.tmp-3e5f6d9c beside it") == "removed bundles/.Tumor.tmp-3e5f6d9c beside it"


def test_the_encoder_scale_warning_names_the_bundle_not_its_temporary(tmp_path, monkeypatch):
    import types

    import tifffile

    import data_tools.features.efficientnet as efficientnet
    from data_tools.bundle import build_bundle
    from data_tools.errors import BundleError
    from data_tools.features.grid import compute_features

    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (192, 256, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", image, photometric="rgb")  # no µm/px: the pcam-cnn scale warning
    built = build_bundle(tmp_path / "s.tif", tmp_path / "b", level_sets=(3,), tile_size=32, progress=False)
    temporary = tmp_path / "bundles" / ".Tumor_094.tmp-3e5f6d9c"
    shutil.copytree(built, temporary)
    # the warning comes from the encoder's name and the bundle: a stand-in spares loading pcam-cnn
    monkeypatch.setattr(efficientnet, "load_encoder", lambda name, **kw: types.SimpleNamespace(name=name, dim=64))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(BundleError):  # dim 0: refused right after the warning, before any view is encoded
            compute_features(temporary, encoder_name="pcam-cnn", dim=0, progress=False)
    said = [str(w.message) for w in caught if "µm/px" in str(w.message)]
    assert said and said[0].startswith(f"{tmp_path / 'bundles' / 'Tumor_094' / 'metadata.json'}: "), said
    assert ".tmp-" not in said[0]
