"""The package's contract check (histojax.testing) on registered ids and every action/observation mode.

Default run: two ids (3 levels on the whole sample slide; 7 levels on a region bundle) and the modes
combined into two configurations; every other registered id (the C16 ids on the small C16 dataset)
under ``make test-all``. The feature observation mode is checked in tests/data_pipeline/test_features.py (it needs
a feature grid). Each configuration compiles once, with small budgets.
"""

from __future__ import annotations

import jax.numpy as jnp
import pytest

import histojax
from histojax.core.env import HistoEnv
from histojax.testing import check_contract, check_env

SMALL = dict(batch=4, steps=8, jit_steps=2)
# every other registered id (the region scenario's included) under `make test-all`: test_contract_of_every_other_...
DEFAULT_IDS = ("HistoJAX-Easy-v0",)


@pytest.mark.parametrize("env_id", DEFAULT_IDS)
def test_contract_of_registered_id(env_id):
    (report,) = check_contract([env_id], **SMALL)
    assert report.skipped is None and report.ok, report.failures
    assert len(report.checks) >= 12


@pytest.mark.parametrize(
    "overrides",
    [  # the continuous one under make test-all (make test under 10 min)
        pytest.param(
            dict(action_mode="continuous", obs_mode="pixels_float", with_position=True), marks=pytest.mark.slow
        ),
        dict(task="classification", with_position=True),
    ],
    ids=["continuous-float-position", "classification-position"],
)
def test_contract_of_each_mode(overrides):
    env, params = histojax.make("HistoJAX-Easy-v0", **overrides)
    report = check_env(env, params, **SMALL)
    assert report.ok, report.failures


class _NanReward(HistoEnv):
    """An env that breaks the contract: every reward is NaN."""

    def step(self, key, state, action, params=None):
        obs, state, reward, terminated, truncated, info = super().step(key, state, action, params)
        return obs, state, reward * jnp.nan, terminated, truncated, info


def test_contract_catches_a_broken_env():
    import dataclasses

    env, params = histojax.make("HistoJAX-Easy-v0")
    broken = _NanReward(**{f.name: getattr(env, f.name) for f in dataclasses.fields(env)})
    report = check_env(broken, params, **SMALL)
    assert not report.ok
    failed = " ".join(report.failures)
    assert "finite rewards" in failed and "jit == no-jit" in failed


def test_contract_skips_an_id_without_its_data(monkeypatch, tmp_path):
    monkeypatch.setenv("HISTOJAX_C16_DATASET", str(tmp_path / "none"))
    (report,) = check_contract(["HistoJAX-C16-Easy-v0"], **SMALL)
    assert report.skipped and "dataset.json" in report.skipped and not report.checks


def _c16_contract_dataset(tmp_path_factory):
    """The small C16 dataset with the data every C16 id observes: pixels (v0) and the pcam-cnn feature grids
    the v1 / v2 ids and the reading id observe (``histojax c16 --small --features``), built once per session."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path_factory.getbasetemp() / "c16-contract-features"
    if not (out / "dataset.json").is_file():
        make_c16_dataset(out, small=True, features=True, progress=False)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("env_id", [i for i in histojax.registered_envs() if i not in DEFAULT_IDS])
def test_contract_of_every_other_registered_id(env_id, tmp_path_factory, monkeypatch):
    from histojax.registry import READING_ID

    if env_id.startswith("HistoJAX-C16-") or env_id == READING_ID:
        out = _c16_contract_dataset(tmp_path_factory)
        monkeypatch.setenv("HISTOJAX_C16_DATASET", str(out))
    if env_id == READING_ID:  # it reads a dataset of the caller's (no default slides): the small C16 set
        report = check_env(*histojax.make(env_id, dataset=str(out)), **SMALL)
    else:
        (report,) = check_contract([env_id], **SMALL)
    assert report.skipped is None and report.ok, report.skipped or report.failures
