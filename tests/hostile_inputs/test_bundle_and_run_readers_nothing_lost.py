"""Nothing lost where users work, the reading and training side: every reader of a bundle in baselines.reading goes
through the checked bundle loader, head folders are read through one guarded reader (strict types, bounded sizes and
structure, no blocking, one line instead of a traceback), the budget curve's options are checked, undefined results
say so, run folders are never overwritten silently and hold one writer at a time, and the words of the evaluate /
train commands.

The head tools read a small feature-only stand-in dataset (tests/reading/test_head.py's, with checksums and a sealed
metadata.json as a build writes them)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_head import make_dataset

from baselines.reading import head_fit, head_mil_fit, pipeline, readers, slides
from data_tools.errors import HistojaxDataError

ROOT = Path(__file__).resolve().parents[2]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ----------------------------------------------------------------------------- every reader of a bundle is checked
@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("runs-ds"), n_train=6, n_test=2)


@pytest.fixture()
def work(small_dataset, tmp_path):
    dest = tmp_path / "ds"
    shutil.copytree(small_dataset, dest)
    return dest


def _first_bundle(ds: Path) -> Path:
    return ds / json.loads((ds / "dataset.json").read_text())["train"][0]


def _link_outside(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    outside = tmp_path / "OUTSIDE.npy"
    np.save(outside, np.full(np.load(bundle / "features_00.npy").shape, 9.0, np.float16))
    (bundle / "features_00.npy").unlink()
    (bundle / "features_00.npy").symlink_to(outside)
    return bundle


def _absolute_path_in_metadata(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    meta = json.loads((bundle / "metadata.json").read_text())
    shutil.copy(bundle / "features_00.npy", tmp_path / "elsewhere.npy")
    meta["features"]["levels"][0]["file"] = str(tmp_path / "elsewhere.npy")
    (bundle / "metadata.json").write_text(json.dumps(meta))
    return bundle


def _flip_a_feature(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    a = np.load(bundle / "features_00.npy")
    a[0, 0, 62] = 7.0
    np.save(bundle / "features_00.npy", a)
    return bundle


@pytest.mark.parametrize(
    "damage, words",
    [
        (_link_outside, "symbolic link"),
        (_absolute_path_in_metadata, "metadata"),
        (_flip_a_feature, "checksum mismatch"),
    ],
)
def test_the_head_tools_read_bundles_through_the_checked_loader(work, tmp_path, damage, words):
    bundle = damage(work, tmp_path)
    for read in (
        lambda: slides.load_slide(bundle),
        lambda: head_mil_fit.load_grid(bundle),
        lambda: slides.load_slides(work, "train"),
    ):
        with pytest.raises(HistojaxDataError) as e:
            read()
        assert words in str(e.value) and str(bundle) in str(e.value), e.value


def test_head_fit_refuses_a_linked_feature_grid_in_one_line(work, tmp_path, capsys, monkeypatch):
    import baselines.validation

    monkeypatch.setattr(baselines.validation, "check_validation_share", lambda *a, **k: None)  # 3 slides a class:
    _link_outside(work, tmp_path)  # the share is too small to fit on; here only the reading of the bundles is checked
    assert head_fit.main(["--dataset", str(work), "--out", str(tmp_path / "head")]) == 2
    assert "symbolic link" in _one_line(capsys)
    assert not (tmp_path / "head").exists()


def test_readers_cell_level_reads_the_checked_metadata(work, tmp_path):
    bundle = _first_bundle(work)
    meta = json.loads((bundle / "metadata.json").read_text())
    meta["levels"][1]["downsample"] = 3.0  # edited after the build: the seal no longer matches
    (bundle / "metadata.json").write_text(json.dumps(meta))
    spec = slides.read_spec(work)
    with pytest.raises(HistojaxDataError, match="digest mismatch"):
        pipeline.cell_level_for(work, spec, "train")


# ----------------------------------------------------------------------------- head folders: one guarded reader
def _logit_head(folder: Path, **cfg) -> Path:
    from histojax.reading.heads.logit import LogitHead

    LogitHead(cal_a=2.0, cal_b=-4.0, prior_logit=-0.3, dim=62, k=2, top=1).save(folder)
    params = {k: cfg.pop(k) for k in ("a", "b", "prior_logit") if k in cfg}
    if cfg:
        c = json.loads((folder / "config.json").read_text())
        c.update(cfg)
        (folder / "config.json").write_text(json.dumps(c))
    if params:
        p = json.loads((folder / "params.json").read_text())
        p.update(params)
        (folder / "params.json").write_text(json.dumps(p))
    return folder


def _stats_head(folder: Path) -> Path:
    import jax.numpy as jnp

    from histojax.reading.heads.mil import StatsHead

    n = 4 * 2 + 3 + 1
    StatsHead(
        params={"mu": jnp.zeros(n), "sd": jnp.ones(n), "w": jnp.full(n, 0.1), "b": jnp.float32(0.0)},
        prior_logit=jnp.float32(-0.3),
    ).save(folder)
    return folder


def _load(folder):
    from histojax.reading import heads

    return heads.load(folder)


@pytest.mark.parametrize(
    "edit, words",
    [
        ({"minus_median": "false"}, "'minus_median' is \"false\", not a bool"),
        ({"k": 2.9}, "'k' is 2.9, not an int"),
        ({"k": 1_000_000_000}, "'k' is 1000000000, outside [1, 64]"),
        ({"format": 9}, "format 9; this version reads format 1"),
        ({"format": "1"}, "'format' is \"1\", not an int"),
        ({"dim": -1}, "'dim' is -1, outside"),
        ({"a": 1e38, "b": -1e38}, "params.json: 'a' is 1e+38, outside"),
        ({"b": [1, 2]}, "'b' is [1, 2], not a finite number"),
    ],
)
def test_a_logit_head_config_is_read_strictly(tmp_path, edit, words):
    folder = _logit_head(tmp_path / "h", **edit)
    with pytest.raises(ValueError) as e:
        _load(folder)
    assert words in str(e.value) and "\n" not in str(e.value), e.value


def test_a_head_reading_an_entry_the_features_lack_is_refused_not_clamped(tmp_path):
    from histojax.reading import heads

    grid = np.zeros((4, 4, 11), np.float32)
    for folder in (_logit_head(tmp_path / "logit", dim=62), _stats_head(tmp_path / "stats")):
        head = _load(folder)
        with pytest.raises(ValueError, match="reads feature entry 62 .* the features have 11 entries"):
            heads.score(head, grid, np.ones((4, 4), bool))


@pytest.mark.parametrize("dtype", [np.complex64, object])
def test_complex_or_object_head_parameters_are_refused(tmp_path, dtype):
    folder = _stats_head(tmp_path / "s")
    z = dict(np.load(folder / "params.npz"))
    z["w"] = z["w"].astype(dtype)
    np.savez(folder / "params.npz", **z)
    with pytest.raises(ValueError, match="array w has dtype"):
        _load(folder)


def test_a_fifo_params_json_is_refused_without_blocking(tmp_path):
    import threading

    folder = _logit_head(tmp_path / "h")
    (folder / "params.json").unlink()
    os.mkfifo(folder / "params.json")
    result = {}

    def load():
        try:
            _load(folder)
        except ValueError as e:
            result["error"] = str(e)

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(20)
    if t.is_alive():  # free the blocked reader
        with open(folder / "params.json", "w"):
            pass
        pytest.fail("loading a head whose params.json is a FIFO blocked")
    assert "not a regular file" in result["error"]


def test_an_unused_array_in_params_npz_is_refused_before_it_is_read(tmp_path):
    import tracemalloc

    folder = _stats_head(tmp_path / "s")
    z = dict(np.load(folder / "params.npz"))
    np.savez_compressed(folder / "params.npz", **z, junk=np.zeros(25_000_000, np.float32))  # 100 MB, ~100 kB on disk
    assert (folder / "params.npz").stat().st_size < 1_000_000
    tracemalloc.start()
    with pytest.raises(ValueError, match="holds arrays this head does not use \\(junk\\)"):
        _load(folder)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20_000_000, peak


def test_an_oversized_config_json_is_refused_by_its_size(tmp_path):
    folder = _logit_head(tmp_path / "h")
    c = json.loads((folder / "config.json").read_text())
    c["notes"] = "x" * (2 << 20)  # valid JSON, 2 MiB
    (folder / "config.json").write_text(json.dumps(c))
    with pytest.raises(ValueError, match="config.json: 2,097,.* bytes, more than the 1,048,576"):
        _load(folder)


@pytest.mark.parametrize("damage", ["empty", "truncated", "nested"])
def test_a_damaged_head_is_one_line_from_the_readers_command(small_dataset, tmp_path, capsys, damage):
    folder = _stats_head(tmp_path / "s")
    if damage == "empty":
        (folder / "params.npz").write_bytes(b"")
    elif damage == "truncated":
        data = (folder / "params.npz").read_bytes()
        (folder / "params.npz").write_bytes(data[: len(data) // 2])
    else:
        (folder / "config.json").write_text("[" * 200_000)
    with pytest.raises(ValueError):
        _load(folder)
    code = readers.main(["--dataset", str(small_dataset), "--head", str(folder), "--out", str(tmp_path / "r")])
    assert code == 2
    line = _one_line(capsys)
    assert str(folder) in line, line


# ----------------------------------------------------------------------------- the budget curve's options
@pytest.mark.parametrize(
    "options, words",
    [
        (["--budgets", "0.1", "2"], "--budgets: 2 is not a fraction"),
        (["--budgets", "-0.5"], "--budgets: -0.5 is not a fraction"),
        (["--budgets", "nan"], "--budgets: nan"),
        (["--steps", "-1"], "--steps -1: must be a whole number from 1"),
        (["--seeds", "0"], "--seeds 0: must be"),
        (["--policy-seeds", "0"], "--policy-seeds 0: must be"),
        (["--folds", "100"], "--folds 100: "),
        (["--folds", "1"], "--folds 1: give 0"),
        (["--folds", "-3"], "--folds -3: give 0"),
    ],
)
@pytest.mark.parametrize("command", ["module", "histojax"])
def test_the_budget_curve_refuses_bad_options_in_one_line(small_dataset, tmp_path, capsys, options, words, command):
    from baselines.reading import budget_curve
    from histojax.cli import main as histojax_main

    argv = ["--dataset", str(small_dataset), "--out", str(tmp_path / "bc"), *options]
    code = budget_curve.main(argv) if command == "module" else histojax_main(["budget-curve", *argv])
    assert code == 2
    line = _one_line(capsys)
    assert words in line, line
    assert not (tmp_path / "bc").exists()


# ----------------------------------------------------------------------------- run folders: nothing overwritten, one writer
TRAIN = ["train", "--env", "HistoJAX-Easy-v0", "--total-steps", "512", "--seeds", "1"]


def _finished_run(folder: Path) -> Path:
    (folder / "checkpoint").mkdir(parents=True)
    for name in ("params.msgpack", "log.csv", "log.json", "curve.png"):
        (folder / name).write_bytes(b"a finished run's " + name.encode())
    (folder / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "seed": 0}))
    (folder / "checkpoint" / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "seed": 0}))
    return folder


def _contents(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".histojax-run.lock"
    }


@pytest.mark.parametrize("what", ["users-notes", "slide-head", "finished-run"])
def test_train_out_refuses_a_folder_it_would_overwrite(tmp_path, capsys, what):
    from histojax.cli import main

    out = tmp_path / "exp"
    if what == "users-notes":
        out.mkdir()
        (out / "config.json").write_text('{"my": "notes"}')
    elif what == "slide-head":
        _logit_head(out)
    else:
        _finished_run(out)
    before = _contents(out)
    assert main([*TRAIN, "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert str(out) in line and "--overwrite" in line, line
    assert _contents(out) == before
    if what != "finished-run":  # --overwrite replaces only a run's own files: a user's or a head's are refused still
        assert main([*TRAIN, "--out", str(out), "--overwrite"]) == 2
        assert "did not write" in _one_line(capsys)
        assert _contents(out) == before


def test_overwrite_replaces_only_a_runs_own_state_and_keeps_its_results_until_the_new_ones(tmp_path):
    from baselines.harness import run_folder

    out = _finished_run(tmp_path / "exp")
    assert run_folder.claim(out, {"env_id": "HistoJAX-Easy-v0", "seed": 7}, overwrite=True) == out
    run_folder.release(out)
    assert not (out / "checkpoint").exists() and (out / "params.msgpack").read_bytes().startswith(b"a finished")


def test_an_unfinished_run_of_the_same_config_may_start_again_another_configs_is_refused(tmp_path, capsys):
    from baselines.harness import run_folder

    out = tmp_path / "exp"
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "seed": 0, "lr": 1e-3}))
    assert run_folder.claim(out, {"env_id": "HistoJAX-Easy-v0", "seed": 0}) == out
    run_folder.release(out)
    with pytest.raises(run_folder.RunFolderError, match="unfinished run of another config.*--resume.*--overwrite"):
        run_folder.claim(out, {"env_id": "HistoJAX-Easy-v0", "seed": 7})


def test_the_default_run_folder_is_never_overwritten_the_next_free_number_is_taken(tmp_path, monkeypatch):
    from baselines.harness import run_folder

    monkeypatch.chdir(tmp_path)
    first = _finished_run(Path("runs/ppo-HistoJAX-Easy-v0"))
    before = _contents(first)
    got = run_folder.claim(first, {"env_id": "HistoJAX-Easy-v0", "seed": 0}, default=True)
    run_folder.release(got)
    assert got == Path("runs/ppo-HistoJAX-Easy-v0-2") and _contents(first) == before


def test_one_writer_per_run_folder_and_a_killed_writer_leaves_no_lock(tmp_path, capsys):
    import subprocess
    import sys

    from baselines.harness import run_folder
    from histojax.cli import main

    out = tmp_path / "run"
    out.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            (
                "import fcntl, os, sys, time\n"
                f"fd = os.open({str(out / run_folder.LOCK)!r}, os.O_RDWR | os.O_CREAT)\n"
                "fcntl.flock(fd, fcntl.LOCK_EX); os.write(fd, str(os.getpid()).encode()); print('held', flush=True)\n"
                "time.sleep(120)\n"
            ),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main([*TRAIN, "--out", str(out)]) == 2
        line = _one_line(capsys)
        assert "another training run" in line and str(out) in line, line
        (out / "checkpoint").mkdir()
        (out / "checkpoint" / "config.json").write_text(json.dumps({"algo": "ppo", "env_id": "HistoJAX-Easy-v0"}))
        assert main(["train", "--resume", str(out)]) == 2
        assert "another training run" in _one_line(capsys)
    finally:
        holder.kill()
        holder.wait()
    assert run_folder.claim(out, {"algo": "ppo", "env_id": "HistoJAX-Easy-v0"}) == out  # the OS dropped the lock
    run_folder.release(out)


# ----------------------------------------------------------------------------- undefined results say so
def test_one_class_figures_print_undefined_and_write_null(tmp_path, capsys):
    import types

    from baselines.evaluate.checks import one_class, undefined_figures
    from baselines.evaluate.cli import json_safe, print_table

    params = lambda labels: types.SimpleNamespace(slide=types.SimpleNamespace(slide_label=np.array(labels)))  # noqa: E731
    assert one_class(params([0, 0])) == 0 and one_class(params([1])) == 1 and one_class(params([0, 1])) is None
    row = {
        "episodes": 8,
        "success_rate": 1.0,
        "mean_return": 0.1,
        "mean_length": 2.0,
        "mean_steps_to_success": 2.0,
        "mean_fraction_read": 0.1,
        "mean_fields_of_view": 1.0,
        "success_rate_per_seed": [1.0],
    }
    rows = undefined_figures({"ppo (greedy)": dict(row), "random": dict(row)}, "detection", 0)  # no tumour slide
    assert rows["random"]["success_rate"] is None and rows["random"]["success_rate_per_seed"] == [None]
    diag = undefined_figures({"ppo (greedy)": {**row, "diagnosis_auc": float("nan")}}, "classification", 1)
    assert diag["ppo (greedy)"]["diagnosis_auc"] is None and diag["ppo (greedy)"]["success_rate"] == 1.0
    print_table("t", rows)
    out = capsys.readouterr().out
    assert "100.0%" not in out and "undef.: undefined: one class" in out
    text = json.dumps(json_safe({"results": rows, "x": float("nan"), "y": [np.float32("inf")]}), allow_nan=False)
    assert json.loads(text)["x"] is None and "NaN" not in text


# ----------------------------------------------------------------------------- words
@pytest.mark.parametrize("episodes", ["99999999999999999999", str(2**31), str(2**63)])
def test_evaluate_refuses_a_huge_episode_count_in_one_line(episodes, capsys):
    from histojax.cli import main

    with pytest.raises(SystemExit) as e:
        main(["evaluate", "--env", "HistoJAX-Easy-v0", "--episodes", episodes])
    assert e.value.code == 2
    assert "--episodes" in _one_line(capsys)


def test_checkpoint_every_below_zero_is_refused(tmp_path, capsys):
    from histojax.cli import main

    with pytest.raises(SystemExit) as e:
        main([*TRAIN, "--checkpoint-every", "-1", "--out", str(tmp_path / "r")])
    assert e.value.code == 2 and "--checkpoint-every" in _one_line(capsys)
    assert not (tmp_path / "r").exists()


def test_an_empty_shard_is_refused(tmp_path, capsys):
    from data_tools.__main__ import main as data_main

    (tmp_path / "slides").mkdir()
    for argv in (["dataset", str(tmp_path / "slides"), "--out", str(tmp_path / "ds"), "--shard", ""],):
        assert data_main(argv) == 2
        assert "--shard ''" in _one_line(capsys)


def test_a_published_agent_without_its_training_dataset_says_so_and_suggests_dataset(tmp_path, capsys, monkeypatch):
    import shutil

    from histojax.cli import main

    monkeypatch.chdir(tmp_path)  # runs/r6/ref/validation, recorded in its config.json, is not here
    agent = shutil.copytree(ROOT / "baselines" / "published" / "c16-v1-diagnosis", tmp_path / "agent")
    config = json.loads((agent / "config.json").read_text())  # published before: its training path recorded
    (agent / "config.json").write_text(
        json.dumps({**config, "env_kwargs": {**config["env_kwargs"], "dataset": "runs/r6/ref/validation"}})
    )
    assert main(["evaluate", str(agent), "--episodes", "2"]) == 2
    line = _one_line(capsys)
    assert "runs/r6/ref/validation, which does not exist here" in line and "--dataset" in line, line
    assert "not a dataset folder" not in line


def test_head_fit_on_an_all_normal_training_split_says_so(work, tmp_path, capsys):
    spec = json.loads((work / "dataset.json").read_text())
    spec["train"] = [e for e in spec["train"] if "normal" in e]
    (work / "dataset.json").write_text(json.dumps(spec))
    assert head_fit.main(["--dataset", str(work), "--out", str(tmp_path / "h")]) == 2
    line = _one_line(capsys)
    assert "holds only normal slides" in line and "--val-fraction" not in line, line


def test_a_c16_agent_on_other_features_names_the_dataset_and_the_encoder_it_needs(tmp_path):
    from baselines.evaluate.checks import encoder_refusal

    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "dataset.json").write_text(json.dumps({"encoder": "colour-stats", "train": [], "test": []}))
    config = {"env_id": "HistoJAX-C16-Diagnosis-v1", "obs_mode": "features", "env_kwargs": {"dataset": str(ds)}}
    line = encoder_refusal(config, "published/c16-v1-diagnosis/config.json")
    assert "observes pcam-cnn features" in line and str(ds / "dataset.json") in line and "'colour-stats'" in line
    assert "params.msgpack" not in line
    (ds / "dataset.json").write_text(json.dumps({"encoder": "pcam-cnn", "train": [], "test": []}))
    assert encoder_refusal(config, "c.json") is None
    assert encoder_refusal({**config, "env_id": "HistoJAX-Easy-v0"}, "c.json") is None


def test_a_dataset_without_feature_grids_is_named_not_none(tmp_path):
    from data_tools.errors import BundleError
    from histojax import datasets, registry

    (tmp_path / "dataset.json").write_text(json.dumps({"kind": "histojax dataset", "train": [], "test": []}))
    with pytest.raises(BundleError) as e:
        datasets.check_dataset(
            tmp_path, registry.spec_of("HistoJAX-C16-Diagnosis-v1").settings, "HistoJAX-C16-Diagnosis-v1"
        )
    assert "records no feature grids" in str(e.value) and "None" not in str(e.value)
    assert str(tmp_path / "dataset.json") in str(e.value)


def test_a_coarse_map_entry_the_features_lack_names_the_bundle(tmp_path):
    import types

    from histojax.reading.coarse_map import coarse_maps

    params = types.SimpleNamespace(slide=types.SimpleNamespace(features=np.zeros((10, 11), np.float32)))
    bundle = types.SimpleNamespace(path=tmp_path / "b", metadata={"features": {"encoder": "colour-stats"}})
    with pytest.raises(ValueError) as e:
        coarse_maps(None, params, [bundle], 62)
    assert f"{tmp_path / 'b'}/metadata.json" in str(e.value) and "colour-stats" in str(e.value)


def test_a_read_only_run_folder_is_named_not_a_temporary(tmp_path, monkeypatch, capsys):
    """(Permissions do not bind root, so the refusal to create the lock file is simulated.)"""
    from baselines.harness import run_folder
    from histojax.cli import main

    out = tmp_path / "ro"
    out.mkdir()
    real_open = os.open

    def read_only(path, flags, *a):
        if str(path).startswith(str(out)) and flags & os.O_CREAT:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *a)

    monkeypatch.setattr(run_folder.os, "open", read_only)
    assert main([*TRAIN, "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"error: {out}: cannot be written (Permission denied)") and ".tmp-" not in line, line
