"""The cohort path's inputs: discovery never opens a FIFO and
never loops, a loose DICOM file keeps its folder's other slides, TIFF-based extensions are read and other
formats listed as skipped; label tables name their encoding problems and case-folded duplicates;
imported ``.h5`` features are checked from their shapes before anything is read, bounded in host memory,
refused when empty, mixed or off the slide, and warned about when they cover little of the tissue.

Hang tests run in a subprocess with a timeout, so a regression fails instead of hanging the suite.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.datasets.discover import discover
from data_tools.datasets.split import read_label_table
from data_tools.errors import HistojaxDataError

h5py = pytest.importorskip("h5py")

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).parents[1] / "data"
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
posix_only = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs and symlinks need a POSIX file system")


def _tif(path: Path, size=(96, 128)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(path, np.full((*size, 3), 200, np.uint8), tile=(32, 32), photometric="rgb")
    return path


def _asap(path: Path) -> Path:
    path.write_text(
        '<ASAP_Annotations><Annotations><Annotation Name="a" Type="Polygon" PartOfGroup="metastasis">'
        '<Coordinates><Coordinate Order="0" X="1" Y="1" /><Coordinate Order="1" X="20" Y="1" />'
        '<Coordinate Order="2" X="20" Y="20" /></Coordinates></Annotation></Annotations>'
        "</ASAP_Annotations>"
    )
    return path


def _run(script: str, timeout: float = 60) -> str:
    """Run ``script`` in a fresh interpreter; a hang past ``timeout`` s is a test failure, not a stuck suite."""
    try:
        proc = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(script)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=ENV,
            cwd=ROOT,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung for {timeout} s (killed)")
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


# ------------------------------------------------------------------ 6. FIFOs and symlink loops
@posix_only
def test_fifos_named_like_a_slide_annotation_labels_or_features_are_never_opened(tmp_path):
    """Was: ``mkfifo SLIDES/p.tif`` hung ``histojax dataset`` (killed at 60 s); a FIFO ``q.xml`` hung
    discovery itself. Now a FIFO is listed as skipped and every reader refuses it without opening it."""
    slides = tmp_path / "S"
    _tif(slides / "s1.tif")
    for name in ("p.tif", "q.xml", "labels.csv", "f.h5"):
        os.mkfifo(slides / name)
    out = _run(f"""
        import warnings
        from pathlib import Path
        from data_tools.datasets.discover import discover
        from data_tools.datasets.split import read_label_table
        from data_tools.errors import HistojaxDataError
        from data_tools.features.hdf5 import read_patch_features
        from data_tools.slide_files.open import open_slide
        S = Path({str(slides)!r})
        skipped = []
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            entries = discover(S, skipped=skipped)
        print("slides", [e.name for e in entries])
        print("skipped", sorted((p.path.name, "FIFO" in p.reason) for p in skipped))
        print("warned", sum("skipped: a FIFO" in str(w.message) for w in caught))
        for fn, arg in ((open_slide, "p.tif"), (read_label_table, "labels.csv"), (read_patch_features, "f.h5")):
            try:
                fn(S / arg)
            except HistojaxDataError as e:
                print("refused", arg, e.path == str(S / arg), "regular file" in str(e))
    """)
    assert "slides ['s1']" in out
    assert "skipped [('f.h5', True), ('labels.csv', True), ('p.tif', True), ('q.xml', True)]" in out
    assert "warned 4" in out
    for name in ("p.tif", "labels.csv", "f.h5"):
        assert f"refused {name} True True" in out, out


@posix_only
def test_symlink_loops_are_named_skipped_and_never_make_twins(tmp_path):
    """Was: two self-links (``ln -s . S/e/a; ln -s . S/e/b``) hung discovery (killed at 90 s); one self-link
    made "two slides named 's2'". Now each folder is searched once and the links are named as loops."""
    slides = tmp_path / "S"
    _tif(slides / "s1.tif")
    _tif(slides / "e" / "s2.tif")
    os.symlink(".", slides / "e" / "a")
    os.symlink(".", slides / "e" / "b")
    os.symlink("../e", slides / "e" / "up")
    os.symlink("y", slides / "x")  # links that lead back to each other
    os.symlink("x", slides / "y")
    os.symlink("gone", slides / "dangling.tif")
    out = _run(f"""
        from pathlib import Path
        from data_tools.datasets.discover import discover
        skipped = []
        entries = discover(Path({str(slides)!r}), skipped=skipped, warn_skipped=False)
        print("slides", [e.name for e in entries])
        print("skipped", sorted((s.path.name, "symlink loop" in s.reason) for s in skipped))
        print("broken", [s.path.name for s in skipped if "broken link" in s.reason])
    """)
    assert "slides ['s1', 's2']" in out
    assert "skipped [('a', True), ('b', True), ('dangling.tif', False), ('up', True), ('x', True), ('y', True)]" in out
    assert "broken ['dangling.tif']" in out


@posix_only
def test_a_link_to_a_folder_searched_elsewhere_is_used_once(tmp_path):
    slides = tmp_path / "S"
    _tif(slides / "site" / "s1.tif")
    os.symlink("site", slides / "again")
    os.symlink("site/s1.tif", slides / "s1-link.tif")  # a file reached twice
    skipped = []
    entries = discover(slides, skipped=skipped, warn_skipped=False)
    assert [e.name for e in entries] == ["s1"]
    reasons = {s.path.name: s.reason for s in skipped}
    assert "searched once" in reasons["again"] and "used once" in reasons.get("s1.tif", reasons.get("s1-link.tif"))


# ------------------------------------------------------------------ 14. a loose .dcm keeps its folder
def test_a_loose_dcm_file_does_not_swallow_its_folder(tmp_path):
    """Was: one ``.dcm`` beside SVS / TIFF slides made the folder one DICOM slide named after it; the other
    slides, their annotations and the sub-folders were dropped, exit 0. Now they are all still found."""
    slides = tmp_path / "cohort"
    for name in ("a.tif", "b.svs", "c.tiff", "sub/d.tif"):
        _tif(slides / name)
    _asap(slides / "a.xml")
    shutil.copy(DATA / "dicom-wsi" / "level0.dcm", slides / "stray.dcm")
    entries = {e.name: e for e in discover(slides, warn_skipped=False)}
    assert sorted(entries) == ["a", "b", "c", "cohort", "d"]
    assert entries["cohort"].path == slides and entries["a"].annotation == slides / "a.xml"
    assert entries["a"].label == 1 and entries["b"].label == 0


def test_a_dicom_series_folder_is_one_slide(tmp_path):
    series = tmp_path / "S" / "case-7"
    shutil.copytree(DATA / "dicom-wsi", series)
    _tif(tmp_path / "S" / "other.tif")
    uids = tmp_path / "S" / "export"  # a PACS export: files named by their UID, no .dcm
    uids.mkdir()
    for k, f in enumerate(sorted((DATA / "dicom-wsi").iterdir())):
        shutil.copy(f, uids / f"1.2.826.0.1.3680043.8.498.{k}")
    (uids / "README").write_text("exported")
    skipped = []
    entries = discover(tmp_path / "S", skipped=skipped, warn_skipped=False)
    assert [(e.name, e.path) for e in entries] == [
        ("case-7", series),
        ("export", uids),
        ("other", tmp_path / "S" / "other.tif"),
    ]
    assert [s.path.name for s in skipped] == ["README"]


# ------------------------------------------------------------------ 15. TIFF-based extensions, skipped list
def test_tiff_based_extensions_are_read_and_other_formats_listed_as_skipped(tmp_path):
    """Was: ``.qptiff`` (and BigTIFF ``.btf`` / ``.tf8``) were passed over without a word, as were MIRAX and
    other formats histojax cannot read. Now the TIFF-based ones are slides (and MIRAX, read through OpenSlide); the
    rest are listed with why."""
    from data_tools.slide_files.open import open_slide

    slides = tmp_path / "S"
    _tif(slides / "akoya.qptiff")
    _tif(slides / "big.btf")
    tifffile.imwrite(slides / "big8.tf8", np.full((64, 64, 3), 200, np.uint8), bigtiff=True, photometric="rgb")
    for name in ("m.mrxs", "o.vsi", "z.czi", "notes.txt"):
        (slides / name).write_text("x")
    (slides / "m").mkdir()  # a MIRAX slide's data folder: part of the slide, not searched
    (slides / "m" / "Slidedat.ini").write_text("x")
    (slides / "meta.json").write_text('{"not": "an annotation"}')
    skipped = []
    with pytest.warns(UserWarning, match=r"o\.vsi: skipped: a Olympus VSI slide"):
        entries = discover(slides, skipped=skipped)
    assert [e.name for e in entries] == ["akoya", "big", "big8", "m"]
    with open_slide(entries[2].path) as reader:
        assert reader.dimensions == (64, 64)
    reasons = {s.path.name: s.reason for s in skipped}
    assert sorted(reasons) == ["meta.json", "notes.txt", "o.vsi", "z.czi"]
    assert "Olympus VSI" in reasons["o.vsi"] and "Zeiss CZI" in reasons["z.czi"]
    assert "not an ASAP XML, GeoJSON or NCRF" in reasons["meta.json"]


# ------------------------------------------------------------------ 9, 17. label tables
def test_labels_differing_only_in_case_are_refused_naming_both_rows(tmp_path):
    """Was: ``S1,1`` and ``s1,0`` for one slide gave exit 0 with label 0 (the later row won silently)."""
    p = tmp_path / "labels.csv"
    p.write_text("slide,label\nS1,1\ns1,0\n")
    with pytest.raises(HistojaxDataError, match=r"labels\.csv: rows 2 \('S1', label 1\) and 3 \('s1', label 0\)"):
        read_label_table(p)
    p.write_text("slide,label,split\nS1,1,train\ns1.tif,1,test\n")
    with pytest.raises(HistojaxDataError, match=r"rows 2 .* and 3 .*different splits"):
        read_label_table(p)
    p.write_text("slide,label\nS1,1\ns1,tumour\n")  # the same label twice: one slide
    assert read_label_table(p) == ({"S1": 1}, {})


def test_the_label_table_and_reference_csv_in_the_slides_folder_are_not_skipped(tmp_path):
    _tif(tmp_path / "S" / "s1.tif")
    (tmp_path / "S" / "labels.csv").write_text("s1,1\n")
    (tmp_path / "S" / "other.csv").write_text("s1,1\n")
    skipped = []
    assert (
        discover(tmp_path / "S", labels_csv=tmp_path / "S" / "labels.csv", skipped=skipped, warn_skipped=False)[0].label
        == 1
    )
    assert [s.path.name for s in skipped] == ["other.csv"] and "--labels" in skipped[0].reason


def test_labels_through_discovery_with_case_folded_twins(tmp_path):
    _tif(tmp_path / "S" / "S1.tif")
    (tmp_path / "labels.csv").write_text("S1,1\ns1,0\n")
    with pytest.raises(HistojaxDataError, match="labels.csv: rows 1 .* and 2 .* different labels"):
        discover(tmp_path / "S", labels_csv=tmp_path / "labels.csv", warn_skipped=False)


@pytest.mark.parametrize(
    "encoding, ok", [("utf-8-sig", True), ("utf-16", True), ("latin-1", False), ("utf-16-le", False), ("cp1252", False)]
)
def test_label_table_encodings_are_read_or_named(tmp_path, encoding, ok):
    """Was: a UTF-16 or Latin-1 table gave "'utf-8' codec can't decode byte 0xff" with no file named."""
    p = tmp_path / "labels.csv"
    p.write_bytes("slide,label\nbiopsie_é,1\nS2,0\n".encode(encoding))
    if ok:
        assert read_label_table(p) == ({"biopsie_é": 1, "S2": 0}, {})
    else:
        with pytest.raises(HistojaxDataError, match=r"labels\.csv: the label table .*(UTF-8|NUL)") as e:
            read_label_table(p)
        assert e.value.path == str(p)


def test_a_label_table_that_is_not_csv(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("slide,label\n" + "a" * 200_000 + ",1\n")  # a field over the csv module's limit
    with pytest.raises(HistojaxDataError, match=r"labels\.csv: not a readable CSV table"):
        read_label_table(p)


# ------------------------------------------------------------------ 7, 11, 17. imported .h5 features
SIZE = (384, 512)  # H, W level-0 px
TILE = 32


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    """A 512 × 384 px slide: white glass with a pink tissue block over x 64..448, y 64..320; 32-px views,
    3 zoom levels (downsamples 1, 2, 4)."""
    from data_tools.bundle import build_bundle

    root = tmp_path_factory.mktemp("cohort-bundle")
    rng = np.random.default_rng(0)
    image = np.full((*SIZE, 3), 244, np.uint8)
    image[64:320, 64:448] = [190, 80, 150]
    image = (image.astype(np.int16) + rng.integers(-4, 5, image.shape)).clip(0, 255).astype(np.uint8)
    tifffile.imwrite(root / "slide.tif", image, photometric="rgb", tile=(64, 64))
    return build_bundle(root / "slide.tif", root / "bundle", level_sets=(3,), tile_size=TILE, progress=False)


def _work(bundle: Path, tmp_path: Path) -> Path:
    dest = tmp_path / "b"
    shutil.rmtree(dest, ignore_errors=True)
    return Path(shutil.copytree(bundle, dest))


def _h5(path: Path, coords, features, **attrs) -> Path:
    with h5py.File(path, "w") as f:
        f.create_dataset("features", data=features)
        c = f.create_dataset("coords", data=coords)
        c.attrs.update(attrs)
    return path


def _tissue_patches(scale: float = 1.0):
    """64-px patches over the tissue block, their corners multiplied by ``scale`` (wrong units)."""
    ys, xs = np.mgrid[64:320:64, 64:448:64]
    coords = np.stack([xs.ravel(), ys.ravel()], 1) * scale
    return coords, np.random.default_rng(1).normal(size=(len(coords), 8)).astype(np.float32)


def test_features_covering_the_tissue_import_without_a_warning(bundle, tmp_path):
    from data_tools.features.hdf5 import import_features

    coords, feats = _tissue_patches()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        info = import_features(_work(bundle, tmp_path), _h5(tmp_path / "s.h5", coords, feats, patch_size=64))
    covered, total = info["import"]["tissue_coverage"]
    assert total > 0 and covered == total


@pytest.mark.parametrize("scale", [2, 3])
def test_coordinates_in_the_wrong_units_warn_with_the_coverage(bundle, tmp_path, scale):
    """Was: coordinates ×10 (1 of 20 cells covered) or ×2 (28 of 160) built with no note. Now a warning naming
    the file says how much of the tissue the patches cover, under the stated 50 %."""
    from data_tools.features.hdf5 import import_features

    coords, feats = _tissue_patches(scale)
    with pytest.warns(UserWarning, match=r"s\.h5: its patches cover \d+ of the \d+ tissue views .*under 50%"):
        info = import_features(_work(bundle, tmp_path), _h5(tmp_path / "s.h5", coords, feats, patch_size=64))
    covered, total = info["import"]["tissue_coverage"]
    assert covered < 0.5 * total


@pytest.mark.parametrize(
    "case, match",
    [
        ("n0", r"holds no patches \(N = 0\)"),
        ("d0", r"features have D = 0 dimensions"),
        ("strings", r"features are not numbers"),
        ("outside", r"none of its 24 patches lies on the slide \(512×384 level-0 px"),
        ("1e300", r"a coordinate is 1e\+300, beyond ±2\^31 level-0 px"),
        ("no-size", r"pass --patch-size P \(px at pyramid level --patch-level L\)"),
        ("attr", r"the 'patch_size' attribute of coords is not a number"),
        ("float16", r"feature values reach [\d.]+e\+0[67], beyond float16's ±65504"),
    ],
)
def test_feature_files_that_cannot_be_right_are_refused_naming_them(bundle, tmp_path, case, match):
    """Was: N = 0 and D = 0 built all-zero grids; coordinates all outside the slide gave "need at least one
    array to concatenate", one at 1e300 "invalid value encountered in cast", string features a raw
    ValueError, features beyond ±65504 were stored as float16 infinities; the hint named ``--level L``, an option ``histojax dataset`` does not have."""
    from data_tools.features.hdf5 import FeatureFileError, import_features

    coords, feats = _tissue_patches()
    attrs = {"patch_size": 64}
    if case == "n0":
        coords, feats = coords[:0], feats[:0]
    elif case == "d0":
        feats = feats[:, :0]
    elif case == "strings":
        feats = np.array([[b"x"] * 8] * len(coords))
    elif case == "outside":
        coords = coords + 10_000
    elif case == "1e300":
        coords = coords.astype(np.float64)
        coords[3, 0] = 1e300
    elif case == "no-size":
        attrs = {}
    elif case == "attr":
        attrs = {"patch_size": "sixty-four"}
    elif case == "float16":  # stored as float16 by default: would be infinite
        feats = feats * 1e6
    h5 = _h5(tmp_path / f"{case}.h5", coords, feats, **attrs)
    work = _work(bundle, tmp_path)
    before = sorted(p.name for p in work.iterdir())
    with pytest.raises(FeatureFileError, match=match) as e:
        import_features(work, h5)
    assert e.value.path == str(h5)
    assert sorted(p.name for p in work.iterdir()) == before  # nothing half-written


def test_a_huge_patch_count_is_refused_from_its_shape_before_reading(bundle, tmp_path):
    """Was: N = 2·10⁷ in a 486 KB gzipped file read 5.9 GB, then a MemoryError traceback. Now the shapes are
    checked against the stated host limit (``MAX_IMPORT_BYTES``, 4 GiB) before any data is read."""
    import tracemalloc

    from data_tools.features.hdf5 import MAX_IMPORT_BYTES, FeatureFileError, import_features

    h5 = tmp_path / "huge.h5"
    with h5py.File(h5, "w") as f:  # never written: the file holds no chunks, a few KB
        f.create_dataset("coords", shape=(20_000_000, 2), dtype="int32", chunks=(65536, 2), compression="gzip")
        f.create_dataset(
            "features", shape=(20_000_000, 64), dtype="float32", chunks=(4096, 64), compression="gzip"
        ).attrs["unused"] = 1
        f["coords"].attrs["patch_size"] = 256
    assert h5.stat().st_size < 100_000
    tracemalloc.start()
    try:
        with pytest.raises(
            FeatureFileError,
            match=r"huge\.h5: 20,000,000 patches × 64 features need 5\.1 GiB .*"
            r"limit of 4\.0 GiB",
        ):
            import_features(_work(bundle, tmp_path), h5)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20 and MAX_IMPORT_BYTES == 4 * 2**30


def test_a_patch_size_in_the_wrong_units_is_refused_before_the_overlap_table(bundle, tmp_path):
    """Was: ``patch_size`` 1e9 made every patch overlap every view: 1.19 GB for a 4.8 MB file, then a
    MemoryError traceback. Now a patch larger than the slide is refused, and the patch–view overlaps are
    counted from N numbers and bounded before the table is built."""
    from data_tools.features.hdf5 import FeatureFileError, import_features, overlap_count

    rng = np.random.default_rng(0)
    n = 200_000
    coords = rng.integers(0, 32, (n, 2)).astype(np.int32)
    assert overlap_count(coords.astype(float), 1e9, (1000, 1000), 128.0, 128.0) == n * 1e6  # no overflow
    small = _h5(tmp_path / "s.h5", coords[:10], np.zeros((10, 1), np.float32), patch_size=1e9)
    with pytest.raises(
        FeatureFileError,
        match=r"s\.h5: a patch of 1e\+09 level-0 px is larger than the whole slide "
        r"\(512×384 level-0 px\)",
    ):
        import_features(_work(bundle, tmp_path), small)
    big = _h5(tmp_path / "big.h5", coords, np.zeros((n, 1), np.float32), patch_size=300)
    with pytest.raises(
        FeatureFileError,
        match=r"big\.h5: its 200,000 patches of 300 level-0 px overlap [\d,]+ "
        r"views of a 12×16 grid: \d+\.\d GiB .*limit of 0\.1 GiB",
    ):
        import_features(_work(bundle, tmp_path), big, max_bytes=100 * 2**20)
    with pytest.raises(FeatureFileError, match=r"patch extent 1e\+10 level-0 px is not in \(0, 2\^31\)"):
        import_features(
            _work(bundle, tmp_path), _h5(tmp_path / "b2.h5", coords[:10], np.zeros((10, 1)), patch_size=1e10)
        )


def test_mixed_feature_dimensions_are_refused_naming_two_files(tmp_path):
    from data_tools.features.hdf5 import FeatureFileError, check_feature_dims

    coords, feats = _tissue_patches()
    a = _h5(tmp_path / "a.h5", coords, feats)
    b = _h5(tmp_path / "b.h5", coords, feats[:, :4])
    c = _h5(tmp_path / "c.h5", coords, feats)
    check_feature_dims([a, c])
    with pytest.raises(FeatureFileError, match=r"b\.h5: has D = 4 features but .*a\.h5 has D = 8"):
        check_feature_dims([a, b, c])


def test_import_features_takes_patch_level(bundle, tmp_path, capsys):
    """The hint and ``histojax dataset`` say ``--patch-level``; ``import-features`` takes it too (``--level``
    still works)."""
    from data_tools.__main__ import main

    coords, feats = _tissue_patches()
    h5 = _h5(tmp_path / "s.h5", coords, feats)
    work = _work(bundle, tmp_path)
    assert main(["import-features", str(work), str(h5), "--patch-size", "64", "--patch-level", "0"]) == 0
    assert main(["import-features", str(work), str(h5)]) == 2
    assert "--patch-level L" in capsys.readouterr().err


# ------------------------------------------------------------------ the command, end to end
@pytest.fixture(scope="module")
def tissue_tif(tmp_path_factory) -> Path:
    """A 512 × 512 px crop of the sample slide's tissue (real H&E pixels), tiled TIFF."""
    from histojax.sample import SAMPLE_SLIDE

    with tifffile.TiffFile(SAMPLE_SLIDE) as tif:
        pixels = tif.pages[0].asarray()[800:1312, 800:1312, :3]
    path = tmp_path_factory.mktemp("tissue") / "crop.tif"
    tifffile.imwrite(path, np.ascontiguousarray(pixels), tile=(128, 128), photometric="rgb")
    return path


