"""``make``'s options are one typed set (histojax.make_options.MakeOptions): each field says where it goes, and
the name lists the registry used to keep by hand are derived from it."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

import histojax
from histojax.core.env import EnvParams, HistoEnv
from histojax.core.modes import base
from histojax.make_options import DATASET, KINDS, MODE, PARAMS, STATIC, UNSET, MakeOptions
from histojax.reading.modes import glimpse, zoom_select
from histojax.registry import DATASET_FIELDS, MODE_SETTINGS, PARAM_FIELDS, STATIC_FIELDS, EnvSpec


def test_every_option_has_one_kind_and_the_kinds_cover_the_env():
    kinds = {f.name: f.metadata["kind"] for f in dataclasses.fields(MakeOptions)}
    assert set(kinds.values()) == set(KINDS)
    # params: exactly the EnvParams fields a user sets (the slide and the mode's tables are make's own)
    assert set(MakeOptions.names(PARAMS)) == {f.name for f in dataclasses.fields(EnvParams)} - {"slide", "mode_data"}
    # static: exactly HistoEnv's trace-time settings (its name is the id)
    assert set(MakeOptions.names(STATIC)) == {f.name for f in dataclasses.fields(HistoEnv) if f.compare} - {"name"}
    # mode: every keyword an action mode's prepare takes
    prepare_kw = {
        p
        for cls in (*vars(base).values(), *vars(glimpse).values(), *vars(zoom_select).values())
        if inspect.isclass(cls) and "prepare" in vars(cls)
        for p in list(inspect.signature(cls.prepare).parameters)[4:]
        if p != "settings"
    }
    assert prepare_kw and prepare_kw <= set(MakeOptions.names(MODE))
    assert (STATIC_FIELDS, PARAM_FIELDS, MODE_SETTINGS, DATASET_FIELDS) == tuple(MakeOptions.names(k) for k in KINDS)


def test_given_and_over():
    base_opts = MakeOptions(n_levels=3, max_steps_in_episode=100)
    given = MakeOptions.of({"max_steps_in_episode": 7, "read_budget": 0.5, "tumour_slides_only": True})
    merged = given.over(base_opts)
    assert merged.given() == {"n_levels": 3, "max_steps_in_episode": 7, "read_budget": 0.5, "tumour_slides_only": True}
    assert merged.given(MODE) == {"read_budget": 0.5} and merged.given(DATASET) == {"tumour_slides_only": True}
    assert merged.given(STATIC, PARAMS) == {"n_levels": 3, "max_steps_in_episode": 7}
    assert merged.reward is UNSET and repr(UNSET) == "UNSET"
    with pytest.raises(dataclasses.FrozenInstanceError):
        merged.n_levels = 5


def test_an_unknown_setting_is_refused_naming_it():
    with pytest.raises(
        TypeError,
        match=r"make\('HistoJAX-Easy-v0'\) got unknown settings \['bogus'\]; static: .*"
        r"'action_mode'.*; params: .*'max_steps_in_episode'",
    ):
        histojax.make("HistoJAX-Easy-v0", bogus=1)
    with pytest.raises(TypeError, match=r"unknown scenario settings \['read_budget'\]"):
        EnvSpec(id="X", settings={"n_levels": 3, "read_budget": 0.5})  # a mode setting is make's, per call
    assert EnvSpec(id="X", settings={"n_levels": 3, "max_steps_in_episode": 9}).options.given() == {
        "n_levels": 3,
        "max_steps_in_episode": 9,
    }


def test_make_sends_each_option_where_it_goes():
    env, params = histojax.make(
        "HistoJAX-Easy-v0", max_steps_in_episode=7, action_mode="zoom_select", read_budget=0.5, step_cost=0.02
    )
    assert env.n_levels == 3 and env.action_mode == "zoom_select"  # the id's static setting, and one given
    assert int(params.max_steps_in_episode) == 7 and float(params.step_cost) == pytest.approx(0.02)
    assert params.mode_data is not None  # read_budget went to the mode's prepare
