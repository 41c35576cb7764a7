"""A hostile pass over the slides a policy records (a run's or published agent's ``slides_seen.json``, read by
:func:`baselines.reading.provenance.check_policy`, the guard of every scorer of a trained policy): a slide renamed
in another dataset is still known by its identity; a run copied to another dataset whose slide merely shares a
name is not refused; identities that are not strings, NaN in the lists, a link to a regular file and garbage JSON
are handled; a ``slides_seen.json`` that is a FIFO or a folder is refused (never taken for no record, which would
skip the guard), and one nested past the parser or with ``fitted`` not a list is one line (a string ``fitted`` is
not read letter by letter)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from baselines.reading.provenance import RUN_RECORD, check_policy
from data_tools.bundle_files.seals import DATASET_DIGEST, metadata_digest
from data_tools.errors import HistojaxDataError

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs need a POSIX system")
KIND = "histojax dataset of real slides (data_tools dataset)"


def _dataset(folder: Path, slides: dict[str, str]) -> Path:
    """A sealed dataset of bundles ``NAME`` whose metadata records the SHA-256 ``slides[NAME]`` of their source."""
    for name, digest in slides.items():
        (folder / "bundles" / name).mkdir(parents=True)
        (folder / "bundles" / name / "metadata.json").write_text(json.dumps({"source": {"sha256": digest}}))
    body = {"kind": KIND, "train": [f"bundles/{n}" for n in slides], "test": []}
    (folder / "dataset.json").write_text(json.dumps({**body, DATASET_DIGEST: metadata_digest(body)}))
    return folder


def _run(folder: Path, record) -> Path:
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"algo": "ppo", "env_id": "HistoJAX-Easy-v0"}))
    (folder / RUN_RECORD).write_text(record if isinstance(record, str) else json.dumps(record))
    return folder


def _record(identities=None, fitted=("a",), seal="trained-on"):
    return {
        "fitted": list(fitted),
        "validation": [],
        "dataset": {"seal": seal},
        "identities": {"a": "sha256:AAA"} if identities is None else identities,
    }


def test_a_renamed_slide_is_known_by_its_identity(tmp_path):
    ds = _dataset(tmp_path / "other", {"z": "AAA", "b": "BBB"})
    run = _run(tmp_path / "run", _record())
    with pytest.raises(HistojaxDataError, match=r"trained on 1 of the 2 slides .*z \(recorded as a\)") as e:
        check_policy(run, ds, ["bundles/z", "bundles/b"])
    assert str(e.value).startswith(str(run / RUN_RECORD)) and "\n" not in str(e.value)


def test_a_run_copied_to_another_dataset_sharing_only_a_name_is_not_refused(tmp_path):
    ds = _dataset(tmp_path / "other", {"a": "CCC"})  # another slide named "a" (another seal, another file)
    assert check_policy(_run(tmp_path / "run", _record()), ds, ["bundles/a"]) == []


@pytest.mark.parametrize(
    "identities",
    [{"a": 5}, {"a": None}, {"a": float("nan")}, ["sha256:AAA"], "sha256:AAA"],
)
def test_identities_that_are_not_strings_are_no_identity_and_no_traceback(tmp_path, identities):
    ds = _dataset(tmp_path / "other", {"z": "AAA"})
    run = _run(tmp_path / "run", json.dumps(_record(identities)))  # NaN written as JSON's NaN
    assert check_policy(run, ds, ["bundles/z"]) == []  # renamed, and no usable identity: not known


def test_nan_and_null_in_the_lists_are_no_slide(tmp_path):
    ds = _dataset(tmp_path / "other", {"b": "BBB"})
    run = _run(tmp_path / "run", '{"fitted": [NaN, null, 1], "validation": [], "identities": {}}')
    assert check_policy(run, ds, ["bundles/b"]) == []


def test_a_link_to_a_regular_record_is_read_and_garbage_is_one_line(tmp_path):
    ds = _dataset(tmp_path / "other", {"a": "AAA"})
    run = _run(tmp_path / "run", "{}")
    (tmp_path / "elsewhere.json").write_text(json.dumps(_record()))
    (run / RUN_RECORD).unlink()
    (run / RUN_RECORD).symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(HistojaxDataError, match="trained on 1 of the 1 slides"):
        check_policy(run, ds, ["bundles/a"])
    (run / RUN_RECORD).unlink()
    (run / RUN_RECORD).write_text("{not json")
    with pytest.raises(HistojaxDataError, match=r"slides_seen\.json: unreadable") as e:
        check_policy(run, ds, ["bundles/a"])
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_record_that_is_a_fifo_or_a_folder_is_refused_not_taken_for_none(tmp_path, kind):
    ds = _dataset(tmp_path / "other", {"a": "AAA"})
    run = _run(tmp_path / "run", "{}")
    (run / RUN_RECORD).unlink()
    os.mkfifo(run / RUN_RECORD) if kind == "fifo" else (run / RUN_RECORD).mkdir()
    with pytest.raises(HistojaxDataError, match=r"slides_seen\.json"):
        check_policy(run, ds, ["bundles/a"])


@pytest.mark.parametrize(
    "record",
    ["[" * 100_000 + "]" * 100_000, '{"fitted": 5}', '{"fitted": "ab", "identities": {}}'],
)
def test_a_record_nested_past_the_parser_or_of_wrong_types_is_one_line(tmp_path, record):
    """``"fitted": "ab"`` would be the letters a and b, so slide ab, the one it names, would pass the guard."""
    ds = _dataset(tmp_path / "other", {"ab": "ABAB"})
    run = _run(tmp_path / "run", record)
    with pytest.raises(HistojaxDataError, match=r"slides_seen\.json") as e:
        check_policy(run, ds, ["bundles/ab"])
    assert "\n" not in str(e.value)
