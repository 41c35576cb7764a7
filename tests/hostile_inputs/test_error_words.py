"""The words of error lines: a user error is one line with no debug hint; only an unexpected error (raised inside
a library) says how to see its traceback."""

from __future__ import annotations

import json

from histojax import cli


def _line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    return err


def test_a_users_bad_folder_is_one_line_without_the_debug_hint(tmp_path, capsys):
    (tmp_path / "ds").mkdir()  # not a dataset: a HistojaxDataError the command does not catch itself
    assert (
        cli.main(
            [
                "train",
                "--env",
                "HistoJAX-Easy-v0",
                "--total-steps",
                "512",
                "--dataset",
                str(tmp_path / "ds"),
                "--out",
                str(tmp_path / "r"),
            ]
        )
        == 2
    )
    line = _line(capsys)
    assert "no dataset.json" in line and "HISTOJAX_DEBUG" not in line, line


def test_a_bad_setting_the_project_words_is_a_user_error_without_the_hint(tmp_path, capsys):
    assert cli.main(["train", "--env", "HistoJAX-Nope-v0", "--total-steps", "512", "--out", str(tmp_path / "r")]) == 2
    line = _line(capsys)
    assert "unknown environment id" in line and "HISTOJAX_DEBUG" not in line, line
    assert not (tmp_path / "r").exists()  # refused after its claim: the folder it made is gone


def test_an_unexpected_error_from_inside_a_library_keeps_the_hint(monkeypatch, capsys):
    monkeypatch.setattr(cli, "_dispatch", lambda command, rest: json.loads("{"))  # a ValueError raised in json
    assert cli.main(["info", "x"]) == 2
    assert _line(capsys).endswith("(HISTOJAX_DEBUG=1 shows the traceback)")


def test_the_published_learned_set_reader_names_the_encoder_mismatch_first(tmp_path):
    from baselines.evaluate.checks import encoder_refusal
    from baselines.published_agents import PUBLISHED

    agent = PUBLISHED / "c16-v2-learned-set-reader" / "config.json"
    (tmp_path / "dataset.json").write_text(json.dumps({"encoder": "colour-stats"}))
    config = json.loads(agent.read_text())
    config["env_kwargs"] = {**(config.get("env_kwargs") or {}), "dataset": str(tmp_path)}
    line = encoder_refusal(config, agent)  # said before the env is made (where a missing downsample would speak)
    assert line is not None and "slide head of pcam-cnn features" in line and "'colour-stats' features" in line, line
    (tmp_path / "dataset.json").write_text(json.dumps({"encoder": "pcam-cnn"}))
    assert encoder_refusal(config, agent) is None


def test_a_negative_seed_is_a_usage_error_not_an_internal_one(tmp_path, capsys):
    import pytest

    with pytest.raises(SystemExit) as e:
        cli.main(["dataset", str(tmp_path), "--out", str(tmp_path / "ds"), "--seed", "-1"])
    assert e.value.code == 2
    line = _line(capsys)
    assert "--seed: '-1' must be in [0, 2**32)" in line and "HISTOJAX_DEBUG" not in line, line
    assert not (tmp_path / "ds").exists()
