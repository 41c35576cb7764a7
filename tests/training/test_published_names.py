"""The published agents and heads by name: ``histojax published`` lists them with what each was trained on, a bare
name on ``histojax evaluate`` reaches the packaged folder from any working folder, and the command's own packages
are never taken from the working folder (``python -m`` puts it first on the import path). The installed wheel's
side of this is in tests/project/test_wheel.py (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from baselines.published_agents import PUBLISHED, describe, published_names, published_or_path
from histojax import cli

ROOT = Path(__file__).resolve().parents[2]


def test_every_published_folder_has_a_name_and_what_it_was_trained_on():
    names = published_names()
    assert names == sorted(p.name for p in PUBLISHED.iterdir() if p.is_dir())
    assert {"c16-v2-set-reader", "c16-v2-head", "c16-v1-diagnosis"} <= set(names)
    for name in names:
        d = describe(name)
        record = (
            json.loads((PUBLISHED / name / "published.json").read_text())["trained_on"]
            if d["kind"] == "agent"
            else json.loads((PUBLISHED / name / "config.json").read_text())["fitted_on"]
        )
        assert d["trained_on"].startswith(f"{record['dataset']}, {record['split']}, {record['slides']} slides"), name
    assert describe("c16-v2-set-reader")["what"].endswith("diagnoses through c16-v2-head")
    assert describe("c16-v2-head")["kind"] == "head"


def test_histojax_published_lists_them_and_shows_one_in_full(capsys):
    assert cli.main(["published"]) == 0
    out = capsys.readouterr().out
    for name in published_names():
        line = next(row for row in out.splitlines() if row.startswith(name + " "))
        assert describe(name)["trained_on"] in line
    assert cli.main(["published", "c16-v2-set-reader"]) == 0
    out = capsys.readouterr().out
    assert "trained on: c16-full, train, 128 slides" in out and "chosen by: validation AUC" in out


def test_histojax_published_shows_the_slides_each_records_having_seen(capsys):
    """An agent's ``slides_seen.json`` and a head's ``config.json`` ``slides_seen``: how many slides every scorer
    refuses it (those it trained or was fitted on, and those it was validated on)."""
    assert cli.main(["published", "c16-v2-set-reader"]) == 0
    seen = json.loads((PUBLISHED / "c16-v2-set-reader" / "slides_seen.json").read_text())
    n = len(set(seen["fitted"]) | set(seen["validation"]))
    line = f"slides seen: {n} ({len(seen['fitted'])} trained on, {len(seen['validation'])} validated on)"
    assert line in capsys.readouterr().out
    assert cli.main(["published", "c16-v2-head"]) == 0
    assert "slides seen: 180 (180 fitted on, 35 validated on)" in capsys.readouterr().out


def test_an_unknown_published_name_is_one_line(capsys):
    assert cli.main(["published", "c16-v9-nothing"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: no published agent or head is named 'c16-v9-nothing'") and "\n" not in err
    assert "c16-v2-set-reader" in err


def test_a_published_name_is_the_packaged_folder_from_any_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    packaged = "baselines/published/c16-v2-set-reader"
    for given in ("c16-v2-set-reader", packaged, packaged + "/"):
        assert published_or_path(given) == str(PUBLISHED / "c16-v2-set-reader"), given
    assert published_or_path("c16-v2-head") == str(PUBLISHED / "c16-v2-head")
    for given in (
        "runs/c16-v2-set-reader",
        "./c16-v2-set-reader",
        "c16-v9-nothing",
        "runs/ppo-fold{fold}",
        "",
        "baselines/published/",
        "c16-v1-glimpse-reader",
    ):  # a path, or no published name: as given
        assert published_or_path(given) == given
    (tmp_path / "c16-v2-set-reader").mkdir()  # a folder of that name here is not taken for the published agent
    (tmp_path / "c16-v2-set-reader" / "config.json").write_text("{}")
    assert published_or_path("c16-v2-set-reader") == str(PUBLISHED / "c16-v2-set-reader")
    assert published_or_path("./c16-v2-set-reader") == "./c16-v2-set-reader"  # named by its path: that one


def test_evaluate_by_name_reaches_the_published_agent_from_any_folder(tmp_path, monkeypatch, capsys):
    """From an empty folder, ``histojax evaluate c16-v2-set-reader`` loads the packaged agent: without --dataset it
    stops at the published agent's own refusal, naming its packaged config.json (no dataset is built here)."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(["evaluate", "c16-v2-set-reader"]) == 2
    err = capsys.readouterr().err
    assert f"{PUBLISHED / 'c16-v2-set-reader' / 'config.json'}: a published agent" in err and "--dataset" in err
    assert cli.main(["evaluate", "c16-v2-head"]) == 2  # a head by name: found, and refused as not an agent
    assert "a slide head, not an agent" in capsys.readouterr().err
    from baselines.evaluate.cli import add_arguments
    from data_tools.cli_output import build_parser

    args = build_parser(add_arguments, "histojax evaluate").parse_args(["c16-v2-set-reader", "--head", "c16-v2-head"])
    assert (args.checkpoint, args.head) == (str(PUBLISHED / "c16-v2-set-reader"), str(PUBLISHED / "c16-v2-head"))


def test_a_folder_named_like_a_command_package_in_the_working_folder_is_refused(tmp_path):
    """``python -m histojax.cli`` from a folder holding its own ``baselines`` package: one line naming that folder,
    instead of importing it as histojax's."""
    package = "baselines"
    (tmp_path / package).mkdir()
    (tmp_path / package / "__init__.py").write_text("raise SystemExit('the user folder was imported')\n")
    out = subprocess.run(
        [sys.executable, "-m", "histojax.cli", "published"], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip() == (
        f"error: {tmp_path.resolve() / package}: a folder named {package} in the import path "
        f"ahead of histojax's own ({ROOT / package}); python -m puts the working folder "
        "first: run the histojax command, or from another folder"
    )


def test_bench_outside_a_source_checkout_says_where_it_runs(monkeypatch, tmp_path):
    """An installed wheel has no benchmarks/ (and no checkout beside histojax): ``histojax bench`` says so in one
    line; in a checkout it is found beside histojax, never in the working folder."""
    monkeypatch.setattr(cli, "HOME", tmp_path)
    monkeypatch.setattr(cli, "package_home", lambda name: None)
    assert cli.own_package_refusal("benchmarks").startswith("histojax bench runs from a source checkout")
    monkeypatch.undo()
    assert cli.own_package_refusal("benchmarks") is None and cli.own_package_refusal("baselines") is None


def test_an_own_encoder_from_the_working_folder_goes_last_on_the_import_path(tmp_path, monkeypatch):
    """``--encoder my_encoders:fn`` found only in the working folder puts that folder on ``sys.path`` (worker
    processes import it too), last: a folder there named like histojax's own packages is not imported in their
    place afterwards."""
    import os

    from data_tools.features.custom import load_custom_encoder

    (tmp_path / "wf_encoders.py").write_text(
        "import numpy as np\n\n\ndef enc(images):\n    return np.zeros((len(images), 4), np.float32)\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", os.getcwd(), str(tmp_path))])
    load_custom_encoder.cache_clear()
    try:
        assert load_custom_encoder("wf_encoders:enc").dim == 4
        assert sys.path[-1] == str(tmp_path) and sys.path.count(str(tmp_path)) == 1
    finally:
        load_custom_encoder.cache_clear()
        sys.modules.pop("wf_encoders", None)
