"""A second hostile pass over run folders: a link inside a run folder (``checkpoint`` linked elsewhere), a user's
file inside the old run's ``checkpoint/``, ``eval/`` or ``process-N/`` under ``--overwrite``, a lock file that is a
FIFO or a link, and a FIFO or a link where ``--resume`` reads the checkpoint. Each is one line naming the file; none
blocks, none deletes or writes outside the folder. No training runs here (the checks come before it)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from blocking_helpers import at_most

from baselines.harness import run_folder
from baselines.harness.run_folder import RunFolderError, claim, release
from baselines.harness.runner import load_runner, resume_config
from data_tools.errors import HistojaxDataError

CONFIG = {"algo": "ppo", "env_id": "HistoJAX-Easy-v0"}


def _finished(out: Path) -> Path:
    out.mkdir()
    (out / "params.msgpack").write_bytes(b"old params")
    (out / "config.json").write_text(json.dumps(CONFIG))
    return out


def test_a_checkpoint_folder_linked_elsewhere_is_refused_even_with_overwrite(tmp_path):
    """Was: claimed with --overwrite (the link kept), and the run's checkpoints written into the linked folder."""
    out, elsewhere = tmp_path / "run", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (out / "checkpoint").symlink_to(elsewhere)
    for overwrite in (False, True):
        with pytest.raises(RunFolderError, match=r"holds files histojax did not write \(e\.g\. 'checkpoint'\)"):
            claim(out, CONFIG, overwrite=overwrite)
    assert (out / "checkpoint").is_symlink() and list(elsewhere.iterdir()) == []
    (out / "checkpoint").unlink()
    (out / "params.msgpack").symlink_to(tmp_path / "users.bin")  # a final file linked to a user's file
    with pytest.raises(RunFolderError, match="'params.msgpack'"):
        claim(out, CONFIG, overwrite=True)


@pytest.mark.parametrize("sub", ["checkpoint", "eval", "eval/slide1", "process-0"])
def test_overwrite_keeps_a_users_file_inside_the_old_runs_folders(tmp_path, sub):
    """Was: --overwrite removed RUN/checkpoint, RUN/eval and RUN/process-N whole, a user's file inside them too."""
    out = _finished(tmp_path / "run")
    (out / sub).mkdir(parents=True)
    (out / sub / "thesis.txt").write_text("mine")
    with pytest.raises(RunFolderError) as e:
        claim(out, CONFIG, overwrite=True)
    line = str(e.value)
    assert f"'{sub}/thesis.txt'" in line and "--overwrite would remove" in line and "\n" not in line
    assert (out / sub / "thesis.txt").read_text() == "mine" and (out / "params.msgpack").is_file()


def test_overwrite_still_replaces_what_a_run_and_its_evaluation_wrote(tmp_path):
    out = _finished(tmp_path / "run")
    for name in (
        "checkpoint/runner.msgpack",
        "checkpoint/config.json",
        "checkpoint/checkpoint.json",
        "eval/eval.json",
        "eval/eval.csv",
        "eval/trajectory.gif",
        "eval/trajectory_ppo_greedy.png",
        "eval/reading_ppo_greedy_maps.png",
        "eval/slide0/eval.json",
        "process-0/params.msgpack",
        "checkpoint/.runner.msgpack.tmp-0123abcd",
    ):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(json.dumps(CONFIG) if name.endswith("config.json") else "x")
    from data_tools.bundle_files.writes import mark_temporary

    mark_temporary(out / "checkpoint" / ".runner.msgpack.tmp-89abcdef")  # a killed run's atomic write
    (out / "checkpoint" / ".runner.msgpack.tmp-89abcdef" / "runner.msgpack").write_text("half")
    assert claim(out, CONFIG, overwrite=True) == out
    release(out)
    assert not (out / "checkpoint").exists() and not (out / "eval").exists() and not (out / "process-0").exists()
    assert (out / "params.msgpack").is_file()  # the old final files stay until the new run's are written


def test_a_lock_file_that_is_a_fifo_or_a_link_is_one_line(tmp_path):
    """Was: a FIFO lock file gave "OSError: [Errno 22] Invalid argument" (a traceback of `histojax train`)."""
    out = tmp_path / "run"
    out.mkdir()
    os.mkfifo(out / run_folder.LOCK)
    with at_most(10), pytest.raises(RunFolderError, match="is not a regular file .*not the run folder's lock file"):
        claim(out, CONFIG)
    (out / run_folder.LOCK).unlink()
    (out / run_folder.LOCK).symlink_to(tmp_path / "elsewhere")
    with pytest.raises(RunFolderError, match=r"\.histojax-run\.lock: is a symbolic link"):
        claim(out, CONFIG)
    assert not (tmp_path / "elsewhere").exists()


def test_a_fifo_config_json_in_the_run_folder_is_refused_not_waited_on(tmp_path):
    """Was: `histojax train --out R` with R/config.json a FIFO blocked for ever reading it."""
    out = tmp_path / "run"
    out.mkdir()
    os.mkfifo(out / "config.json")
    with at_most(10), pytest.raises(RunFolderError, match="'config.json'"):
        claim(out, CONFIG, overwrite=True)


def _unfinished(out: Path) -> Path:
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "config.json").write_text(json.dumps(CONFIG))
    return out


