"""Nothing lost where users now work, the dataset side: reruns of ``histojax dataset`` / ``c16`` remove only the
temporaries histojax marked as its own, ``build --overwrite`` removes only histojax's files in ``features.partial/``,
every reader of a dataset checks the ``dataset.json`` seal, a corrupt bundle is rebuilt by a rerun, two runs with
different options do not share a folder, an own encoder's overflowing or exiting output is refused, imported
``.h5`` coordinates that miss most of the tissue are reported, and the dataset command's words.

Stand-in slides are small pyramidal TIFFs cut from the real pixels of the embedded CMU-1-Small-Region.svs
(CC0 1.0, see tests/data/LICENSES.md).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from slide_helpers import crop, pyramid, sample_pixels

from data_tools.__main__ import main as data_main
from data_tools.bundle_files.writes import mark_temporary
from data_tools.datasets.build import build_dataset

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def pixels():
    return sample_pixels()


@pytest.fixture(scope="module")
def cohort(tmp_path_factory, pixels):
    """Three slides with a label table giving the split: s1, s2 train, s3 test."""
    root = tmp_path_factory.mktemp("cohort38")
    for i, name in enumerate(("s1", "s2", "s3")):
        pyramid(root / "slides" / f"{name}.tif", crop(pixels, i))
    (root / "labels.csv").write_text("slide,label,split\ns1,0,train\ns2,0,train\ns3,1,test\n")
    return root / "slides", root / "labels.csv"


@pytest.fixture(scope="module")
def built(tmp_path_factory, cohort):
    """The cohort built once (levels 3)."""
    slides, labels = cohort
    out = tmp_path_factory.mktemp("built38") / "o"
    s = build_dataset(slides, out, labels=labels, levels=(3,), progress=False)
    assert s["dataset"] is not None and not s["failed"], s
    return out


def _run(argv, capsys) -> tuple[int, str, str]:
    code = data_main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _one_error(argv, capsys) -> str:
    code, _, err = _run(argv, capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def _users_entries(folder: Path) -> dict[str, str]:
    """The entries of the issue's repro: a user's files under names of histojax's temporaries."""
    (folder / ".notes.tmp-12345678").mkdir(parents=True)
    (folder / ".notes.tmp-12345678" / "thesis.txt").write_text("chapter 1")
    (folder / ".a.old-1").mkdir()
    (folder / ".a.old-1" / "thesis.txt").write_text("chapter 2")
    (folder / ".zz.tmp-1234").mkdir()
    (folder / ".c.tmp-abcdefgh").write_text("chapter 3")
    (folder / ".notes.old-1").mkdir()
    (folder / ".notes.old-1" / "draft.txt").write_text("chapter 4")
    return {
        str(p.relative_to(folder)): (p.read_text() if p.is_file() else "<dir>")
        for p in folder.rglob("*")
        if p.name.startswith(".") or p.parent.name.startswith(".")
    }


def _same(folder: Path, before: dict[str, str]) -> None:
    for rel, content in before.items():
        p = folder / rel
        assert p.exists(), f"{rel} was removed"
        assert (p.read_text() if p.is_file() else "<dir>") == content
    assert not (folder / "notes").exists() and not (folder / "a").exists()  # nothing renamed


# ------------------------------------------------------------------ 1. reruns delete only marked temporaries
def test_a_dataset_rerun_keeps_the_users_entries_named_like_temporaries(built, cohort, tmp_path):
    slides, labels = cohort
    work = tmp_path / "o"
    shutil.copytree(built, work)
    before = _users_entries(work / "bundles")
    records = _users_entries(work / "records")
    ours = mark_temporary(work / "bundles" / ".s9.tmp-0badf00d")  # a killed build's temporary: removed
    (ours / "levels_00.npy").write_bytes(b"\0" * 100)
    s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False)
    assert sorted(s["resumed"]) == ["s1", "s2", "s3"] and s["dataset"] is not None
    _same(work / "bundles", before)  # before: every one deleted, .notes.old-1 renamed to bundles/notes
    _same(work / "records", records)
    assert not ours.exists()


