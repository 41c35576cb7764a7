"""One set of size limits for every slide reader (data_tools.slide_files.limits), and scanner files that never take the
process down: a MIRAX slide whose Slidedat.ini declares absurd sizes is refused before OpenSlide allocates (it made
GLib abort the whole process, rc 134, no file named), any OpenSlide slide is opened first in a child process that can
die alone, and ``dataset`` builds every other slide of the folder.

The MIRAX slides are tests/mirax_fixture.py's, with one Slidedat.ini key edited. Cases that would abort the process
on code without these checks run in a child Python, so that a regression fails the test instead of killing pytest."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.errors import SlideError
from data_tools.slide_files import limits as slide_limits
from data_tools.slide_files.open import open_slide

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"


def _edit_ini(folder: Path, **edits) -> None:
    """Set ``KEY=value`` for each edit in the MIRAX data folder's Slidedat.ini (every section holding the key;
    ``LEVEL1_KEY`` edits the key in zoom level 1's section only)."""
    ini = folder / "Slidedat.ini"
    text = ini.read_text()
    for key, value in edits.items():
        if key.startswith("LEVEL1_"):
            key = key[len("LEVEL1_") :]
            head, tail = text.split("[LAYER_0_LEVEL_1_SECTION]")
            tail = re.sub(rf"^{key}=.*$", f"{key}={value}", tail, count=1, flags=re.M)
            text = head + "[LAYER_0_LEVEL_1_SECTION]" + tail
        else:
            assert re.search(rf"^{key}=", text, flags=re.M), key
            text = re.sub(rf"^{key}=.*$", f"{key}={value}", text, flags=re.M)
    ini.write_text(text)


@pytest.fixture(scope="module")
def mirax_pixels():
    """512 × 256 px of real tissue (a crop of the sample slide)."""
    with tifffile.TiffFile(SVS) as tif:
        return np.ascontiguousarray(tif.pages[0].asarray()[400:656, 800:1312, :3])


@pytest.fixture(scope="module")
def mirax_cases(tmp_path_factory, mirax_pixels):
    """name → a MIRAX slide whose Slidedat.ini declares what the name says."""
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    from mirax_fixture import mirax

    root = tmp_path_factory.mktemp("mirax-limits")
    cases = {
        "good": {},
        "two-billion-columns": {"IMAGENUMBER_X": 2_000_000_000},
        "forty-thousand-squared": {"IMAGENUMBER_X": 40_000, "IMAGENUMBER_Y": 40_000},
        "billion-px-camera-image": {"DIGITIZER_WIDTH": 1_000_000_000},
        "hundred-thousand-columns": {"IMAGENUMBER_X": 100_000},
        "area-over-the-limit": {
            "IMAGENUMBER_X": 4000,
            "IMAGENUMBER_Y": 4000,
            "DIGITIZER_WIDTH": 200,
            "DIGITIZER_HEIGHT": 200,
        },
        "million-zoom-levels": {"HIER_0_COUNT": 1_000_000},
        "two-billion-data-files": {"FILE_COUNT": 2_000_000_000},
        "nan-overlap": {"OVERLAP_X": "nan"},
        "overlap-past-the-image": {"OVERLAP_Y": 5000},
        "concat-past-30": {"LEVEL1_IMAGE_CONCAT_FACTOR": 40},
    }
    out = {}
    for name, edits in cases.items():
        path, _ = mirax(root / name / f"{name}.mrxs", mirax_pixels)
        _edit_ini(path.with_suffix(""), **edits)
        out[name] = path
    return out


_OPEN_ALL = r"""
import json, sys
import data_tools.slide_files.openslide as reader
from data_tools.errors import SlideError
from data_tools.slide_files.open import open_slide
if sys.argv[1] == "no-precheck":
    reader.check_mirax = lambda path: None  # only the child-process probe and the limits after opening stand
out = {}
for path in sys.argv[2:]:
    try:
        with open_slide(path) as s:
            out[path] = ["opened", [[lv.width, lv.height] for lv in s.levels]]
    except SlideError as e:
        out[path] = ["refused", str(e)]
print(json.dumps(out))
"""


