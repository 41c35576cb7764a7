"""`data_tools c16` checks its .tar.gz inputs against the bytes the published C16 tables were built from."""

from __future__ import annotations

import io
import re
import tarfile
from pathlib import Path

import pytest

from data_tools.datasets.c16.dataset import make_c16_dataset
from data_tools.datasets.c16.inputs import KNOWN_INPUTS, check_known_inputs, differing_lines
from data_tools.errors import HistojaxDataError

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"


def _tar_gz(path: Path, name: str = "train/Tumor_001.json", data: bytes = b"{}") -> Path:
    with tarfile.open(path, "w:gz") as tar:
        info = tarfile.TarInfo(name)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return path


def test_other_bytes_get_one_line_naming_the_input(tmp_path):
    other = _tar_gz(tmp_path / "camelyon16_ncrf_train.tar.gz")
    record = check_known_inputs(annotations=other, patches=None)
    assert record == {
        "annotations": {"file": str(other), "sha256": record["annotations"]["sha256"], "matches_published": False}
    }
    lines = differing_lines(record)
    assert len(lines) == 1 and "annotations" in lines[0] and str(other) in lines[0]
    assert "published tables were built from other inputs" in lines[0]


def test_folders_npz_and_missing_paths_are_not_hashed(tmp_path):
    (tmp_path / "patches").mkdir()
    (tmp_path / "bank.npz").write_bytes(b"x")
    assert check_known_inputs(annotations=tmp_path / "none.tar.gz", patches=tmp_path / "patches") == {}
    assert check_known_inputs(patches=tmp_path / "bank.npz") == {}


def test_the_c16_command_says_which_input_differs_before_it_builds(tmp_path, capsys):
    """Through make_c16_dataset: a tarball with other bytes gets its line on stderr (here the tarball holds
    no valid NCRF JSON, so the build then stops with its own one-line error, nothing written)."""
    bad = _tar_gz(tmp_path / "ncrf.tar.gz", data=b"not json")
    with pytest.raises(HistojaxDataError):
        make_c16_dataset(tmp_path / "out", annotations=bad, small=True, progress=False)
    err = capsys.readouterr().err
    assert err.count("published tables were built from other inputs") == 1 and str(bad) in err
    assert not (tmp_path / "out" / "dataset.json").exists()


def test_known_sha256s_are_the_docs():
    """The constants and docs/c16-benchmark.md name the same files, sha256s and revisions."""
    doc = (ROOT / "docs" / "c16-benchmark.md").read_text()
    for kind, known in KNOWN_INPUTS.items():
        assert re.fullmatch(r"[0-9a-f]{64}", known["sha256"]), kind
        row = next((line for line in doc.splitlines() if f"`{known['file']}`" in line and "|" in line), None)
        assert row is not None, f"no row for {known['file']} in docs/c16-benchmark.md"
        assert f"`{known['sha256']}`" in row, f"{known['file']}: the doc's sha256 is not the constant"
        revision = re.search(r"revision ([0-9a-f]{40})", known["source"]).group(1)
        assert revision in row, f"{known['file']}: the doc's revision is not the constant's"


@pytest.mark.skipif(not SHARED.is_dir(), reason="the two published inputs are not on this machine")
def test_the_published_inputs_match():
    record = check_known_inputs(
        annotations=SHARED / "annotations" / "camelyon16_ncrf_train.tar.gz",
        patches=SHARED / "pcam_train_patches.tar.gz",
    )
    assert set(record) == {"annotations", "patches"}
    assert all(r["matches_published"] for r in record.values()) and differing_lines(record) == []
