"""A command that refuses a folder leaves it exactly as it found it: no lock file, no folder it made; and every
folder histojax writes into a run folder is one of the run's own entries (``--overwrite`` replaces it)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from baselines.harness import run_folder

TRAIN = ["train", "--env", "HistoJAX-Easy-v0", "--total-steps", "512", "--seeds", "1"]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def _tree(folder: Path) -> dict:
    """Every entry under ``folder`` (the lock file included) with its bytes (None for a folder)."""
    return {str(p.relative_to(folder)): (None if p.is_dir() else p.read_bytes()) for p in sorted(folder.rglob("*"))}


def _finished_run(folder: Path) -> Path:
    (folder / "checkpoint").mkdir(parents=True)
    for name in ("params.msgpack", "log.csv", "log.json", "curve.png"):
        (folder / name).write_bytes(b"a finished run's " + name.encode())
    (folder / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "seed": 0}))
    (folder / "checkpoint" / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "seed": 0}))
    return folder


@pytest.mark.parametrize("what", ["users-notes", "finished-run", "dataset"])
def test_a_refused_train_out_leaves_the_folder_exactly_as_it_was_no_lock_file(tmp_path, capsys, what):
    from histojax.cli import main

    out = tmp_path / "folder"
    if what == "users-notes":
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    elif what == "dataset":
        out.mkdir()
        (out / "dataset.json").write_text("{}")
        (out / "bundles").mkdir()
    else:
        _finished_run(out)
    before = _tree(out)
    assert main([*TRAIN, "--out", str(out)]) == 2
    assert str(out) in _one_line(capsys)
    assert _tree(out) == before  # no .histojax-run.lock left behind


def test_a_train_refused_after_its_claim_removes_the_folder_it_made(tmp_path, capsys, monkeypatch):
    from histojax.cli import main

    monkeypatch.chdir(tmp_path)
    Path("ds").mkdir()  # not a dataset: refused when the environment is made, after the run folder was claimed
    assert main([*TRAIN, "--dataset", "ds", "--fold", "3", "--out", "new/run"]) == 2
    assert "dataset" in _one_line(capsys)
    assert sorted(os.listdir(tmp_path)) == ["ds"]  # neither new/run nor new/ left behind


def test_a_refused_resume_leaves_no_lock_file(tmp_path, capsys):
    from histojax.cli import main

    run = tmp_path / "run"
    (run / "checkpoint").mkdir(parents=True)
    (run / "checkpoint" / "config.json").write_text("not json")
    before = _tree(run)
    assert main(["train", "--algo", "ppo", "--resume", str(run)]) == 2
    _one_line(capsys)
    assert _tree(run) == before


def test_release_removes_the_lock_file_and_keeps_a_folder_it_did_not_make(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    assert run_folder.claim(out, {"env_id": "HistoJAX-Easy-v0"}) == out
    assert (out / run_folder.LOCK).is_file()
    run_folder.release(out)
    assert out.is_dir() and os.listdir(out) == []
    fresh = tmp_path / "a" / "b"
    assert run_folder.claim(fresh, {"env_id": "HistoJAX-Easy-v0"}) == fresh
    (fresh / "log.csv").write_text("the run wrote this")
    run_folder.release(fresh)
    assert os.listdir(fresh) == ["log.csv"]  # a folder holding the run's files stays


def test_a_lock_taken_again_after_release_works_in_one_process(tmp_path):
    out = tmp_path / "run"
    for _ in range(2):
        run_folder.claim(out, {"env_id": "HistoJAX-Easy-v0"})
        run_folder.release(out)
    assert not out.exists()


def _evaluated_all_folds(run: Path) -> None:
    folds = run / "eval-all-folds"
    (folds / "fold0").mkdir(parents=True)
    (folds / "eval.json").write_text("{}")
    (folds / "eval.csv").write_text("fold,policy\n")
    (folds / "fold0" / "eval.json").write_text("{}")
    (folds / "fold0" / "reading_slide0.png").write_bytes(b"png")


def test_overwrite_works_after_evaluate_all_folds_and_reader_training(tmp_path):
    run = _finished_run(tmp_path / "run")
    _evaluated_all_folds(run)
    (run / "head_reward.json").write_text("{}")  # baselines.reading.train_readers
    (run / "curve-seeds.png").write_bytes(b"png")
    (run / "curve-seeds.csv").write_text("seed\n")
    assert run_folder.foreign_entries(run) == []
    assert run_folder.claim(run, {"env_id": "HistoJAX-Easy-v0", "seed": 7}, overwrite=True) == run
    run_folder.release(run)
    for gone in ("eval-all-folds", "head_reward.json", "curve-seeds.png", "curve-seeds.csv", "checkpoint"):
        assert not (run / gone).exists(), gone  # derived from the old run: replaced with it
    assert (run / "params.msgpack").read_bytes().startswith(b"a finished")  # until the new run's are written


def test_a_users_file_inside_eval_all_folds_is_still_refused(tmp_path):
    run = _finished_run(tmp_path / "run")
    _evaluated_all_folds(run)
    (run / "eval-all-folds" / "fold0" / "thesis.txt").write_text("mine")
    before = _tree(run)
    with pytest.raises(run_folder.RunFolderError, match="eval-all-folds/fold0/thesis.txt"):
        run_folder.claim(run, {"env_id": "HistoJAX-Easy-v0", "seed": 7}, overwrite=True)
    assert _tree(run) == before


def _leftover_lock(folder: Path) -> Path:
    lock = folder / run_folder.LOCK
    lock.write_text("12345\n")  # what a refused `train --out` of histojax 0.1.0 left behind
    return lock


def test_a_lock_left_by_an_older_refused_train_never_makes_a_bundle_foreign(tmp_path):
    import fcntl

    from data_tools.bundle_files.format import FORMAT_VERSION, METADATA
    from data_tools.bundle_files.writes import foreign_entries

    bundle = tmp_path / "b"
    bundle.mkdir()
    (bundle / METADATA).write_text(json.dumps({"format_version": FORMAT_VERSION, "checksums": {}}))
    lock = _leftover_lock(bundle)
    assert foreign_entries(bundle) == []  # build --overwrite replaces it, the leftover with it
    fd = os.open(lock, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # held by a run: not a leftover
        assert foreign_entries(bundle) == [run_folder.LOCK]
    finally:
        os.close(fd)
    lock.write_text("my notes")  # a user's file of that name: foreign
    assert foreign_entries(bundle) == [run_folder.LOCK]


def test_a_lock_left_by_an_older_refused_train_never_blocks_a_head_refit(tmp_path):
    import jax

    from histojax.reading.heads.learned import LearnedHead, init_params

    head = LearnedHead(
        params=init_params(jax.random.PRNGKey(0), 4, hidden=4, attention=2), features_dim=4, hidden=4, attention=2
    )
    folder = head.save(tmp_path / "head")
    _leftover_lock(folder)
    head.save(folder)  # the refit: refused before ("holds files the head there did not write")
    assert sorted(os.listdir(folder)) == ["config.json", "params.npz"]