def test_c16_cleaning_keeps_the_users_entries_named_like_temporaries(tmp_path):
    from data_tools.datasets.c16.dataset import clean_stale

    before = _users_entries(tmp_path / "bundles")
    slides = _users_entries(tmp_path / "slides")
    ours = mark_temporary(tmp_path / "slides" / ".Tumor_001.tif.tmp-0badf00d")
    aside = mark_temporary(tmp_path / "bundles" / ".Tumor_001.old-0badf00d")  # killed mid-swap: put back
    (aside / "metadata.json").write_text("{}")
    removed = clean_stale(tmp_path)
    _same(tmp_path / "bundles", before)
    _same(tmp_path / "slides", slides)
    assert not ours.exists() and "slides/.Tumor_001.tif.tmp-0badf00d" in removed
    assert sorted(p.name for p in (tmp_path / "bundles" / "Tumor_001").iterdir()) == ["metadata.json"]


def test_a_bundle_build_keeps_a_users_folder_named_like_its_temporary(cohort, tmp_path):
    from data_tools.bundle import build_bundle

    slides, _ = cohort
    (tmp_path / ".b.tmp-12345678").mkdir()
    (tmp_path / ".b.tmp-12345678" / "thesis.txt").write_text("t")
    (tmp_path / ".b.old-0badf00d").mkdir()
    (tmp_path / ".b.old-0badf00d" / "metadata.json").write_text("{}")
    build_bundle(slides / "s1.tif", tmp_path / "b", level_sets=(3,), progress=False)
    build_bundle(slides / "s1.tif", tmp_path / "b", level_sets=(3,), progress=False, overwrite=True)
    assert (tmp_path / ".b.tmp-12345678" / "thesis.txt").read_text() == "t"
    assert (tmp_path / ".b.old-0badf00d" / "metadata.json").read_text() == "{}"
    assert not any(p.name.startswith(".histojax") for p in (tmp_path / "b").iterdir())  # no marker stays
    assert sorted(p.name for p in tmp_path.iterdir()) == [".b.old-0badf00d", ".b.tmp-12345678", "b"]


# ------------------------------------------------------------------ 5. build --overwrite and features.partial
def test_build_overwrite_keeps_a_users_file_in_features_partial(cohort, tmp_path, capsys):
    slides, _ = cohort
    out = tmp_path / "b"
    code, _, err = _run(["build", str(slides / "s1.tif"), "--out", str(out), "--levels", "3", "--quiet"], capsys)
    assert code == 0, err
    (out / "features.partial").mkdir()
    (out / "features.partial" / "000000.npy").write_bytes(b"\0" * 10)
    (out / "features.partial" / "thesis.txt").write_text("t")
    line = _one_error(
        ["build", str(slides / "s1.tif"), "--out", str(out), "--levels", "3", "--overwrite", "--quiet"], capsys
    )
    assert "features.partial/thesis.txt" in line and str(out) in line
    assert (out / "features.partial" / "thesis.txt").read_text() == "t"  # before: deleted, rc 0


def test_cleaning_features_partial_removes_only_histojaxs_chunks(built, tmp_path):
    from data_tools.datasets.locks import clean_partial_features

    bundle = tmp_path / "s1"
    shutil.copytree(built / "bundles" / "s1", bundle)
    meta = json.loads((bundle / "metadata.json").read_text())
    (bundle / "metadata.json").write_text(json.dumps({**meta, "features": {"encoder": "colour-stats"}}))
    partial = bundle / "features.partial"
    partial.mkdir()
    (partial / "000000.npy").write_bytes(b"\0" * 10)
    (partial / "settings.json").write_text("{}")
    (partial / "thesis.txt").write_text("t")
    assert not clean_partial_features(bundle)
    assert sorted(p.name for p in partial.iterdir()) == ["thesis.txt"]


