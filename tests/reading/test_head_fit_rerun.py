"""A rerun of a head fit keeps the work already done (``head_fit``, ``learned_head_fit``, ``head_mil_fit``: one rule,
:func:`baselines.reading.fitting.claim_head`): the same command over a finished head fits nothing and says so in its
first line; a head of other options is refused in one line naming the difference; ``--restart`` moves the old head
aside to ``OUT.previous-N`` (still a loadable head) and fits again; a fit killed before its head was written is fitted
again and says so; ``learned_head_fit --all-folds`` keeps every finished fold and fits only the missing ones.

The stand-in pcam-cnn bundles of tests/reading/test_head.py (logit and MIL fits) and the TRIDENT-layout cohort of
tests/learned_fixture.py (the learned fit, its training replaced by an untrained head: the bookkeeping, cheaply)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from learned_fixture import untrained_fit
from test_head import make_dataset
from test_head_provenance import FAST
from test_head_provenance import small as small  # noqa: F401  (the module fixture: the cohort with three folds)

from baselines.reading import head_fit, head_mil_fit
from baselines.reading import learned_head_fit as learned
from baselines.reading.fitting import OPTIONS, claim_head
from baselines.reading.slides import HeadDataError
from histojax.reading import heads
from histojax.reading.heads.files import TEMP_MARKER
from histojax.reading.heads.learned import KIND

DONE = "holds a finished head of this command: nothing to fit (--restart fits it again)"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("rerun") / "ds", n_train=20, n_test=2)


def _out(capsys) -> tuple[list[str], list[str]]:
    c = capsys.readouterr()
    return c.out.strip().splitlines(), [line for line in c.err.strip().splitlines() if line.startswith("error")]


@pytest.mark.slow  # about 14 s (four logit fits); the default tests below cover each behaviour on the learned fit
def test_a_logit_head_fit_rerun_keeps_refuses_restarts_and_refits_a_killed_fit(dataset, tmp_path, capsys):
    out = tmp_path / "head"
    argv = ["--dataset", str(dataset), "--out", str(out), "--ks", "1", "3", "--minus-median", "--val-fraction", "0.3"]
    assert head_fit.main(argv) == 0
    saved = (out / "config.json").read_bytes()
    assert json.loads(saved)[OPTIONS]["--seed"] == 0
    capsys.readouterr()
    assert head_fit.main(argv) == 0  # the same command: nothing fitted, the head untouched
    lines, _ = _out(capsys)
    assert lines[0] == f"{out} {DONE}" and len(lines) == 1
    assert (out / "config.json").read_bytes() == saved
    assert head_fit.main([*argv, "--seed", "1"]) == 2  # another config: refused, naming the difference
    _, err = _out(capsys)
    assert len(err) == 1 and f"{out} holds a head fitted with --seed 0, not 1; --restart moves it aside" in err[0]
    assert (out / "config.json").read_bytes() == saved
    assert head_fit.main([*argv, "--seed", "1", "--restart"]) == 0  # moved aside, never deleted
    lines, _ = _out(capsys)
    assert lines[0] == f"{out}: moved the head there aside to {out}.previous-1 (--restart); fitting it again"
    assert (tmp_path / "head.previous-1" / "config.json").read_bytes() == saved
    assert heads.load(tmp_path / "head.previous-1").kind == heads.load(out).kind  # still a head folder
    assert json.loads((out / "config.json").read_text())[OPTIONS]["--seed"] == 1
    (out / "config.json").unlink()  # a fit killed between its parameters and its config.json (written last)
    assert head_fit.main([*argv, "--seed", "1"]) == 0
    lines, _ = _out(capsys)
    assert lines[0].startswith(f"{out} holds no finished head (a fit killed while writing its head left params.json")
    assert lines[0].endswith(": fitting it again") and (out / "config.json").is_file()


def test_a_head_fitted_before_its_options_were_recorded_is_refused_not_refitted(tmp_path, capsys):
    out = tmp_path / "head"
    out.mkdir()
    (out / "params.npz").write_bytes(b"")
    (out / "config.json").write_text(json.dumps({"kind": KIND, "files": ["params.npz"]}))
    with pytest.raises(HeadDataError, match="records no fit options") as e:
        claim_head(out, KIND, {"--seed": 0})
    assert str(e.value).startswith(f"{out} holds a head whose config.json") and "--restart" in str(e.value)
    assert claim_head(out, KIND, {"--seed": 0}, restart=True) == "restarted" and not out.exists()
    assert (tmp_path / "head.previous-1" / "config.json").is_file()


def test_a_fit_killed_before_its_head_was_written_is_fitted_again_and_says_so(tmp_path, capsys):
    out = tmp_path / "head"
    assert claim_head(out, KIND, {}) == "new" and capsys.readouterr().out == ""  # nothing there: nothing said
    (tmp_path / ".head.tmp-0123abcd").mkdir()  # killed while saving (learned: one atomic folder)
    (tmp_path / ".head.tmp-0123abcd" / TEMP_MARKER).write_text("x")
    assert claim_head(out, KIND, {}) == "again"
    assert capsys.readouterr().out.strip() == (
        f"{out} holds no finished head (a fit killed while saving its head left .head.tmp-0123abcd): fitting it again"
    )
    shutil.rmtree(tmp_path / ".head.tmp-0123abcd")
    out.mkdir()
    (out / "params.json").write_text("{}")  # killed between the parameters and config.json (written last)
    assert claim_head(out, KIND, {}) == "again"
    assert "left params.json without config.json): fitting it again" in capsys.readouterr().out


@pytest.mark.slow  # about 24 s (MIL candidates scored on validation); the learned fit's tests cover the rule
def test_a_mil_head_fit_rerun_keeps_its_head_and_refuses_another_config(dataset, tmp_path, capsys):
    out = tmp_path / "mil"
    argv = ["--dataset", str(dataset), "--cache", str(tmp_path / "c.npz"), "--out", str(out)]
    argv += ["--candidates", "stats", "--seeds", "1", "--val-fraction", "0.3"]
    assert head_mil_fit._main()(argv) == 0
    saved = (out / "config.json").read_bytes()
    capsys.readouterr()
    assert head_mil_fit._main()(argv) == 0  # no --table: still nothing fitted again
    lines, _ = _out(capsys)
    assert lines == [f"{out} {DONE}"] and (out / "config.json").read_bytes() == saved
    assert head_mil_fit._main()([*argv, "--seeds", "2"]) == 2
    _, err = _out(capsys)
    assert len(err) == 1 and "holds a head fitted with --seeds 1, not 2" in err[0]


@pytest.mark.slow  # about 19 s (five fold fits); test_all_folds_keeps_finished_folds_and_fits_the_rest is the default
def test_learned_all_folds_rerun_fits_only_the_unfinished_fold(small, tmp_path, capsys, monkeypatch):  # noqa: F811
    fitted = []

    def counted(train_slides, val, *a, **k):
        fitted.append(len(train_slides))
        return untrained_fit(train_slides, val, *a, **k)

    monkeypatch.setattr(learned, "train", counted)
    monkeypatch.setattr(learned, "check_head", lambda *a, **k: None)
    out = tmp_path / "heads"
    argv = ["--dataset", str(small["root"]), "--out", str(out), "--all-folds", "--val-fraction", "0.4", *FAST]
    assert learned._main()(argv) == 0 and len(fitted) == 3
    kept = {i: (out / f"fold{i}" / "config.json").read_bytes() for i in (0, 2)}
    shutil.rmtree(out / "fold1")  # killed while saving fold 1: its marked temporary left beside it
    (out / ".fold1.tmp-0123abcd").mkdir()
    (out / ".fold1.tmp-0123abcd" / TEMP_MARKER).write_text("x")
    capsys.readouterr()
    fitted.clear()
    assert learned._main()(argv) == 0 and len(fitted) == 1  # fold 1 only
    lines, _ = _out(capsys)
    assert f"fold 0: finished, kept ({out / 'fold0'})" in lines and f"fold 2: finished, kept ({out / 'fold2'})" in lines
    assert any(line.startswith(f"{out / 'fold1'} holds no finished head (a fit killed") for line in lines)
    assert all((out / f"fold{i}" / "config.json").read_bytes() == b for i, b in kept.items())
    assert learned._main()([*argv, "--seed", "1"]) == 2 and len(fitted) == 1  # refused before any fold is fitted
    _, err = _out(capsys)
    assert len(err) == 1 and f"{out / 'fold0'} holds a head fitted with --seed 0, not 1" in err[0]
    assert learned._main()([*argv, "--seed", "1", "--restart"]) == 0 and len(fitted) == 4
    assert sorted(p.name for p in (tmp_path / "heads.previous-1").glob("fold*")) == ["fold0", "fold1", "fold2"]
    assert json.loads((out / "fold0" / "config.json").read_text())[OPTIONS]["--seed"] == 1


def test_a_learned_head_rerun_fits_nothing_refuses_another_config_and_restarts(small, tmp_path, capsys, monkeypatch):  # noqa: F811
    monkeypatch.setattr(learned, "train", untrained_fit)
    monkeypatch.setattr(learned, "check_head", lambda *a, **k: None)
    out = tmp_path / "h"
    argv = ["--dataset", str(small["root"]), "--out", str(out), "--val-fraction", "0.4", *FAST]
    assert learned._main()(argv) == 0
    saved = (out / "config.json").read_bytes()
    with monkeypatch.context() as m:
        m.setattr(learned, "load_split", lambda *a, **k: pytest.fail("read slides for a finished head"))
        capsys.readouterr()
        assert learned._main()(argv) == 0
        assert _out(capsys)[0] == [f"{out} {DONE}"]
        assert learned._main()([*argv, "--steps", "50"]) == 2
        err = _out(capsys)[1]
        assert (
            len(err) == 1 and f"{out} holds a head fitted with --steps 100, not 50; --restart moves it aside" in err[0]
        )
    assert (out / "config.json").read_bytes() == saved
    assert learned._main()([*argv, "--steps", "50", "--restart"]) == 0
    lines, _ = _out(capsys)
    assert lines[0] == f"{out}: moved the head there aside to {out}.previous-1 (--restart); fitting it again"
    assert (tmp_path / "h.previous-1" / "config.json").read_bytes() == saved
    assert heads.load(tmp_path / "h.previous-1").kind == heads.load(out).kind  # the old head: still a head folder
    assert json.loads((out / "config.json").read_text())[OPTIONS]["--steps"] == 50


def test_all_folds_keeps_finished_folds_and_fits_the_rest(small, tmp_path, capsys, monkeypatch):  # noqa: F811
    """The fold loop of ``--all-folds`` (each fold's fit replaced by writing its head from one fitted head)."""
    monkeypatch.setattr(learned, "train", untrained_fit)
    monkeypatch.setattr(learned, "check_head", lambda *a, **k: None)
    argv = ["--dataset", str(small["root"]), "--val-fraction", "0.4", *FAST]
    assert learned._main()([*argv, "--out", str(tmp_path / "one"), "--fold", "0"]) == 0
    one = json.loads((tmp_path / "one" / "config.json").read_text())
    fitted = []

    def fake_run(args, parser=None):  # fold I's fit: fold 0's head relabelled fold I
        fitted.append(args.fold)
        Path(args.out).mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp_path / "one" / "params.npz", Path(args.out) / "params.npz")
        cfg = {**one, OPTIONS: {**one[OPTIONS], "--fold": args.fold}}
        (Path(args.out) / "config.json").write_text(json.dumps(cfg))
        return 0

    monkeypatch.setattr(learned, "run", fake_run)
    out = tmp_path / "heads"
    folds = ["--out", str(out), "--all-folds"]
    assert learned.all_folds_command(learned_args([*argv, *folds])) == 0 and fitted == [0, 1, 2]
    shutil.rmtree(out / "fold1")  # a kill during fold 1: fold 0 and 2 finished
    fitted.clear()
    capsys.readouterr()
    assert learned.all_folds_command(learned_args([*argv, *folds])) == 0 and fitted == [1]
    lines, _ = _out(capsys)
    assert f"fold 0: finished, kept ({out / 'fold0'})" in lines and f"fold 2: finished, kept ({out / 'fold2'})" in lines
    assert lines[-1].startswith("kept 2 finished, fitted 1 of 3 heads, one per fold")
    assert learned.all_folds_command(learned_args([*argv, *folds, "--seed", "1"])) == 2 and fitted == [1]
    err = _out(capsys)[1]
    assert len(err) == 1 and f"{out / 'fold0'} holds a head fitted with --seed 0, not 1" in err[0]
    assert learned.all_folds_command(learned_args([*argv, *folds, "--seed", "1", "--restart"])) == 0
    assert fitted == [1, 0, 1, 2]
    assert sorted(p.name for p in (tmp_path / "heads.previous-1").iterdir()) == ["fold0", "fold1", "fold2"]


def learned_args(argv):
    import argparse

    p = argparse.ArgumentParser()
    learned.add_arguments(p)
    return p.parse_args(argv)