def test_resume_reads_no_fifo_and_no_link(tmp_path):
    """Was: `histojax train --resume R` with R/checkpoint/config.json or runner.msgpack a FIFO blocked for ever
    (killed at 90 s); runner.msgpack linked to another run's checkpoint was resumed from it without a word."""
    run = _unfinished(tmp_path / "run")
    os.mkfifo(run / "checkpoint" / "runner.msgpack")
    with (
        at_most(10),
        pytest.raises(HistojaxDataError, match=r"runner\.msgpack: is a FIFO, not the run's own checkpoint"),
    ):
        load_runner(run / "checkpoint", None, 1, 1)
    (run / "checkpoint" / "runner.msgpack").unlink()
    (tmp_path / "other.msgpack").write_bytes(b"\x80")
    (run / "checkpoint" / "runner.msgpack").symlink_to(tmp_path / "other.msgpack")
    with pytest.raises(HistojaxDataError, match="is a symbolic link, not the run's own checkpoint"):
        load_runner(run / "checkpoint", None, 1, 1)
    (run / "checkpoint" / "config.json").unlink()
    os.mkfifo(run / "checkpoint" / "config.json")
    with at_most(10), pytest.raises(HistojaxDataError, match=r"config\.json: is a FIFO, not the run's own config"):
        resume_config(run, "ppo")
    (run / "checkpoint" / "config.json").unlink()
    (run / "checkpoint" / "config.json").write_text(" " * (run_folder.MAX_CONFIG_BYTES + 1))
    with pytest.raises(HistojaxDataError, match="more than a run's config holds"):
        resume_config(run, "ppo")
    (run / "checkpoint" / "config.json").write_text(json.dumps(CONFIG))
    assert resume_config(run, "ppo")["env_id"] == "HistoJAX-Easy-v0"  # the run's own file still reads


# ----------------------------------------------------------------------------- the dataset seal's file
def _sealed(folder: Path) -> Path:
    from data_tools.bundle_files.seals import DATASET_DIGEST, metadata_digest

    folder.mkdir()
    spec = {
        "kind": "histojax dataset of real slides (data_tools dataset)",
        "train": ["bundles/s1"],
        "test": ["bundles/s2"],
        "labels": {"s1": 0, "s2": 1},
    }
    (folder / "dataset.json").write_text(json.dumps({**spec, DATASET_DIGEST: metadata_digest(spec)}))
    return folder


def test_a_dataset_json_that_is_a_fifo_a_folder_or_not_an_object_is_one_line(tmp_path):
    """Was: a FIFO dataset.json blocked make, the head fits and evaluate --dataset for ever (killed at 40 s); a folder
    gave IsADirectoryError and a JSON list AttributeError ('list' object has no attribute 'get') from make."""
    from data_tools.datasets.index import read_dataset_json
    from data_tools.errors import BundleError
    from histojax.datasets import dataset_slides

    ds = _sealed(tmp_path / "ds")
    assert read_dataset_json(ds)["labels"] == {"s1": 0, "s2": 1}
    (ds / "dataset.json").unlink()
    os.mkfifo(ds / "dataset.json")
    for read in (lambda: read_dataset_json(ds), lambda: dataset_slides(ds, "train")):
        with at_most(10), pytest.raises(BundleError, match=r"dataset\.json: is a FIFO, not a dataset index file"):
            read()
    (ds / "dataset.json").unlink()
    (ds / "dataset.json").mkdir()
    with pytest.raises(BundleError, match="is a folder, not a dataset index file"):
        dataset_slides(ds, "train")
    (ds / "dataset.json").rmdir()
    (ds / "dataset.json").write_text("[1, 2]")
    with pytest.raises(BundleError, match="holds a JSON list, not a dataset index"):
        dataset_slides(ds, "train")


def test_a_dataset_json_linked_to_a_regular_file_is_read_with_its_seal_checked(tmp_path):
    from data_tools.datasets.index import read_dataset_json
    from data_tools.errors import BundleError

    other = _sealed(tmp_path / "other")
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "dataset.json").symlink_to(other / "dataset.json")
    assert read_dataset_json(ds)["labels"]["s2"] == 1
    spec = json.loads((other / "dataset.json").read_text())
    (other / "dataset.json").write_text(json.dumps({**spec, "labels": {"s1": 1, "s2": 1}}))  # edited, seal kept
    with pytest.raises(BundleError, match="does not match its seal"):
        read_dataset_json(ds)


# ----------------------------------------------------------------------------- a head's params.json, named as such
def test_a_heads_params_json_is_named_as_its_parameters_not_its_config(tmp_path):
    """Was: a linked or NaN-holding params.json was called "the head's own config" / "a head config"."""
    import shutil

    from baselines.published_agents import PUBLISHED
    from histojax.reading import heads

    head = shutil.copytree(PUBLISHED / "c16-v2-head", tmp_path / "head")
    (head / "params.json").unlink()
    (head / "params.json").symlink_to(PUBLISHED / "c16-v2-head" / "params.json")
    with pytest.raises(ValueError, match=r"params\.json: is a symbolic link, not the head's own parameters"):
        heads.load(head)
    (head / "params.json").unlink()
    (head / "params.json").write_text('{"a": NaN, "b": 0.0, "prior_logit": 0.0}')
    with pytest.raises(ValueError, match=r"params\.json: not valid JSON \(NaN is not a number a head's parameters"):
        heads.load(head)


def test_an_unknown_entry_in_a_heads_params_json_is_refused(tmp_path):
    """Was: ``{"a": …, "b": …, "prior_logit": …, "scale": 10}`` loaded and "scale" was ignored without a word."""
    import json
    import shutil

    from baselines.published_agents import PUBLISHED
    from histojax.reading import heads

    head = shutil.copytree(PUBLISHED / "c16-v2-head", tmp_path / "head")
    params = json.loads((head / "params.json").read_text())
    (head / "params.json").write_text(json.dumps({**params, "scale": 10}))
    with pytest.raises(ValueError, match=r"params\.json: unknown entry 'scale'") as e:
        heads.load(head)
    assert "\n" not in str(e.value)
    (head / "params.json").write_text(json.dumps(params))
    assert heads.load(head).dim == 62  # the same file without it loads