# ------------------------------------------------------------------ 7. a corrupt bundle is rebuilt by a rerun
def _flip_a_byte(bundle: Path) -> Path:
    from data_tools.bundle_files.reading import read_metadata

    name = sorted(n for n in read_metadata(bundle)["checksums"] if n.endswith(".npy"))[0]
    data = bytearray((bundle / name).read_bytes())
    data[-1] ^= 0xFF
    (bundle / name).write_bytes(bytes(data))
    return bundle / name


@pytest.mark.parametrize("restart", [False, True])
def test_a_dataset_rerun_rebuilds_a_bundle_whose_checksum_does_not_match(built, cohort, tmp_path, restart):
    from data_tools.bundle_files.reading import load_bundle
    from data_tools.errors import BundleError

    slides, labels = cohort
    work = tmp_path / "o"
    shutil.copytree(built, work)
    _flip_a_byte(work / "bundles" / "s1")
    with pytest.raises(BundleError, match="checksum mismatch"):
        load_bundle(work / "bundles" / "s1")
    s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False, restart=restart)
    assert s["built"] == ["s1"] and sorted(s["resumed"]) == ["s2", "s3"]  # before: 0 built, 3 already done
    load_bundle(work / "bundles" / "s1")
    assert s["dataset"] is not None


@pytest.mark.slow  # about 20 s: two small c16 builds
def test_a_c16_rerun_rebuilds_a_bundle_whose_checksum_does_not_match(tmp_path):
    from data_tools.bundle_files.reading import load_bundle
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path / "c16"
    make_c16_dataset(out, small=True, n_tumour=1, n_normal=1, progress=False)
    bundle = next(p for p in sorted((out / "bundles").iterdir()) if p.is_dir())
    _flip_a_byte(bundle)
    ds = make_c16_dataset(out, small=True, n_tumour=1, n_normal=1, progress=False)
    load_bundle(bundle)  # before: "checksum mismatch": the rerun kept (or hard-linked) the damaged file
    assert ds["run"]["built"] == [bundle.name]


# ------------------------------------------------------------------ 8. two runs of other options, one folder
def test_a_dataset_run_with_other_options_is_refused_while_the_first_holds_the_folder(
    cohort, tmp_path, capsys, monkeypatch
):
    import data_tools.datasets.build as build_module
    from data_tools.bundle_files.reading import read_metadata

    slides, labels = cohort
    out = tmp_path / "o"
    real, second = build_module.build_one, {}

    def build_one(job):  # while the first run builds its first slide, the second starts
        if not second:
            second["started"] = True
            second["code"], _, second["err"] = _run(
                [
                    "dataset",
                    str(slides),
                    "--out",
                    str(out),
                    "--labels",
                    str(labels),
                    "--levels",
                    "3",
                    "--restart",
                    "--tile-size",
                    "64",
                    "--quiet",
                ],
                capsys,
            )
        return real(job)

    monkeypatch.setattr(build_module, "build_one", build_one)
    s = build_dataset(slides, out, labels=labels, levels=(3,), progress=False)
    lines = second["err"].strip().splitlines()
    assert second["code"] == 2 and len(lines) == 1 and "another histojax dataset run" in lines[0], second
    assert str(out) in lines[0]  # before: both exit 0, bundles of two tile sizes, no dataset.json
    assert s["dataset"] is not None and sorted(s["built"]) == ["s1", "s2", "s3"]
    assert {read_metadata(out / "bundles" / n).tile_size for n in ("s1", "s2", "s3")} == {128}
    assert not list(out.glob("*lock"))  # the run lock goes with the run
    monkeypatch.undo()
    code, _, err = _run(
        ["dataset", str(slides), "--out", str(out), "--labels", str(labels), "--levels", "3", "--quiet"], capsys
    )  # the same command again: cooperates (resumes)
    assert code == 0, err


def test_runs_of_one_plan_share_the_folder(built, cohort, tmp_path):
    from data_tools.datasets.locks import RUN_LOCK, RunLock

    slides, labels = cohort
    work = tmp_path / "o"
    shutil.copytree(built, work)
    other = RunLock(work / RUN_LOCK)
    assert other.claim(exclusive=False)  # a shard of the same plan, running
    try:
        s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False)
        assert sorted(s["resumed"]) == ["s1", "s2", "s3"]
    finally:
        other.release()


