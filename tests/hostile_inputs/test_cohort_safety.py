"""The cohort path: nothing of the user's is deleted or overwritten (folders inside ``--out``, a
previous bundle during a failed rebuild, a ``dataset.json`` the user wrote, ``build --overwrite`` over a folder
histojax cannot prove it wrote), a bundle never reads a file outside itself, ``--jobs`` workers die with their
parent, a split that failures left unscorable is refused, and the build side's one-line words (another tool's
``plan.json``, a full disk, colliding record names, stale leftovers of any name).

Stand-in slides are small pyramidal TIFFs cut from the real pixels of the embedded CMU-1-Small-Region.svs
(CC0 1.0, see tests/data/LICENSES.md).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from slide_helpers import crop, pyramid, sample_pixels

from data_tools.__main__ import main as data_main
from data_tools.bundle_files.reading import load_bundle, read_metadata
from data_tools.bundle_files.writes import mark_temporary
from data_tools.datasets.build import build_dataset
from data_tools.errors import BundleError, HistojaxDataError

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def pixels():
    return sample_pixels()


BLANK = np.full((640, 512, 3), 242, np.uint8)  # glass only: fails with "no tissue found"


@pytest.fixture(scope="module")
def cohort(tmp_path_factory, pixels):
    """Three slides with a label table giving the split: s1, s2 train, s3 test."""
    root = tmp_path_factory.mktemp("cohort")
    for i, name in enumerate(("s1", "s2", "s3")):
        pyramid(root / "slides" / f"{name}.tif", crop(pixels, i))
    (root / "labels.csv").write_text("slide,label,split\ns1,0,train\ns2,0,train\ns3,0,test\n")
    return root / "slides", root / "labels.csv"


@pytest.fixture(scope="module")
def built(tmp_path_factory, cohort):
    """The cohort built once (levels 3)."""
    slides, labels = cohort
    out = tmp_path_factory.mktemp("built") / "o"
    s = build_dataset(slides, out, labels=labels, levels=(3,), progress=False)
    assert s["dataset"] is not None and not s["failed"]
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


def _tree(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else b"<dir>") for p in sorted(folder.rglob("*"))
    }


# ------------------------------------------------------------------ 1. a user's folder inside --out
def test_a_users_folder_inside_out_is_never_removed(cohort, tmp_path, capsys):
    slides, labels = cohort
    out = tmp_path / "o"
    (out / "bundles" / "s1").mkdir(parents=True)
    (out / "bundles" / "s1" / "thesis.txt").write_text("t")
    code, text, err = _run(
        ["dataset", str(slides), "--out", str(out), "--labels", str(labels), "--levels", "3", "--quiet"], capsys
    )
    assert (out / "bundles" / "s1" / "thesis.txt").read_text() == "t"  # before: removed when s1 failed
    assert sorted(p.name for p in (out / "bundles" / "s1").iterdir()) == ["thesis.txt"]
    assert code == 1 and "failed s1:" in text and "thesis.txt" in text and "did not write" in text
    ds = json.loads((out / "dataset.json").read_text())
    assert "s1" in ds["failed"] and "bundles/s1" not in ds["train"]


# ------------------------------------------------------------------ 2. a failed rebuild keeps the old bundle
def _full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_failed_rebuild_keeps_the_previous_bundle_and_dataset_json(built, cohort, tmp_path, monkeypatch):
    import data_tools.bundle

    slides, labels = cohort
    slides = shutil.copytree(slides, tmp_path / "slides")  # same bytes and mtimes: the records still match
    work = tmp_path / "o"
    shutil.copytree(built, work)
    before = {n: read_metadata(work / "bundles" / n)["metadata_sha256"] for n in ("s1", "s2", "s3")}
    later = time.time() + 100
    for tif in slides.glob("*.tif"):  # `touch SLIDES/*`: every slide is rebuilt
        os.utime(tif, (later, later))
    monkeypatch.setattr(data_tools.bundle, "_build_into", _full_disk)  # the disk is full while writing levels
    s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False)
    for n, digest in before.items():  # before: every old bundle deleted, dataset.json rewritten without them
        assert read_metadata(work / "bundles" / n)["metadata_sha256"] == digest
        load_bundle(work / "bundles" / n)
    assert sorted(s["failed"]) == ["s1", "s2", "s3"] and sorted(s["kept"]) == ["s1", "s2", "s3"]
    # the reason names where it was writing (a full disk's OSError names no file): the bundle, not its temporary
    assert all(
        f"bundles/{n}:" in r and "No space left on device" in r and ".tmp-" not in r for n, r in s["failed"].items()
    )
    ds = json.loads((work / "dataset.json").read_text())
    assert ds["train"] == ["bundles/s1", "bundles/s2"] and ds["test"] == ["bundles/s3"]
    assert sorted(ds["kept_after_failed_rebuild"]) == ["s1", "s2", "s3"]
    assert not list((work / "bundles").glob(".*tmp-*"))  # the half-built temporaries are gone
    monkeypatch.undo()
    for tif in slides.glob("*.tif"):
        os.utime(tif, (later, later))
    s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False)  # the disk freed: rebuilt, swapped
    assert sorted(s["built"]) == ["s1", "s2", "s3"] and not s["failed"]
    assert "kept_after_failed_rebuild" not in s["dataset"] and not list((work / "records").rglob("failed/*.json"))


def test_restart_keeps_dataset_json_loadable_during_the_rebuild(built, cohort, tmp_path, monkeypatch):
    """``--restart`` no longer deletes dataset.json first: ``make(dataset=...)`` works while slides rebuild,
    and a rebuild that fails leaves the old bundles."""
    import data_tools.bundle
    from histojax.datasets import dataset_slides

    slides, labels = cohort
    work = tmp_path / "o"
    shutil.copytree(built, work)
    seen = []

    def check_then_fail(*args, **kwargs):
        seen.append(len(dataset_slides(work, "all")))  # before: "not a dataset folder (no dataset.json)"
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(data_tools.bundle, "build_bundle", check_then_fail)
    with pytest.raises(HistojaxDataError, match="the test split would hold no slide.*s3: .*No space left"):
        build_dataset(
            slides, work, labels=labels, levels=(3,), restart=True, progress=False, seed=1
        )  # another seed: new options, every slide rebuilt, and every rebuild fails
    assert seen == [3, 3, 3]
    assert all((work / "bundles" / n / "metadata.json").is_file() for n in ("s1", "s2", "s3"))
    assert len(dataset_slides(work, "all")) == 3  # the old dataset.json stays, its bundles whole
    assert json.loads((work / "plan.json").read_text())["options"]["seed"] == 1


# ------------------------------------------------------------------ 3. a dataset.json the user wrote
def test_a_dataset_json_the_user_wrote_is_never_overwritten(cohort, built, tmp_path, capsys):
    slides, labels = cohort
    out = tmp_path / "o"
    out.mkdir()
    (out / "dataset.json").write_text("{}\n")
    line = _one_error(
        ["dataset", str(slides), "--out", str(out), "--labels", str(labels), "--levels", "3", "--quiet"], capsys
    )
    assert "dataset.json" in line and "not written by histojax dataset or c16" in line
    assert (out / "dataset.json").read_text() == "{}\n" and sorted(p.name for p in out.iterdir()) == ["dataset.json"]
    # one histojax wrote, then edited by hand: refused too; the same, as written: accepted
    work = tmp_path / "w"
    shutil.copytree(built, work)
    ds = json.loads((work / "dataset.json").read_text())
    (work / "dataset.json").write_text(json.dumps({**ds, "test": []}))
    assert "not written by histojax dataset or c16" in _one_error(["dataset", "--merge", "--out", str(work)], capsys)
    (work / "dataset.json").write_text(json.dumps(ds))
    assert _run(["dataset", "--merge", "--out", str(work)], capsys)[0] == 0
    # written before dataset.json was sealed (no digest, histojax's kind): still histojax's
    (work / "dataset.json").write_text(json.dumps({k: v for k, v in ds.items() if k != "dataset_sha256"}))
    assert _run(["dataset", "--merge", "--out", str(work)], capsys)[0] == 0
    assert "dataset_sha256" in json.loads((work / "dataset.json").read_text())


# ------------------------------------------------------------------ 4. build --overwrite proves what it replaces
@pytest.mark.parametrize("plant", ["empty metadata.json", "dataset.json", "a bundle plus a file"])
def test_build_overwrite_replaces_only_what_histojax_wrote(built, cohort, tmp_path, capsys, plant):
    slides, _ = cohort
    out = tmp_path / "f"
    if plant == "a bundle plus a file":
        shutil.copytree(built / "bundles" / "s1", out)
    else:
        out.mkdir()
        (out / ("metadata.json" if plant.startswith("empty") else "dataset.json")).write_text("")
    (out / "thesis.txt").write_text("years of work")
    before = _tree(out)
    line = _one_error(
        ["build", str(slides / "s2.tif"), "--out", str(out), "--overwrite", "--levels", "3", "--quiet"], capsys
    )
    assert str(out) in line and "refusing to overwrite" in line
    assert _tree(out) == before  # before: the folder was wiped
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_build_overwrite_still_replaces_its_own_bundle(built, cohort, tmp_path, capsys):
    slides, _ = cohort
    out = tmp_path / "f"
    shutil.copytree(built / "bundles" / "s1", out)
    code, _, err = _run(
        ["build", str(slides / "s2.tif"), "--out", str(out), "--overwrite", "--levels", "3", "--quiet"], capsys
    )
    assert code == 0, err
    assert read_metadata(out).source["file"] == "s2.tif"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


# ------------------------------------------------------------------ 5. a bundle never reads outside itself
@pytest.mark.parametrize("verify", [True, False])
def test_a_symlinked_bundle_entry_is_refused(built, tmp_path, verify):
    bundle = tmp_path / "b"
    shutil.copytree(built / "bundles" / "s1", bundle)
    outside = tmp_path / "outside.npy"
    shutil.copy(bundle / "tissue.npy", outside)  # the genuine bytes (checksum matches), outside the bundle
    (bundle / "tissue.npy").unlink()
    (bundle / "tissue.npy").symlink_to(outside)
    with pytest.raises(BundleError, match=r"entry 'tissue\.npy' is a symbolic link") as info:
        load_bundle(bundle, verify=verify)  # before: loaded the file outside
    assert str(bundle) in str(info.value)
    (bundle / "tissue.npy").unlink()
    (bundle / "tissue.npy").symlink_to("/etc/passwd")
    with pytest.raises(BundleError, match=r"tissue\.npy' is a symbolic link \(to /etc/passwd\)"):
        load_bundle(bundle, verify=verify)  # before: opened and hashed /etc/passwd
    (bundle / "tissue.npy").unlink()
    os.mkfifo(bundle / "tissue.npy")  # not a regular file: refused without opening it (no hang)
    with pytest.raises(BundleError, match="not a regular file"):
        load_bundle(bundle, verify=verify)


def test_a_symlinked_metadata_json_is_refused(built, tmp_path):
    bundle = tmp_path / "b"
    shutil.copytree(built / "bundles" / "s1", bundle)
    (tmp_path / "m.json").write_bytes((bundle / "metadata.json").read_bytes())
    (bundle / "metadata.json").unlink()
    (bundle / "metadata.json").symlink_to(tmp_path / "m.json")
    with pytest.raises(BundleError, match="'metadata.json' is a symbolic link"):
        read_metadata(bundle)


# ------------------------------------------------------------------ 8. --jobs workers die with their parent
def _children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
            cmd = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        fields = text.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and b"spawn_main" in cmd:
            found.append(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")  # a zombie nobody reaps is dead


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_jobs_workers_die_with_their_parent(cohort, tmp_path, sig):
    slides, labels = cohort
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "data_tools",
            "dataset",
            str(slides),
            "--out",
            str(tmp_path / "o"),
            "--labels",
            str(labels),
            "--levels",
            "3",
            "--jobs",
            "2",
            "--quiet",
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    workers: list[int] = []
    try:
        deadline = time.time() + 120
        while len(workers) < 2 and time.time() < deadline and proc.poll() is None:
            time.sleep(0.05)
            workers = _children(proc.pid)
        assert len(workers) == 2, "the pool's two workers never started"
        time.sleep(1.0)  # the workers past their initializer, building
        proc.send_signal(sig)
        proc.wait(timeout=30)
        deadline = time.time() + 10
        while any(map(_alive, workers)) and time.time() < deadline:
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)], "workers outlived their parent"  # before: alive for good
    finally:
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------ 10. a split that cannot be scored
def test_failures_that_empty_the_test_split_are_refused(pixels, tmp_path, capsys):
    slides = tmp_path / "slides"
    pyramid(slides / "a.tif", crop(pixels, 1))
    pyramid(slides / "b.tif", crop(pixels, 2))
    pyramid(slides / "c.tif", BLANK)  # the one test slide fails: no tissue
    (tmp_path / "labels.csv").write_text("slide,label,split\na,0,train\nb,0,train\nc,0,test\n")
    out = tmp_path / "o"
    line = _one_error(
        [
            "dataset",
            str(slides),
            "--out",
            str(out),
            "--labels",
            str(tmp_path / "labels.csv"),
            "--levels",
            "3",
            "--quiet",
        ],
        capsys,
    )  # before: exit 0 (1) with 0 test slides
    assert "the test split would hold no slide" in line and "c: " in line and "no tissue" in line
    assert not (out / "dataset.json").exists()
    assert (out / "bundles" / "a" / "metadata.json").is_file()  # the built slides are kept


def test_failures_that_leave_no_tumour_slide_in_test_are_refused(pixels, tmp_path, capsys):
    from data_tools.datasets.build import check_scorable

    plan = {
        "slides": {
            "a": {"split": "train", "label": 1},
            "b": {"split": "test", "label": 1},
            "c": {"split": "test", "label": 0},
        }
    }
    with pytest.raises(HistojaxDataError, match="test split would hold no tumour slide.*b: no tissue"):
        check_scorable(tmp_path, plan, {"a": {}, "c": {}}, {"b": "no tissue"})
    check_scorable(tmp_path, plan, {"a": {}, "b": {}, "c": {}}, {})


# ------------------------------------------------------------------ 16 / 17. build-side words
@pytest.mark.parametrize("plan", [{"steps": ["fetch", "train"]}, {"slides": 5}, [1, 2], "not json"])
def test_another_tools_plan_json_is_one_line_and_untouched(cohort, tmp_path, capsys, plan):
    slides, labels = cohort
    out = tmp_path / "o"
    out.mkdir()
    (out / "plan.json").write_text(plan if isinstance(plan, str) else json.dumps(plan))
    before = _tree(out)
    line = _one_error(
        ["dataset", str(slides), "--out", str(out), "--labels", str(labels), "--levels", "3", "--quiet"], capsys
    )  # before: KeyError / "'int' object is not iterable" tracebacks
    assert "plan.json" in line and "histojax dataset" in line
    assert _tree(out) == before
    for extra in ([], ["--restart"]):
        assert "plan.json" in _one_error(
            ["dataset", str(slides), "--out", str(out), "--levels", "3", "--quiet", *extra], capsys
        )
    assert "plan.json" in _one_error(["dataset", "--merge", "--out", str(out)], capsys)
    assert _tree(out) == before


def test_a_full_disk_names_the_file(cohort, tmp_path, capsys, monkeypatch):
    import data_tools.bundle_files.writes as writes

    slides, labels = cohort
    monkeypatch.setattr(writes.os, "fsync", _full_disk)
    line = _one_error(
        ["dataset", str(slides), "--out", str(tmp_path / "o"), "--labels", str(labels), "--levels", "3", "--quiet"],
        capsys,
    )
    assert "No space left on device" in line and "plan.json" in line  # before: "error: No space left on device"


def test_record_names_never_collide(pixels, tmp_path, capsys):
    """``x.tif`` (fails) beside ``x.failed.tif``: the failure of x and the record of x.failed were one file."""
    slides = tmp_path / "slides"
    pyramid(slides / "x.tif", BLANK)
    pyramid(slides / "x.failed.tif", crop(pixels, 1))
    pyramid(slides / "y.tif", crop(pixels, 2))
    (tmp_path / "labels.csv").write_text("slide,label,split\nx,0,train\nx.failed,0,train\ny,0,test\n")
    out = tmp_path / "o"
    code, text, err = _run(
        [
            "dataset",
            str(slides),
            "--out",
            str(out),
            "--labels",
            str(tmp_path / "labels.csv"),
            "--levels",
            "3",
            "--quiet",
        ],
        capsys,
    )
    assert code == 1, err  # before: dataset.json never written
    ds = json.loads((out / "dataset.json").read_text())
    assert list(ds["failed"]) == ["x"] and ds["train"] == ["bundles/x.failed"]
    assert _run(["dataset", "--merge", "--out", str(out)], capsys)[0] == 1  # before: "x not built yet"


def test_legacy_failure_records_are_still_read(built, tmp_path):
    from data_tools.datasets.build import collect_records

    work = tmp_path / "o"
    shutil.copytree(built, work)
    (work / "records" / "s3.json").unlink()
    (work / "records" / "s3.failed.json").write_text(json.dumps({"name": "s3", "reason": "no tissue"}))
    assert collect_records(work, ["s1", "s3"])[1] == {"s3": "no tissue"}


# ------------------------------------------------------------------ 19. leftovers of killed builds of any name
def test_a_build_removes_stale_leftovers_of_other_names(cohort, tmp_path):
    from data_tools.bundle import build_bundle

    slides, _ = cohort
    parent = tmp_path / "bundles"
    dead = mark_temporary(parent / ".other.tmp-0badf00d")
    (dead / "pixels_00.npy").write_bytes(b"\0" * 1000)
    (parent / ".other.lock").write_text("")  # a killed build's lock file
    (parent / ".gone.dataset-lock").write_text("4242")
    aside = parent / ".prev.old-0badf00d"  # killed between moving the previous bundle aside and the swap
    mark_temporary(aside)
    (aside / "metadata.json").write_text("{}")
    mine = parent / ".notes.tmp-12345678"  # not a bundle's files: not histojax's to judge
    mine.mkdir()
    (mine / "thesis.txt").write_text("t")
    build_bundle(slides / "s1.tif", parent / "new", level_sets=(3,), progress=False)
    left = sorted(p.name for p in parent.iterdir())
    assert left == [".notes.tmp-12345678", "new", "prev"]  # before: .other.tmp-*, .other.lock, .gone… stayed
    assert (parent / "prev" / "metadata.json").read_text() == "{}"


def test_a_dataset_run_removes_stale_lock_files(built, cohort, tmp_path):
    slides, labels = cohort
    work = tmp_path / "o"
    shutil.copytree(built, work)
    (work / "bundles" / ".s9.dataset-lock").write_text("4242")
    (work / "bundles" / ".s9.lock").write_text("")
    (mark_temporary(work / "records" / ".s1.json.tmp-0badf00d") / "s1.json").write_text("{")
    s = build_dataset(slides, work, labels=labels, levels=(3,), progress=False)
    assert sorted(s["resumed"]) == ["s1", "s2", "s3"]
    assert not list(work.rglob("*lock")) and not list(work.rglob(".*.tmp-*"))


def test_make_during_a_first_build_says_it_is_being_built(tmp_path):
    """Before dataset.json exists, ``make(dataset=...)`` says the folder is being built, naming a slide lock,
    not "not a dataset folder ... make one with synth"."""
    from data_tools.datasets.locks import bundle_lock_path, file_lock
    from histojax.datasets import dataset_slides

    out = tmp_path / "o"
    (out / "bundles").mkdir(parents=True)
    (out / "plan.json").write_text("{}")
    with file_lock(bundle_lock_path(out / "bundles" / "s1")):
        with pytest.raises(
            BundleError,
            match=r"being built by `histojax dataset` \(1 slide lock\(s\) held, e\.g\. "
            r"bundles/\.s1\.dataset-lock\).*--merge",
        ):
            dataset_slides(out)
    with pytest.raises(BundleError, match="not every slide recorded"):
        dataset_slides(out)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_worker_killed_mid_build_is_one_line(cohort, tmp_path, capsys):
    """A ``--jobs`` worker killed (as the out-of-memory killer would) is one line naming --out, not a
    ``BrokenProcessPool`` traceback; a rerun resumes."""
    import threading

    slides, labels = cohort
    out = tmp_path / "o"
    killed = []

    def kill_a_worker():
        deadline = time.time() + 120
        while time.time() < deadline and not killed:
            workers = _children(os.getpid())
            if workers:
                time.sleep(0.5)
                os.kill(workers[0], signal.SIGKILL)
                killed.append(workers[0])
            time.sleep(0.05)

    threading.Thread(target=kill_a_worker, daemon=True).start()
    line = _one_error(
        ["dataset", str(slides), "--out", str(out), "--labels", str(labels), "--levels", "3", "--jobs", "2", "--quiet"],
        capsys,
    )
    assert killed and str(out) in line and "worker process died" in line and "rerun to resume" in line
    s = build_dataset(slides, out, labels=labels, levels=(3,), progress=False)
    assert s["dataset"] is not None and not s["failed"] and not list(out.rglob(".*.tmp-*"))
