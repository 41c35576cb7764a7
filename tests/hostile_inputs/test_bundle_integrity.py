"""Bundles refused instead of loaded wrong: mask values, sealed metadata, metadata fields and file
names, unusable zoom levels, ``--overwrite`` of someone's files, and reads during a rebuild."""

from __future__ import annotations

import json
import shutil
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

import data_tools.bundle
from data_tools.bundle import METADATA, build_bundle, load_bundle
from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.seals import METADATA_DIGEST, metadata_digest, write_metadata
from data_tools.bundle_files.writes import atomic_folder
from data_tools.errors import BundleError

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
TARGET = ROOT / "histojax" / "data" / "CMU-1-Small-Region.target.xml"
KIDNEY = ROOT / "tests" / "data" / "kidney-48-5_IHC.tif"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    """The sample slide with its tumour target, Easy levels (3), 128-px views."""
    return build_bundle(
        SVS, tmp_path_factory.mktemp("svs") / "bundle", annotations_path=TARGET, level_sets=(3,), progress=False
    )


@pytest.fixture
def copy(bundle, tmp_path) -> Path:
    return Path(shutil.copytree(bundle, tmp_path / "copy"))


def _meta(folder: Path) -> dict:
    return json.loads((folder / METADATA).read_text())


def _replace_array(folder: Path, name: str, array: np.ndarray) -> None:
    """Write ``array`` as ``name`` and record its checksum (resealing the metadata), as another tool would."""
    np.save(folder / name, array, allow_pickle=False)
    meta = _meta(folder)
    meta["checksums"][name] = sha256(folder / name)
    write_metadata(folder, meta)


def _edit_metadata(folder: Path, edit) -> None:
    """Change ``metadata.json`` by hand (the digest is left as it was)."""
    meta = _meta(folder)
    edit(meta)
    (folder / METADATA).write_text(json.dumps(meta))


# --------------------------------------------------------------------------- item 3: mask values
def test_valid_bundle_is_sealed_and_loads_without_warning(bundle):
    meta = _meta(bundle)
    assert meta[METADATA_DIGEST] == metadata_digest(meta)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_bundle(bundle)


@pytest.mark.parametrize("scale", [7, 255])
def test_tumour_mask_not_01_is_refused(copy, scale):
    tumour = np.load(copy / "tumour_01.npy")
    assert tumour.max() == 1
    _replace_array(copy, "tumour_01.npy", (tumour * scale).astype(np.uint8))
    for verify in (True, False):
        with pytest.raises(BundleError, match=r"tumour_01\.npy.*expected 0/1"):
            load_bundle(copy, verify=verify)


def test_tumour_mask_not_01_is_refused_by_make(copy):
    import histojax

    _replace_array(copy, "tumour_02.npy", (np.load(copy / "tumour_02.npy") * 7).astype(np.uint8))
    with pytest.raises(BundleError, match=r"tumour_02\.npy.*expected 0/1"):
        histojax.make("HistoJAX-Easy-v0", slide=copy)


def test_tissue_mask_not_01_is_refused(copy):
    tissue = np.load(copy / "tissue.npy").astype(np.uint8) * 255
    _replace_array(copy, "tissue.npy", tissue)
    with pytest.raises(BundleError, match=r"tissue\.npy.*expected 0/1"):
        load_bundle(copy)


def test_tissue_mask_of_wrong_shape_names_the_file(copy):
    _replace_array(copy, "tissue.npy", np.zeros((3, 5), bool))
    with pytest.raises(BundleError, match=r"tissue\.npy: tissue mask of shape \(3, 5\)"):
        load_bundle(copy)


def test_float_mask_is_refused(copy):
    _replace_array(copy, "tissue.npy", np.load(copy / "tissue.npy").astype(np.float32))
    with pytest.raises(BundleError, match=r"tissue\.npy.*dtype float32"):
        load_bundle(copy)