# ------------------------------------------------------------------ 6. every reader checks the dataset.json seal
def _edit_a_label(work: Path) -> None:
    index = work / "dataset.json"
    ds = json.loads(index.read_text())
    assert ds["labels"]["s1"] == 0 and "dataset_sha256" in ds
    ds["labels"]["s1"] = 1  # the seal left as it was
    index.write_text(json.dumps(ds, indent=1))


def test_every_reader_of_a_dataset_refuses_an_edited_dataset_json(built, tmp_path):
    import histojax
    from baselines.reading.learned_head_fit import read_spec as learned_read_spec
    from baselines.reading.slides import read_spec
    from data_tools.errors import BundleError
    from histojax.datasets import dataset_labels, dataset_slides

    work = tmp_path / "o"
    shutil.copytree(built, work)
    assert len(dataset_slides(work, "train")) == 2 and read_spec(work)["labels"]["s1"] == 0  # sealed, unedited
    _edit_a_label(work)
    for read in (
        lambda: dataset_slides(work, "train"),
        lambda: dataset_labels(work),
        lambda: read_spec(work),
        lambda: learned_read_spec(work),
        lambda: histojax.make("HistoJAX-Easy-v0", dataset=work),
    ):
        with pytest.raises(BundleError) as e:  # before: the edited label was used
            read()
        line = str(e.value)
        assert "\n" not in line and str(work / "dataset.json") in line and "seal" in line


def test_a_seal_removed_by_hand_is_said(built, tmp_path):
    """A dataset.json of a kind histojax seals, with its seal key deleted and a label edited, was read as an
    older unsealed index without a word: now one warning naming the file, once per file."""
    import warnings as _warnings

    from data_tools.datasets import index as dataset_index
    from histojax.datasets import dataset_labels

    work = tmp_path / "unsealed"
    shutil.copytree(built, work)
    index = work / "dataset.json"
    ds = json.loads(index.read_text())
    ds.pop("dataset_sha256")
    ds["labels"]["s1"] = 1
    index.write_text(json.dumps(ds))
    dataset_index._UNSEALED_WARNED.discard(str(index.resolve()))
    with pytest.warns(UserWarning, match="carries no seal") as caught:
        dataset_labels(work)
    line = str(caught[0].message)
    assert "\n" not in line and str(index) in line and "unchecked" in line
    with _warnings.catch_warnings():
        _warnings.simplefilter("error")
        dataset_labels(work)  # said once per file


def test_a_validation_split_of_a_sealed_dataset_reads_and_its_labels_are_checked(built, tmp_path):
    from baselines.validation import write_validation_dataset
    from data_tools.datasets.index import read_dataset_json
    from data_tools.errors import BundleError

    val = write_validation_dataset(built, 0.5, 0, tmp_path / "val")
    assert read_dataset_json(val)["labels"]["s1"] == 0
    ds = json.loads((val / "dataset.json").read_text())
    ds["labels"]["s1"] = 1
    (val / "dataset.json").write_text(json.dumps(ds))
    with pytest.raises(BundleError, match="labels differ"):
        read_dataset_json(val)


# ------------------------------------------------------------------ 9. your own encoder: overflow, SystemExit
OWN_ENCODERS = """
import numpy as np


def huge(images):
    return np.full((len(images), 4), 1e6, np.float32)  # finite float32, infinity in float16


def exits(images):
    raise SystemExit(0)


class Stop(BaseException):
    pass


def stops(images):
    raise Stop("stop")
"""


@pytest.fixture()
def own_encoders(tmp_path, monkeypatch):
    (tmp_path / "own38.py").write_text(OWN_ENCODERS)
    monkeypatch.syspath_prepend(str(tmp_path))
    from data_tools.features.custom import load_custom_encoder

    load_custom_encoder.cache_clear()
    yield "own38"
    load_custom_encoder.cache_clear()


@pytest.fixture(scope="module")
def one_bundle(tmp_path_factory, cohort):
    from data_tools.bundle import build_bundle

    slides, _ = cohort
    return build_bundle(slides / "s1.tif", tmp_path_factory.mktemp("one38") / "b", level_sets=(3,), progress=False)


