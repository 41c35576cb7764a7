"""``histojax dataset``: a folder of real slides becomes a dataset, its resume, shards and bad
input, and the leftovers of killed runs.

Stand-in slides are small pyramidal TIFFs cut from the real pixels of CMU-1-Small-Region.svs; the
CAMELYON16 stand-in has the official names and layout, with real CAMELYON16 ASAP XML (tumor_039:
metastasis polygons and exclusion holes) rescaled to fit the small slides and renamed to the
original ``_0`` / ``_2`` groups.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
import tifffile
from slide_helpers import pyramid

from data_tools.__main__ import main as data_main
from data_tools.bundle_files.writes import mark_temporary
from data_tools.datasets.build import build_dataset, merge_dataset
from data_tools.datasets.locks import bundle_lock_path, clean_stale, file_lock
from data_tools.datasets.split import read_label_table, seeded_split, shard_names
from data_tools.errors import BundleError, HistojaxDataError
from histojax.sample import SAMPLE_SLIDE

DATA = Path(__file__).parents[1] / "data"
C16_XML = DATA / "annotations" / "tumor_039.xml"


@pytest.fixture(scope="module")
def pixels():
    with tifffile.TiffFile(SAMPLE_SLIDE) as tif:
        return tif.pages[0].asarray()


def crop(pixels, i: int, size=(640, 512)) -> np.ndarray:
    """A (H, W) = size crop of the real sample pixels (from its tissue-rich middle), different for each ``i``."""
    h, w = size
    y, x = 320 + (i * 160) % 1920, 768 + (i * 64) % 512
    return np.ascontiguousarray(pixels[y : y + h, x : x + w, :3])


def rescaled_xml(src: Path, out: Path, size: tuple[int, int], groups=None) -> Path:
    """``src`` ASAP XML with its coordinates scaled uniformly into ``size = (W, H)`` px (centred, 10 %
    margin) and group names renamed by ``groups``."""
    text = src.read_text()
    xy = np.array([(float(a), float(b)) for a, b in re.findall(r'X="([-\d.eE]+)" Y="([-\d.eE]+)"', text)])
    lo, hi = xy.min(0), xy.max(0)
    s = 0.8 * min(size[0] / (hi - lo)[0], size[1] / (hi - lo)[1])
    off = (np.asarray(size) - s * (hi - lo)) / 2

    def move(m):
        x, y = (np.array([float(m[1]), float(m[2])]) - lo) * s + off
        return f'X="{x:.2f}" Y="{y:.2f}"'

    text = re.sub(r'X="([-\d.eE]+)" Y="([-\d.eE]+)"', move, text)
    for old, new in (groups or {}).items():
        text = text.replace(f'PartOfGroup="{old}"', f'PartOfGroup="{new}"')
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out


@pytest.fixture(scope="module")
def camelyon16(tmp_path_factory, pixels):
    """CAMELYON16 as downloaded, in miniature: training/tumor (2, annotated), training/normal (2),
    training/lesion_annotations, testing/images (2), testing/reference.csv in the official row format."""
    root = tmp_path_factory.mktemp("c16") / "CAMELYON16"
    groups = {"metastasis": "_0", "negative": "_2"}
    for i, name in enumerate(("tumor_001", "tumor_002")):
        pyramid(root / "training" / "tumor" / f"{name}.tif", crop(pixels, i), mpp=0.243)
        rescaled_xml(C16_XML, root / "training" / "lesion_annotations" / f"{name}.xml", (512, 640), groups)
    for i, name in enumerate(("normal_001", "normal_002")):
        pyramid(root / "training" / "normal" / f"{name}.tif", crop(pixels, 4 + i), mpp=0.243)
    for i, name in enumerate(("test_001", "test_002")):
        pyramid(root / "testing" / "images" / f"{name}.tif", crop(pixels, 8 + i), mpp=0.243)
    rescaled_xml(C16_XML, root / "testing" / "lesion_annotations" / "test_001.xml", (512, 640), groups)
    (root / "testing" / "reference.csv").write_text("Test_001,Tumor,Macro,Primary\nTest_002,Normal,,\n")
    return root


@pytest.fixture(scope="module")
def c16_dataset(tmp_path_factory, camelyon16):
    out = tmp_path_factory.mktemp("c16out") / "ds"
    summary = build_dataset(camelyon16, out, levels=(5, 7), progress=False)
    return out, summary


def test_camelyon16_as_downloaded_official_split_and_labels(c16_dataset):
    out, summary = c16_dataset
    assert not summary["failed"] and summary["dataset"] is not None
    ds = json.loads((out / "dataset.json").read_text())
    assert ds["train"] == ["bundles/normal_001", "bundles/normal_002", "bundles/tumor_001", "bundles/tumor_002"]
    assert ds["test"] == ["bundles/test_001", "bundles/test_002"]
    assert ds["labels"] == {
        "normal_001": 0,
        "normal_002": 0,
        "test_001": 1,
        "test_002": 0,
        "tumor_001": 1,
        "tumor_002": 1,
    }
    from data_tools.bundle_files.reading import read_metadata

    meta = read_metadata(out / "bundles" / "tumor_001")
    # _0 → tumour, _2 → exclusion: the exclusion holes are cut out of the tumour
    assert meta.annotations["n_polygons"]["tumour"] > 0 and meta.annotations["n_polygons"]["exclusion"] > 0
    assert not list(out.rglob("*.lock")) and not list(out.rglob("*lock"))  # no lock files after a run


def test_registered_c16_ids_accept_such_a_dataset(c16_dataset):
    import histojax

    out, _ = c16_dataset
    env, params = histojax.make("HistoJAX-C16-Hard-v0", dataset=out, verify=False)
    assert params.slide.num_slides == 4
    env, params = histojax.make("HistoJAX-C16-Diagnosis-v0", dataset=out, split="test", verify=False)
    assert [int(v) for v in params.slide.slide_label] == [1, 0]  # reference.csv's labels
    with pytest.raises(
        BundleError, match="observes pcam-cnn features.*histojax dataset SLIDES_DIR .*--encoder pcam-cnn"
    ):
        histojax.make("HistoJAX-C16-Hard-v1", dataset=out, verify=False)  # no feature grids: the fix named


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_v1_ids_take_scanned_slides_embedded_with_pcam_cnn(camelyon16, tmp_path):
    """The v1 ids' disjoint-patch-pool format concerns the c16 mosaics; scanned slides embedded with pcam-cnn
    (feature-only bundles) are what they observe."""
    import histojax

    out = tmp_path / "v1"
    summary = build_dataset(camelyon16, out, levels=(5, 7), encoder="pcam-cnn", no_pixels=True, progress=False)
    assert not summary["failed"] and summary["dataset"]["encoder"] == "pcam-cnn"
    env, params = histojax.make("HistoJAX-C16-Hard-v1", dataset=out, verify=False)
    obs, _ = env.reset(jax.random.key(0), params)
    assert params.slide.num_slides == 4 and obs.shape[-1] == 64  # every train slide, pcam-cnn features


def test_rerun_resumes_and_a_killed_build_is_finished(c16_dataset, tmp_path):
    out, _ = c16_dataset
    work = tmp_path / "ds"
    shutil.copytree(out, work)
    root = Path(json.loads((work / "plan.json").read_text())["slides"]["tumor_001"]["path"])
    # a kill during tumor_002: its record gone, a half-written temporary and a stale features folder left
    (work / "records" / "tumor_002.json").unlink()
    shutil.rmtree(work / "bundles" / "tumor_002")
    mark_temporary(work / "bundles" / ".tumor_002.tmp-dead0001")
    (work / "bundles" / ".tumor_002.tmp-dead0001" / "levels_00.npy").write_bytes(b"x" * 100)
    mark_temporary(work / "bundles" / ".other.tmp-dead0002")  # a leftover of a name not built again
    (work / "dataset.json").unlink()
    slides_dir = out.parent.parent / "c16" / "CAMELYON16"
    slides_dir = next(out.parent.parent.glob("c16*/CAMELYON16"))
    summary = build_dataset(slides_dir, work, levels=(5, 7), progress=False)
    assert summary["built"] == ["tumor_002"] and len(summary["resumed"]) == 5
    assert (work / "dataset.json").is_file()
    assert not list((work / "bundles").glob(".*tmp-*")), "stale temporaries of any name are removed"
    assert root.name == "tumor_001.tif"


def test_other_options_on_an_existing_dataset_are_refused(c16_dataset, tmp_path):
    out, _ = c16_dataset
    work = tmp_path / "ds"
    shutil.copytree(out, work)
    slides_dir = next(out.parent.parent.glob("c16*/CAMELYON16"))
    with pytest.raises(HistojaxDataError, match=r"started with other options \(options \['levels'\]\)"):
        build_dataset(slides_dir, work, levels=(3, 5, 7), progress=False)


def test_shards_are_disjoint_and_the_last_writes_dataset_json(camelyon16, tmp_path):
    out = tmp_path / "ds"
    names = [p.stem for p in camelyon16.rglob("*.tif")]
    parts = [shard_names(names, (i, 3)) for i in range(3)]
    assert sorted(sum(parts, [])) == sorted(names) and all(parts)
    s0 = build_dataset(camelyon16, out, levels=(3,), shard=(0, 3), progress=False)
    assert s0["dataset"] is None and not (out / "dataset.json").exists()
    assert sorted(p.name for p in (out / "bundles").iterdir()) == sorted(parts[0])
    assert merge_dataset(out)[1] == sorted(parts[1] + parts[2])  # --merge before the others: missing listed
    assert data_main(["dataset", "--merge", "--out", str(out)]) == 2
    build_dataset(camelyon16, out, levels=(3,), shard=(2, 3), progress=False)
    s1 = build_dataset(camelyon16, out, levels=(3,), shard=(1, 3), progress=False)
    assert s1["dataset"] is not None and len(s1["dataset"]["train"]) + len(s1["dataset"]["test"]) == 6
    assert data_main(["dataset", "--merge", "--out", str(out)]) == 0


def test_a_bundle_locked_by_another_process_is_skipped(camelyon16, tmp_path):
    out = tmp_path / "ds"
    with file_lock(bundle_lock_path(out / "bundles" / "normal_001")):
        s = build_dataset(camelyon16, out, levels=(3,), progress=False)
        assert s["busy"] == ["normal_001"] and s["dataset"] is None
        assert not (out / "bundles" / "normal_001").exists()
    s = build_dataset(camelyon16, out, levels=(3,), progress=False)
    assert s["built"] == ["normal_001"] and s["dataset"] is not None


def test_clean_stale_leaves_a_live_build_alone(tmp_path):
    bundles = tmp_path / "bundles"
    mark_temporary(bundles / ".live.tmp-00000001")
    mark_temporary(bundles / ".dead.tmp-00000002")
    (bundles / "done" / "features.partial").mkdir(parents=True)  # empty, left by a kill + rerun
    (bundles / "done" / "metadata.json").write_text('{"features": {"encoder": "colour-stats"}}')
    with file_lock(bundle_lock_path(bundles / "live")):
        removed = clean_stale(bundles)
    assert sorted(removed) == [".dead.tmp-00000002", "done/features.partial"]
    assert (bundles / ".live.tmp-00000001").is_dir()


# ----------------------------------------------------------------------------- every real format, features
@pytest.fixture(scope="module")
def mixed(tmp_path_factory, pixels):
    """Every real slide format of tests/data in one folder (SVS, stripped TIFF, DICOM WSI folder, a
    pyramidal TIFF), an ASAP XML for the SVS, and TRIDENT-style .h5 features for each."""
    import h5py

    root = tmp_path_factory.mktemp("mixed")
    slides = root / "slides"
    (slides / "aperio").mkdir(parents=True)
    shutil.copy(SAMPLE_SLIDE, slides / "aperio" / "CMU-1-Small-Region.svs")
    shutil.copy(SAMPLE_SLIDE.with_name("CMU-1-Small-Region.target.xml"), slides / "aperio" / "CMU-1-Small-Region.xml")
    shutil.copy(DATA / "kidney-48-5_IHC.tif", slides / "kidney-48-5_IHC.tif")
    shutil.copytree(DATA / "dicom-wsi", slides / "dicom" / "case-7")
    pyramid(slides / "pyr" / "crop-3.tif", crop(pixels, 3))
    feats = root / "trident" / "20x_256px_0px_overlap" / "features_conch_v15"
    feats.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name, (w, h) in (
        ("CMU-1-Small-Region", (2220, 2967)),
        ("kidney-48-5_IHC", (1493, 901)),
        ("case-7", (1024, 768)),
        ("crop-3", (512, 640)),
    ):
        xs, ys = np.meshgrid(np.arange(0, w, 256), np.arange(0, h, 256))
        coords = np.stack([xs.ravel(), ys.ravel()], 1)
        with h5py.File(feats / f"{name}.h5", "w") as f:
            f.create_dataset("features", data=rng.normal(size=(len(coords), 16)).astype(np.float32))
            c = f.create_dataset("coords", data=coords)
            c.attrs["patch_size"] = 256
            c.attrs["patch_level"] = 0
    return slides, root / "trident"


def test_every_real_format_in_one_folder_with_trident_features(mixed, tmp_path):
    slides, trident = mixed
    out = tmp_path / "ds"
    code = data_main(
        [
            "dataset",
            str(slides),
            "--out",
            str(out),
            "--levels",
            "3",
            "--features-from",
            str(trident),
            "--no-pixels",
            "--quiet",
            "--test-fraction",
            "0.5",
        ]
    )
    assert code == 0
    ds = json.loads((out / "dataset.json").read_text())
    assert sorted(ds["labels"]) == ["CMU-1-Small-Region", "case-7", "crop-3", "kidney-48-5_IHC"]
    assert ds["labels"]["CMU-1-Small-Region"] == 1 and sum(ds["labels"].values()) == 1  # annotated → tumour
    formats = {r["name"]: r["format"] for r in ds["slides"]}
    assert formats["case-7"].startswith("dicom") and formats["CMU-1-Small-Region"] == "aperio-svs"
    layout = "imported:20x_256px_0px_overlap/features_conch_v15/*.h5"  # the folder and layout, one name for all
    assert all(r["encoder"] == layout and not r["pixels_kept"] for r in ds["slides"])
    import histojax

    env, params = histojax.make("HistoJAX-Easy-v0", dataset=out, split="all", obs_mode="features", verify=False)
    assert params.slide.num_slides == 4


def test_a_slide_without_features_fails_alone_and_the_exit_status_says_so(mixed, tmp_path, capsys):
    slides, trident = mixed
    feats = tmp_path / "feats"
    shutil.copytree(trident, feats)
    next(feats.rglob("crop-3.h5")).unlink()
    out = tmp_path / "ds"
    assert (
        data_main(
            ["dataset", str(slides), "--out", str(out), "--levels", "3", "--features-from", str(feats), "--quiet"]
        )
        == 1
    )
    text = capsys.readouterr().out
    assert re.search(r"failed crop-3: .*no feature file crop-3\.h5", text)
    ds = json.loads((out / "dataset.json").read_text())
    assert "crop-3" in ds["failed"] and "bundles/crop-3" not in ds["train"] + ds["test"]
    assert not (out / "bundles" / "crop-3").exists()  # nothing half-written


# ----------------------------------------------------------------------------- bad input, one line each
def _fail(argv, capsys) -> str:
    assert data_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


def test_a_slide_without_tissue_fails_with_its_reason(tmp_path, pixels):
    slides = tmp_path / "slides"
    pyramid(slides / "blank.tif", np.full((512, 512, 3), 242, np.uint8))
    pyramid(slides / "real.tif", crop(pixels, 1))
    s = build_dataset(slides, tmp_path / "ds", levels=(3,), progress=False)
    assert list(s["failed"]) == ["blank"] and "no tissue found" in s["failed"]["blank"]
    assert not (tmp_path / "ds" / "bundles" / "blank").exists() and s["dataset"]["failed"]


def test_an_annotation_for_a_missing_slide(tmp_path, pixels, capsys):
    slides = tmp_path / "slides"
    pyramid(slides / "tumor_001.tif", crop(pixels, 1))
    rescaled_xml(C16_XML, slides / "tumor_01.xml", (512, 640))  # misspelt
    err = _fail(["dataset", str(slides), "--out", str(tmp_path / "ds")], capsys)
    assert "tumor_01.xml" in err and "not in" in err
    assert not (tmp_path / "ds").exists()


def test_a_label_table_naming_unknown_slides(tmp_path, pixels, capsys):
    slides = tmp_path / "slides"
    pyramid(slides / "a.tif", crop(pixels, 1))
    (tmp_path / "labels.csv").write_text("slide,label\na,1\nb,0\n")
    err = _fail(
        ["dataset", str(slides), "--out", str(tmp_path / "ds"), "--labels", str(tmp_path / "labels.csv")], capsys
    )
    assert "labels.csv" in err and "not in the folder: b" in err
    (tmp_path / "labels.csv").write_text("slide,label\na,maybe\n")
    assert "'maybe'" in _fail(
        ["dataset", str(slides), "--out", str(tmp_path / "ds"), "--labels", str(tmp_path / "labels.csv")], capsys
    )
    assert not (tmp_path / "ds").exists()


def test_duplicate_names_in_two_folders(tmp_path, pixels, capsys):
    slides = tmp_path / "slides"
    pyramid(slides / "site1" / "case.tif", crop(pixels, 1))
    pyramid(slides / "site2" / "case.svs", crop(pixels, 2))
    err = _fail(["dataset", str(slides), "--out", str(tmp_path / "ds")], capsys)
    assert "two slides named 'case'" in err and "site1" in err and "site2" in err


def test_mixed_mpp_at_one_magnification_range(tmp_path, pixels, capsys):
    slides = tmp_path / "slides"
    pyramid(slides / "x40.tif", crop(pixels, 1), mpp=0.25)
    pyramid(slides / "x20.tif", crop(pixels, 2), mpp=0.5)
    err = _fail(["dataset", str(slides), "--out", str(tmp_path / "ds"), "--magnification-range", "4"], capsys)
    assert "x20.tif" in err and "0.5 µm/px" in err and "0.25 µm/px" in err
    # without one range for all, each slide gets its own: builds
    assert build_dataset(slides, tmp_path / "ok", levels=(3,), progress=False)["dataset"] is not None


def test_a_label_contradicting_the_annotation_is_never_silent(tmp_path, pixels):
    slides = tmp_path / "slides"
    pyramid(slides / "a.tif", crop(pixels, 1))
    pyramid(slides / "b.tif", crop(pixels, 2))
    rescaled_xml(C16_XML, slides / "a.xml", (512, 640))
    (tmp_path / "labels.csv").write_text("name,label\na.tif,Normal\nb.tif,Tumor\n")
    s = build_dataset(slides, tmp_path / "ds", labels=tmp_path / "labels.csv", levels=(3,), progress=False)
    assert list(s["failed"]) == ["a"] and "labelled normal" in s["failed"]["a"]
    assert s["dataset"]["labels"] == {"b": 1}


def test_label_table_forms_and_the_seeded_split():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "reference.csv"
        p.write_text("Test_001,Tumor,Macro,Primary\nTest_002,Normal,,\n")
        assert read_label_table(p) == ({"Test_001": 1, "Test_002": 0}, {})
        p.write_text("slide_id,label,split\nA.svs,1,train\nB.svs,0,test\n")
        assert read_label_table(p) == ({"A": 1, "B": 0}, {"A": "train", "B": "test"})
    names = [f"s{i:02d}" for i in range(20)]
    labels = {n: int(i < 8) for i, n in enumerate(names)}
    train, test = seeded_split(names, labels, 0.25, seed=3)
    assert sum(labels[n] for n in test) == 2 and sum(1 - labels[n] for n in test) == 3
    assert seeded_split(list(reversed(names)), labels, 0.25, seed=3) == (train, test)
    assert seeded_split(names, labels, 0.25, seed=4) != (train, test)


def test_table_labels_reach_the_diagnosis_task_and_jobs_build_in_parallel(tmp_path, pixels):
    import histojax

    slides = tmp_path / "slides"
    for i, name in enumerate(("p1", "p2", "p3")):
        pyramid(slides / f"{name}.tif", crop(pixels, i))
    # p2 is a tumour slide without an annotation (a label table of a TCGA-style cohort): label 1, not "unannotated"
    (tmp_path / "labels.csv").write_text("slide,label,split\np1,0,train\np2,1,train\np3,0,test\n")
    s = build_dataset(slides, tmp_path / "ds", labels=tmp_path / "labels.csv", levels=(5,), jobs=2, progress=False)
    assert sorted(s["built"]) == ["p1", "p2", "p3"] and s["dataset"]["test"] == ["bundles/p3"]
    env, params = histojax.make("HistoJAX-C16-Diagnosis-v0", dataset=tmp_path / "ds", verify=False)
    assert [int(v) for v in params.slide.slide_label] == [0, 1]


# ----------------------------------------------------------------------------- c16 through the shared code
def test_c16_leaves_no_lock_no_partial_features_and_no_stale_temporaries(tmp_path):
    """After a successful run no lock file; a kill during the feature step and a
    rerun leave no ``features.partial/``; stale temporaries of names not built again are removed."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path / "c16"
    make_c16_dataset(out, small=True, n_tumour=1, n_normal=1, features="colour-stats", progress=False)
    assert not list(out.rglob("*lock"))  # neither per-slide locks nor a dataset lock stay behind
    done = next(p for p in (out / "bundles").iterdir() if p.is_dir())
    (done / "features.partial").mkdir()  # what the kill during the feature step left, the grid finished since
    mark_temporary(out / "bundles" / ".Tumor_999.tmp-0badf00d")  # a killed build of a name not built again
    (out / "bundles" / ".Tumor_999.tmp-0badf00d" / "levels_00.npy").write_bytes(b"\0" * 1000)
    make_c16_dataset(out, small=True, n_tumour=1, n_normal=1, features="colour-stats", progress=False)
    assert not list(out.rglob("features.partial")) and not list(out.rglob(".*.tmp-*"))
    assert not list(out.rglob("*lock")) and (out / "dataset.json").is_file()


def test_a_sigkilled_run_resumes(camelyon16, tmp_path):
    """SIGKILL ``data_tools dataset`` once it has finished a slide; the rerun keeps that slide, removes what
    the kill left and writes dataset.json."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "ds"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "data_tools",
            "dataset",
            str(camelyon16),
            "--out",
            str(out),
            "--levels",
            "5,7",
            "--quiet",
        ],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.time() + 300
        while not list((out / "records").glob("*.json")) and time.time() < deadline and proc.poll() is None:
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    done = sorted(p.stem for p in (out / "records").glob("*.json"))
    assert done
    s = build_dataset(camelyon16, out, levels=(5, 7), progress=False)
    assert set(done) <= set(s["resumed"]) and s["dataset"] is not None and not s["failed"]
    assert len(s["dataset"]["train"]) == 4 and len(s["dataset"]["test"]) == 2
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob("*lock"))