# --------------------------------------------------------------------------- item 4: metadata is verified
EDITS = {
    "tile_size": lambda m: m.update(tile_size=64),
    "tissue.level": lambda m: m["tissue"].update(level=0),
    "level_sets": lambda m: m.update(level_sets=[3, 5, 7]),
    "tumour_pixels": lambda m: m["levels"][0].update(tumour_pixels=m["levels"][0]["tumour_pixels"] + 1),
    "mpp": lambda m: m["levels"][1].update(mpp=123.0),
}


@pytest.mark.parametrize("field", sorted(EDITS))
def test_metadata_edit_is_refused(copy, field):
    _edit_metadata(copy, EDITS[field])
    with pytest.raises(BundleError, match="metadata.json: .*(digest mismatch|tissue level)"):
        load_bundle(copy)


def test_metadata_edit_is_refused_by_make(copy):
    import histojax

    _edit_metadata(copy, EDITS["tile_size"])
    with pytest.raises(BundleError, match="metadata digest mismatch"):
        histojax.make("HistoJAX-Easy-v0", slide=copy)


def test_unsealed_metadata_warns_and_is_cross_checked(copy):
    """A bundle written before metadata was sealed loads with a warning; its cross-checks still apply."""
    _edit_metadata(copy, lambda m: m.pop(METADATA_DIGEST))
    with pytest.warns(UserWarning, match="not sealed"):
        load_bundle(copy)
    _edit_metadata(copy, EDITS["tumour_pixels"])
    with pytest.warns(UserWarning, match="not sealed"), pytest.raises(BundleError, match="tumour px"):
        load_bundle(copy)


# --------------------------------------------------------------------------- item 11: errors name the file
@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda m: m.update(tile_size=0), "tile_size 0 must be"),
        (lambda m: m.update(tile_size="128"), "tile_size '128' must be"),
        (lambda m: m["levels"][0].update(width=-4), "level 0 width -4"),
        (lambda m: m["levels"][1].update(downsample=float("nan")), "level 1 downsample nan"),
        (lambda m: m.update(levels=[]), "levels must be a non-empty list"),
        (lambda m: m.update(magnification_range=0), "magnification_range 0"),
    ],
)
def test_malformed_metadata_field_names_metadata_json(copy, edit, message):
    _edit_metadata(copy, edit)
    for verify in (True, False):
        with pytest.raises(BundleError, match=f"metadata.json: {message}"):
            load_bundle(copy, verify=verify)


@pytest.mark.parametrize("entry", ["/etc/passwd", "../copy/pixels_00.npy", "..", "sub/pixels_00.npy", ""])
def test_file_entries_must_stay_inside_the_bundle(copy, entry, monkeypatch):
    opened = []
    monkeypatch.setattr("data_tools.bundle_files.format.sha256", lambda p: opened.append(p) or "x")
    meta = _meta(copy)
    meta["levels"][0]["pixels"] = entry
    write_metadata(copy, meta)  # even a sealed bundle may only name its own files
    for verify in (True, False):
        with pytest.raises(BundleError, match="not a file name inside the bundle"):
            load_bundle(copy, verify=verify)
    assert opened == []


def test_corrupt_npy_header_names_the_file(copy):
    victim = copy / "pixels_01.npy"
    data = bytearray(victim.read_bytes())
    data[10:60] = b"{'descr': '|u1', 'fortran_order': False, 'shape': ("  # unterminated: tokenize fails
    victim.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"pixels_01\.npy: unreadable array"):
        load_bundle(copy, verify=False)
    with pytest.raises(BundleError, match=r"pixels_01\.npy: checksum mismatch"):
        load_bundle(copy)


# --------------------------------------------------------------------------- item 5: extreme build options
@pytest.mark.parametrize(
    "options, message",
    [
        ({"magnification_range": 1e300}, "are both 128×128 px once padded"),
        ({"magnification_range": 1.0}, "gives a single zoom level"),
        ({"tile_size": 4096}, r"smaller than two 4096-px views"),
    ],
)
def test_zoomless_builds_are_refused(tmp_path, options, message):
    out = tmp_path / "bundle"
    with pytest.raises(BundleError, match=message) as info:
        build_bundle(SVS, out, level_sets=(3, 5, 7), progress=False, **options)
    assert "\n" not in str(info.value) and str(SVS) in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_zoomless_bundle_is_refused_by_make(tmp_path, monkeypatch):
    """A bundle built before the build refused it (magnification range 1: one level) is refused at make."""
    import histojax

    monkeypatch.setattr(data_tools.bundle, "check_zoom", lambda *a, **k: None)
    out = build_bundle(KIDNEY, tmp_path / "flat", level_sets=(3,), magnification_range=1.0, progress=False)
    assert len(_meta(out)["levels"]) == 1
    with pytest.raises(BundleError, match="zooming would do nothing"):
        histojax.make("HistoJAX-Easy-v0", slide=out)