def _open_in_child(paths, mode="checked"):
    proc = subprocess.run(
        [sys.executable, "-c", _OPEN_ALL, mode, *map(str, paths)], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert proc.returncode == 0, f"the process died (rc {proc.returncode}): {proc.stderr[-500:]}"
    return json.loads(proc.stdout)


def test_one_definition_of_the_limits_for_every_reader():
    from data_tools.slide_files import dicom, mirax, openslide, tiff

    assert tiff.MAX_SIDE is slide_limits.MAX_SIDE == 1_000_000
    for module in (tiff, dicom, openslide, mirax):  # each reader's checks go through the shared module
        assert "slide_files.limits" in Path(module.__file__).read_text()


def test_absurd_mirax_headers_are_one_line_naming_the_file(mirax_cases):
    """Before: GLib aborted the process (rc 134, "overflow allocating ...") for the first three; the 12,800,000 px
    level of ``hundred-thousand-columns`` was opened (rc 0)."""
    got = _open_in_child(mirax_cases.values())
    for name, path in mirax_cases.items():
        outcome, text = got[str(path)]
        if name == "good":
            assert outcome == "opened" and text == [[512, 256], [256, 128]]
            continue
        assert outcome == "refused", (name, text)
        assert text.startswith(f"{path}: ") and "\n" not in text, text
    said = {n: got[str(p)][1] for n, p in mirax_cases.items()}
    assert "4,000,000,000 camera images, over the limit of 33,554,432" in said["two-billion-columns"]
    assert "1,600,000,000 camera images" in said["forty-thousand-squared"]
    assert "1,000,000,000×128 px, outside the limit of 1..1,000,000 px a side" in said["billion-px-camera-image"]
    assert "12,800,000×256 px, outside the limit of 1..1,000,000 px a side" in said["hundred-thousand-columns"]
    assert "over the limit of 250,000,000,000 px" in said["area-over-the-limit"]
    assert "HIER_0_COUNT=1,000,000 zoom levels" in said["million-zoom-levels"]
    assert "FILE_COUNT=2,000,000,000 data files" in said["two-billion-data-files"]
    assert "overlap of nan" in said["nan-overlap"] and "overlap of 0 × 5000" in said["overlap-past-the-image"]
    assert "IMAGE_CONCAT_FACTOR values summing to 40" in said["concat-past-30"]


def test_a_slide_that_makes_openslide_abort_kills_only_a_child_process(mirax_cases):
    """Without the Slidedat.ini check, OpenSlide is first run in a child process: GLib's abort takes only that
    child, and the slide is refused naming the signal; sizes OpenSlide opens but the shared limits refuse
    (12,800,000 px a side) are refused after it reports them, with the native readers' words."""
    got = _open_in_child(
        [mirax_cases[n] for n in ("forty-thousand-squared", "hundred-thousand-columns", "good")], mode="no-precheck"
    )
    crashed = got[str(mirax_cases["forty-thousand-squared"])]
    assert crashed[0] == "refused" and "OpenSlide crashed opening it (SIGABRT" in crashed[1], crashed
    assert "\n" not in crashed[1]
    wide = got[str(mirax_cases["hundred-thousand-columns"])]
    assert wide[0] == "refused" and "outside the limit of 1..1,000,000 px a side" in wide[1], wide
    assert got[str(mirax_cases["good"])][0] == "opened"


def test_the_tiff_reader_applies_the_same_area_limit(tmp_path):
    """A TIFF whose header declares 600,000 × 600,000 px (each side within the side limit) is refused for its area
    with the words the OpenSlide path uses (before: "offsets tag missing or short", no limit named)."""
    path = tmp_path / "vast.tif"
    tifffile.imwrite(path, np.zeros((16, 16, 3), np.uint8), photometric="rgb")
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        offsets = [tags[name].valueoffset for name in ("ImageWidth", "ImageLength")]
    data = bytearray(path.read_bytes())
    for offset in offsets:
        data[offset : offset + 4] = np.array([600_000], "<u4").tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(
        SlideError,
        match=r"vast\.tif: level 0 declares 600,000×600,000 px = .* over the limit of "
        r"250,000,000,000 px",
    ):
        open_slide(path)


def test_the_limits_hold_for_every_reader_on_reported_levels():
    """The check every reader runs on the levels it found (TIFF, DICOM, OpenSlide): level count, sides, tiles."""
    from data_tools.slide_files.base import LevelInfo, check_levels

    def levels(n, w=1000, tile=(256, 256)):
        return [
            LevelInfo(width=max(1, w >> k), height=max(1, w >> k), downsample=2.0**k, tile_size=tile, compression="x")
            for k in range(n)
        ]

    check_levels("ok.tif", levels(8))
    with pytest.raises(SlideError, match="65 pyramid levels, over the limit of 64"):
        check_levels("many.tif", levels(65, w=2**70))
    with pytest.raises(SlideError, match=r"level 0's tile declares 2,000,000×2,000,000 px"):
        check_levels("tile.tif", levels(2, tile=(2_000_000, 2_000_000)))
    with pytest.raises(SlideError, match=r"level 0 declares 100,000,000,000 tiles of 1×1 px, over"):
        check_levels(
            "tiles.tif", [LevelInfo(width=1_000_000, height=100_000, downsample=1.0, tile_size=(1, 1), compression="x")]
        )


def test_a_mirax_without_its_data_folder_says_so(tmp_path):
    """Before: "format not recognised by OpenSlide" for a .mrxs copied without its folder."""
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    lone = tmp_path / "lone.mrxs"
    lone.write_bytes(b"")
    with pytest.raises(SlideError, match=r"lone\.mrxs: its data folder lone/ is missing"):
        open_slide(lone)
    (tmp_path / "lone").mkdir()
    with pytest.raises(SlideError, match=r"lone\.mrxs: its data folder lone/ has no Slidedat\.ini"):
        open_slide(lone)


def test_dataset_builds_every_other_slide_beside_a_hostile_mirax(mirax_cases, tmp_path):
    """Before: ``dataset`` aborted (rc 134) while it looked at the slides' scales, and nothing was built."""
    slides = tmp_path / "S"
    slides.mkdir()
    for name in ("good", "two-billion-columns"):
        src = mirax_cases[name]
        shutil.copy(src, slides / src.name)
        shutil.copytree(src.with_suffix(""), slides / src.with_suffix("").name)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "data_tools",
            "dataset",
            str(slides),
            "--out",
            str(tmp_path / "o"),
            "--levels",
            "3",
            "--tile-size",
            "64",
            "--quiet",
            "--test-fraction",
            "0",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 1, proc.stderr  # some slides failed, the rest built
    failed = [ln for ln in proc.stdout.splitlines() if "failed two-billion-columns" in ln]
    assert len(failed) == 1 and "two-billion-columns.mrxs: its Slidedat.ini declares" in failed[0], proc.stdout
    ds = json.loads((tmp_path / "o" / "dataset.json").read_text())
    assert [s["name"] for s in ds["slides"]] == ["good"]