def test_an_own_encoder_overflowing_float16_is_refused(own_encoders, one_bundle, tmp_path, capsys):
    from data_tools.bundle_files.reading import read_metadata

    bundle = shutil.copytree(one_bundle, tmp_path / "b")
    line = _one_error(["features", str(bundle), "--encoder", f"{own_encoders}:huge", "--quiet"], capsys)
    assert "65504" in line and str(bundle) in line and "own38:huge" in line  # before: rc 0, inf in every cell
    assert read_metadata(bundle).features is None and not list(bundle.glob("features_*.npy"))
    code, _, err = _run(
        ["features", str(bundle), "--encoder", f"{own_encoders}:huge", "--dtype", "float32", "--quiet"], capsys
    )
    assert code == 0, err  # float32 holds them


@pytest.mark.parametrize("fn", ["exits", "stops"])
def test_an_own_encoder_raising_systemexit_does_not_end_features_with_status_0(
    own_encoders, one_bundle, tmp_path, capsys, fn
):
    bundle = shutil.copytree(one_bundle, tmp_path / "b")
    line = _one_error(["features", str(bundle), "--encoder", f"{own_encoders}:{fn}", "--quiet"], capsys)
    assert f"{own_encoders}:{fn}" in line  # before: exit 0 (SystemExit) or a traceback, nothing written


def test_an_own_encoder_raising_systemexit_does_not_end_c16_with_status_0(own_encoders, tmp_path, capsys):
    code, _, err = _run(
        [
            "c16",
            "--small",
            "--slides",
            "Tumor_072",
            "--encoder",
            f"{own_encoders}:exits",
            "--quiet",
            "--out",
            str(tmp_path / "c"),
        ],
        capsys,
    )
    assert code != 0 and "own38:exits" in err and "SystemExit" in err, (code, err)


