"""A published head named by its package name (``baselines/published/NAME``, as the published agents record theirs)
resolves to the installed package's copy, never to a folder of that name under the working folder; a working-folder
copy is used only when named by an explicit path."""

from __future__ import annotations

from pathlib import Path

from baselines.evaluate.checks import resolve_head
from baselines.published_agents import PUBLISHED

NAME = "c16-v2-learned-head"


def _decoy(root: Path) -> Path:
    decoy = root / "baselines" / "published" / NAME
    decoy.mkdir(parents=True)
    (decoy / "config.json").write_text('{"kind": "learned-attention-mil", "note": "a decoy"}')
    return decoy


def test_the_package_name_of_a_published_head_is_the_installed_copy(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _decoy(tmp_path)
    (tmp_path / "run").mkdir()
    got = resolve_head(f"baselines/published/{NAME}", tmp_path / "run", tmp_path / "run" / "head_reward.json")
    assert got.resolve() == (PUBLISHED / NAME).resolve()


def test_a_working_folder_copy_is_used_when_named_by_an_explicit_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    decoy = _decoy(tmp_path)
    (tmp_path / "run").mkdir()
    where = tmp_path / "run" / "head_reward.json"
    assert resolve_head(f"./baselines/published/{NAME}", tmp_path / "run", where).resolve() == decoy.resolve()
    assert resolve_head(str(decoy), tmp_path / "run", where) == decoy
