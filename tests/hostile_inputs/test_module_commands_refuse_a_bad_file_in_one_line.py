"""``python -m baselines.<module>`` commands say a malformed file found deep inside (a ``dataset.json`` the env
loader reads) in one line, exit 2, as ``histojax`` does (was: ``python -m baselines.ppo_rnn --dataset DIR`` with a
malformed ``dataset.json`` ended in a ``BundleError`` traceback, exit 1; so did ``baselines.ppo``, ``baselines.dqn``
and ``baselines.rotation``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def garbage(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "dataset.json").write_text("not json")
    return tmp_path / "ds"


@pytest.mark.parametrize("module", ["ppo_rnn", "ppo", "dqn"])
def test_a_trainer_on_a_malformed_dataset_json_is_one_line(module, garbage, tmp_path, capsys):
    import importlib

    main = importlib.import_module(f"baselines.{module}").main
    assert main(["--dataset", str(garbage), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"error: {garbage / 'dataset.json'}: malformed JSON (Expecting value: line 1 column 1 (char 0))"
    assert all(line.startswith("warning: ") for line in err[:-1]), err


def test_debug_still_shows_the_traceback(garbage, tmp_path, monkeypatch):
    from baselines import ppo_rnn
    from data_tools.errors import HistojaxDataError

    monkeypatch.setenv("HISTOJAX_DEBUG", "1")
    with pytest.raises(HistojaxDataError):
        ppo_rnn.main(["--dataset", str(garbage), "--out", str(tmp_path / "run")])


def test_in_a_real_process_there_is_no_traceback(garbage, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "baselines.ppo_rnn", "--dataset", str(garbage), "--out", str(tmp_path / "run")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr + proc.stdout, proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: {garbage / 'dataset.json'}: malformed JSON")
