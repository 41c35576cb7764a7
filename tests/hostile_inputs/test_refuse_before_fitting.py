"""Refuse before working: a head fit whose ``--out`` cannot be written (a read-only file system, which refuses
root too) is refused in one line before any slide is read or any candidate trained, and leaves nothing behind."""

from __future__ import annotations

import errno
import os
import tempfile

import pytest

from histojax.reading.heads import files


@pytest.fixture
def read_only(monkeypatch):
    """Every probe file :func:`histojax.reading.heads.files.check_writable` makes fails as on a read-only file
    system; reading a dataset or training fails the test."""

    def refused(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    from baselines.reading import head_fit, head_mil_fit, learned_head_fit

    def worked(*args, **kwargs):
        raise AssertionError("read the dataset before refusing the folder")

    monkeypatch.setattr(head_fit, "read_spec", worked)
    monkeypatch.setattr(learned_head_fit, "read_spec", worked)
    monkeypatch.setattr(head_mil_fit, "read_spec", worked)


@pytest.mark.parametrize("module", ["head_fit", "learned_head_fit", "head_mil_fit"])
def test_a_head_fit_onto_a_folder_it_cannot_write_is_refused_before_any_work(tmp_path, capsys, read_only, module):
    import importlib

    fit = importlib.import_module(f"baselines.reading.{module}")
    main = fit.main if hasattr(fit, "main") else fit._main()
    out = tmp_path / "heads" / "h"
    extra = ["--cache", str(tmp_path / "c.npz")] if module == "head_mil_fit" else []
    assert main(["--dataset", str(tmp_path / "ds"), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    assert f"{out}: cannot be written: Read-only file system" in err and "nothing was fitted" in err, err
    assert os.listdir(tmp_path) == []  # no folder, no probe, no temporary


def test_the_write_check_leaves_nothing_and_passes_a_writable_folder(tmp_path):
    files.check_writable(tmp_path / "a" / "b")
    (tmp_path / "h").mkdir()
    files.check_writable(tmp_path / "h")
    assert sorted(os.listdir(tmp_path)) == ["h"] and os.listdir(tmp_path / "h") == []


def test_a_learned_fit_of_no_candidate_size_is_refused_before_reading_the_dataset(tmp_path, capsys, monkeypatch):
    from baselines.reading import learned_head_fit

    monkeypatch.setattr(learned_head_fit, "read_spec", lambda *a, **k: pytest.fail("read the dataset first"))
    main = learned_head_fit.main if hasattr(learned_head_fit, "main") else learned_head_fit._main()
    assert main(["--dataset", str(tmp_path / "ds"), "--out", str(tmp_path / "h"), "--hidden", "7"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --hidden [7]: none of the candidate sizes") and len(err.splitlines()) == 1, err
    assert os.listdir(tmp_path) == []
