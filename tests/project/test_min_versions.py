"""The floors pyproject.toml declares are the versions ``make test-min`` installs (requirements-min.txt),
so a declared floor is a tested one (``jax>=0.4.30`` was once declared but could not
even be installed with the other floors)."""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _pyproject() -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _floors(requirements: list[str]) -> dict[str, str]:
    """``{name: floor}`` of the ``name>=floor`` requirements (markers dropped)."""
    out = {}
    for req in requirements:
        req = req.split(";")[0].strip()
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9][0-9A-Za-z.]*)", req)
        if m:
            out[m.group(1).lower()] = m.group(2)
    return out


def _pins() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "requirements-min.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            pins[name.strip().lower()] = version.strip()
    return pins


def test_every_floor_is_pinned_and_every_pin_is_a_floor():
    project = _pyproject()
    floors = {**_floors(project["dependencies"]), **_floors(project["optional-dependencies"]["test"])}
    floors.pop("tomli", None)  # Python 3.10 only
    pins = _pins()
    assert {k: pins.get(k) for k in floors if pins.get(k) != floors[k]} == {}, "pyproject floor != requirements-min pin"
    assert set(pins) - set(floors) == {"jaxlib"}  # jax's own pin, named so pip cannot pick another jaxlib
    assert pins["jaxlib"] == pins["jax"]
    # the test extra's requirements all carry a floor (a bare name would not be tested at its lowest)
    assert all(">=" in r for r in project["optional-dependencies"]["test"])


def test_the_check_can_fail():
    assert _floors(["jax>=0.6.2", "six", "tomli>=1.1; python_version < '3.11'"]) == {"jax": "0.6.2", "tomli": "1.1"}


@pytest.mark.skipif(not Path(__import__("sys").prefix).name.endswith("-min"), reason="only inside make test-min's venv")
def test_running_on_the_floors():
    """Inside ``.venv-min``: the installed versions are the pinned floors."""
    for name, version in _pins().items():
        assert metadata.version(name) == version, name