# ------------------------------------------------------------------ 13. imported features on scattered tissue
def test_imported_features_missing_scattered_tissue_warn_and_record_the_coverage(tmp_path):
    """Tissue in 7-px specks (2.6 % of the tissue mask, no view half tissue): coordinates ×10 cover 1 of the 80
    views holding tissue. Before: no warning and ``tissue_coverage: null``."""
    import h5py

    from data_tools.bundle import build_bundle
    from data_tools.features.hdf5 import import_features

    rng = np.random.default_rng(0)
    image = np.full((768, 1024, 3), 244, np.uint8)
    specks = [(y, x) for y in range(40, 740, 96) for x in range(40, 1000, 96)]
    for y, x in specks:
        image[y : y + 7, x : x + 7] = [120, 30, 110]
    image = (image.astype(np.int16) + rng.integers(-4, 5, image.shape)).clip(0, 255).astype(np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", image, photometric="rgb", tile=(64, 64))
    bundle = build_bundle(tmp_path / "s.tif", tmp_path / "b", level_sets=(3,), tile_size=32, progress=False)
    coords = np.array([(x - 10, y - 10) for y, x in specks], float) * 10  # wrong units
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f.create_dataset("features", data=rng.normal(size=(len(coords), 8)).astype(np.float32))
        f.create_dataset("coords", data=coords).attrs["patch_size"] = 32
    with pytest.warns(UserWarning, match=r"s\.h5: its patches cover \d+ of the \d+ tissue views .*under 50%") as w:
        info = import_features(bundle, tmp_path / "s.h5")
    assert len([x for x in w if "tissue views" in str(x.message)]) == 1 and "\n" not in str(w[0].message)
    covered, total = info["import"]["tissue_coverage"]
    assert total > 0 and covered < 0.5 * total


# ------------------------------------------------------------------ 16. the dataset command's words
def test_an_own_encoder_is_found_in_the_working_folder(tmp_path, monkeypatch):
    """The ``histojax`` script's ``sys.path`` holds its own folder, not the working folder (``python -m`` adds it):
    ``histojax dataset slides/ --encoder my_encoders:uni`` failed even from the module's folder."""
    import os
    import sys

    from data_tools.features.custom import load_custom_encoder

    (tmp_path / "cwd_encoders38.py").write_text(OWN_ENCODERS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", os.getcwd(), str(tmp_path))])
    load_custom_encoder.cache_clear()
    try:
        assert load_custom_encoder("cwd_encoders38:huge").dim == 4
    finally:
        load_custom_encoder.cache_clear()
        sys.modules.pop("cwd_encoders38", None)


def test_an_own_encoder_found_nowhere_says_where_it_was_looked_for(tmp_path, monkeypatch):
    from data_tools.errors import HistojaxDataError
    from data_tools.features.custom import load_custom_encoder

    monkeypatch.chdir(tmp_path)
    with pytest.raises(HistojaxDataError) as e:
        load_custom_encoder("no_such_encoders38:uni")
    line = str(e.value)
    assert str(tmp_path) in line and "no_such_encoders38.py" in line and "\n" not in line


@pytest.mark.parametrize("inside", [False, True])
def test_dataset_out_as_the_folder_of_slides_is_one_clear_line(cohort, tmp_path, capsys, inside):
    slides, labels = cohort
    work = shutil.copytree(slides, tmp_path / "S" / "slides" if inside else tmp_path / "S")
    out = tmp_path / "S"
    line = _one_error(["dataset", str(work), "--out", str(out), "--labels", str(labels), "--quiet"], capsys)
    assert "holds no slides" not in line and "folder of slides" in line and "--out" in line  # before: holds no slides
    assert not (out / "plan.json").exists() and not (out / "bundles").exists()


def test_a_short_write_says_no_space_left_on_device(tmp_path, monkeypatch):
    import errno

    import numpy.lib.format

    from data_tools.bundle_files.writes import save_array

    def short_write(*args, **kwargs):
        raise OSError("2612862 requested and 2514816 written")  # numpy's words on a full disk, no errno

    monkeypatch.setattr(numpy.lib.format, "write_array", short_write)
    with pytest.raises(OSError) as e:
        save_array(tmp_path / "pixels_00.npy", np.zeros((4, 4), np.uint8))
    assert e.value.errno == errno.ENOSPC and "No space left on device" in str(e.value)
    assert e.value.filename == str(tmp_path / "pixels_00.npy") and not list(tmp_path.iterdir())


def test_a_full_disk_during_a_bundle_write_says_no_space_left_on_device(cohort, tmp_path, capsys, monkeypatch):
    import numpy.lib.format

    slides, _ = cohort

    def short_write(*args, **kwargs):
        raise OSError("2612862 requested and 2514816 written")

    monkeypatch.setattr(numpy.lib.format, "write_array", short_write)
    line = _one_error(
        ["build", str(slides / "s1.tif"), "--out", str(tmp_path / "b"), "--levels", "3", "--quiet"], capsys
    )
    assert "No space left on device" in line and str(tmp_path / "b") in line
    assert not (tmp_path / "b").exists() and not list(tmp_path.glob(".b.*"))


def test_the_formats_sentence_names_qptiff_ndpi_and_bigtiff(tmp_path, capsys):
    (tmp_path / "x.svs").write_bytes(b"not a slide at all")
    line = _one_error(["info", str(tmp_path / "x.svs")], capsys)
    assert all(word in line for word in ("QPTIFF", "NDPI", "BigTIFF", "OME-TIFF", "DICOM WSI")), line


def test_a_folder_of_one_failing_qptiff_gets_no_empty_dataset_json(tmp_path, capsys):
    slides = tmp_path / "S"
    slides.mkdir()
    (slides / "p.qptiff").write_bytes(b"II*\x00" + b"\x08\x00\x00\x00" + b"\x00" * 8)  # a TIFF header, no image
    out = tmp_path / "o"
    line = _one_error(["dataset", str(slides), "--out", str(out), "--levels", "3", "--quiet"], capsys)
    assert "p" in line and "dataset.json not written" in line  # before: a 0-slide dataset.json, rc 1
    assert not (out / "dataset.json").exists()