# --------------------------------------------------------------------------- item 12: reads during a rebuild
def test_readers_see_a_whole_bundle_while_it_is_rebuilt(tmp_path):
    """A writer swaps two different bundles into place (as ``build --overwrite`` does) while readers load it
    with verification: every load succeeds and is one of the two bundles, whole."""
    a = build_bundle(KIDNEY, tmp_path / "a", level_sets=(3,), progress=False)
    b = build_bundle(KIDNEY, tmp_path / "b", level_sets=(3,), tile_size=64, progress=False)
    digests = {_meta(a)[METADATA_DIGEST], _meta(b)[METADATA_DIGEST]}
    target = tmp_path / "live"
    shutil.copytree(a, target)
    done, errors, seen = threading.Event(), [], []

    def writer():
        try:
            for i in range(40):
                with atomic_folder(target) as tmp:
                    shutil.copytree(b if i % 2 == 0 else a, tmp, dirs_exist_ok=True)  # tmp: made and marked
        finally:
            done.set()

    def reader():
        while not done.is_set():
            try:
                loaded = load_bundle(target)
                seen.append(loaded.metadata[METADATA_DIGEST])
                assert loaded.pixels[0].shape[0] >= loaded.tile_size
            except BaseException as e:  # noqa: BLE001 (recorded and reported below)
                errors.append(e)

    threads = [threading.Thread(target=writer)] + [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert seen and set(seen) <= digests


def test_cached_bundle_built_before_sealing_is_rebuilt(tmp_path, monkeypatch):
    from histojax import cache

    monkeypatch.setenv("HISTOJAX_CACHE", str(tmp_path))
    out = cache.cached_bundle(KIDNEY, level_sets=(3,), storage="dense", name="kidney")
    _edit_metadata(out, lambda m: m.pop(METADATA_DIGEST))  # as an older histojax wrote it
    assert cache.cached_bundle(KIDNEY, level_sets=(3,), storage="dense", name="kidney") == out
    assert METADATA_DIGEST in _meta(out)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_bundle(out)


# --------------------------------------------------------------------------- item 14: what the budget bounds
def test_device_budget_error_says_what_it_bounds(bundle):
    import histojax

    with pytest.raises(BundleError, match="bounds the arrays put on the device, not host memory"):
        histojax.make("HistoJAX-Easy-v0", slide=bundle, max_device_bytes=10**6)


def test_a_file_vanishing_mid_swap_is_read_again(tmp_path):
    """The CI failure of the test above: a reader's ``open`` met the instant between the old folder's rename
    aside and the new one's rename into place (``FileNotFoundError``, not a ``BundleError``). ``stable_read``
    reads again while a rebuild is under way, and raises at once when none is."""
    from data_tools.bundle_files.safe_files import stable_read

    target = tmp_path / "live"
    target.mkdir()
    aside = tmp_path / ".live.old-0badf00d"  # what atomic_folder leaves beside it during the swap
    calls = []

    def read():
        calls.append(1)
        if len(calls) == 1:
            aside.mkdir()
            raise FileNotFoundError(2, "No such file or directory", str(target / "levels_00.npy"))
        aside.rmdir()
        return "whole"

    assert stable_read(target, read) == "whole" and len(calls) == 2

    def missing():
        raise FileNotFoundError(2, "No such file or directory", str(target / "levels_00.npy"))

    with pytest.raises(FileNotFoundError):  # no rebuild in sight: the error is the bundle's own
        stable_read(target, missing)