def _dataset_cli(args, timeout=240):
    try:
        return subprocess.run(
            [sys.executable, "-m", "data_tools", "dataset", *map(str, args)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=ENV,
            cwd=ROOT,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"histojax dataset hung for {timeout} s (killed)")


@posix_only
def test_the_dataset_command_with_a_fifo_a_loop_and_other_formats(tissue_tif, tmp_path):
    """Was: hung (FIFO p.tif, killed at 60 s; two self-links, killed at 90 s). Now it builds the one real slide,
    exit 0, with one ``warning:`` line per file or folder skipped, saying why."""
    slides = tmp_path / "S"
    (slides / "e").mkdir(parents=True)
    shutil.copy(tissue_tif, slides / "e" / "s1.tif")
    os.mkfifo(slides / "p.tif")
    os.symlink(".", slides / "e" / "a")
    os.symlink(".", slides / "e" / "b")
    (slides / "x.vsi").write_text("x")
    proc = _dataset_cli([slides, "--out", tmp_path / "o", "--levels", "3", "--quiet", "--test-fraction", "0"])
    assert proc.returncode == 0, proc.stderr
    warned = [line for line in proc.stderr.splitlines() if line.startswith("warning: ") and "skipped" in line]
    assert len(warned) == 4, proc.stderr
    assert any("p.tif: skipped: a FIFO" in w for w in warned) and any(
        "x.vsi: skipped: a Olympus VSI" in w for w in warned
    )
    assert sum("symlink loop" in w for w in warned) == 2
    import json

    assert json.loads((tmp_path / "o" / "dataset.json").read_text())["labels"] == {"s1": 0}


def test_the_dataset_command_refuses_feature_files_of_two_encoders(tissue_tif, tmp_path):
    """Was: slides imported with D = 8 and D = 4 built one dataset of mixed dimensions without a word."""
    slides, feats = tmp_path / "S", tmp_path / "feats"
    slides.mkdir()
    feats.mkdir()
    coords, f8 = _tissue_patches()
    for name, d in (("a", 8), ("b", 4)):
        shutil.copy(tissue_tif, slides / f"{name}.tif")
        _h5(feats / f"{name}.h5", coords, f8[:, :d], patch_size=64)
    proc = _dataset_cli([slides, "--out", tmp_path / "o", "--levels", "3", "--quiet", "--features-from", feats])
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert re.search(r"^error: .*b\.h5: has D = 4 features but .*a\.h5 has D = 8", proc.stderr, re.M), proc.stderr
    assert not (tmp_path / "o" / "bundles").exists()
