"""Scenarios as data: TOML/JSON → Scenario → registered id → make → step; built-in region ids."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

import histojax
from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE
from histojax.scenarios import Scenario, ScenarioError, SlideSource, load_scenario, register_scenario

TOML = f'''
id = "Test-Sample-Target-Medium-v0"
levels = 5
tile_size = 128
reward = "histogym"
max_steps_in_episode = 40
with_position = true

[[slides]]
slide = "{SAMPLE_SLIDE}"
annotations = "{SAMPLE_ANNOTATIONS}"

[label_map]
"_0" = "tumour"
"_1" = "tumour"
"_2" = "exclusion"

[region]
group = "tumour"
margin = 200

[params]
stride = 0.5
'''


def _step_some(env, params, n=3):
    key = jax.random.PRNGKey(0)
    obs, state = env.reset(key, params)
    for a in range(n):
        obs, state, reward, terminated, truncated, info = env.step(jax.random.PRNGKey(a), state, 4, params)
    return obs, state, reward


def test_toml_register_make_step(tmp_path):
    path = tmp_path / "scenario.toml"
    path.write_text(TOML)
    scenario = histojax.register_scenario(path)
    assert scenario.source == str(path) and scenario.slides[0].annotations == str(SAMPLE_ANNOTATIONS)
    assert scenario.id in histojax.registered_envs()
    env, params = histojax.make(scenario.id)
    assert env.n_levels == 5 and env.reward == "histogym" and env.with_position
    assert int(params.max_steps_in_episode) == 40 and float(params.stride) == 0.5
    meta = env.bundles[0].metadata
    assert meta["region"]["kind"] == "group" and meta["label_map"]["_2"] == "exclusion"
    obs, state, reward = _step_some(env, params)
    assert obs["pixels"].shape == (128, 128, 3) and int(state.z) == 3 and np.isfinite(float(reward))
    # made again: the cached bundle is reused, not rebuilt
    env2, _ = histojax.make(scenario.id)
    assert env2.bundles[0].path == env.bundles[0].path


def test_json_with_bundle_path_and_relative_paths(tmp_path):
    from histojax.sample import sample_bundle

    bundle = sample_bundle(progress=False)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "s.json").write_text(
        json.dumps(
            {
                "id": "Test-Json-Easy-v0",
                "slides": [str(bundle)],
                "levels": 3,
                "obs_mode": "pixels_float",
                "train": [bundle.name],
            }
        )
    )
    scenario = load_scenario(tmp_path / "sub" / "s.json")
    assert scenario.slides == (SlideSource(bundle=str(bundle)),)
    register_scenario(scenario)
    env, params = histojax.make("Test-Json-Easy-v0")
    assert int(params.max_steps_in_episode) == 100  # the Easy default
    obs, _, _ = _step_some(env, params, 1)
    assert obs.dtype == np.float32
    # a relative slide path is taken from the scenario file's folder
    (tmp_path / "sub" / "rel.toml").write_text('id = "X-v0"\nslides = [{slide = "slide.svs", annotations = "a.xml"}]\n')
    rel = load_scenario(tmp_path / "sub" / "rel.toml")
    assert rel.slides[0].slide == str(tmp_path / "sub" / "slide.svs")


@pytest.mark.parametrize("env_id, levels", [("HistoJAX-Easy-Region-v0", 3), ("HistoJAX-Hard-Region-v0", 7)])
def test_builtin_region_ids(env_id, levels):
    env, params = histojax.make(env_id)
    assert env.n_levels == levels
    region = env.bundles[0].metadata["region"]
    assert region["kind"] == "group" and region["group"] == "tumour" and region["margin"] == 300
    x0, y0, x1, y1 = region["box"]
    assert int(params.slide.level_width[-1]) == x1 - x0 and int(params.slide.level_height[-1]) == y1 - y0
    obs, state, reward = _step_some(env, params)
    assert obs.shape == (128, 128, 3) and np.isfinite(float(reward))
    assert "HistoJAX-Medium-Region-v0" in histojax.registered_envs()


@pytest.mark.parametrize(
    "text, match",
    [
        ('id = "A-v0"\nlevels = [3\n', "invalid TOML"),
        ("levels = 3\n", "needs an 'id'"),
        ('id = "A-v0"\nlevel = 3\n', "unknown scenario key"),
        ('id = "A-v0"\nreward = "shiny"\n', "reward"),
        ('id = "A-v0"\nlevels = 1\n', "levels"),
        ('id = "A-v0"\n[region]\nbox = [1, 2, 3]\n', "region box"),
        ('id = "A-v0"\n[region]\nbox = [0, 0, 9, 9]\ngroup = "t"\n', "exactly one"),
        ('id = "A-v0"\n[label_map]\n"_0" = "cancer"\n', "label_map"),
        ('id = "A-v0"\n[params]\nspeed = 2\n', "params"),
    ],
)
def test_bad_toml_names_the_file(tmp_path, text, match):
    path = tmp_path / "bad_scenario.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError, match=match) as e:
        register_scenario(path)
    assert str(path) in str(e.value) and isinstance(e.value, ValueError)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_multi_slide_scenario_with_a_split(tmp_path):
    import tifffile

    rng = np.random.default_rng(0)
    blank = tmp_path / "blank.tif"
    tifffile.imwrite(blank, rng.integers(200, 255, (700, 900, 3), dtype=np.uint8), photometric="rgb")
    path = tmp_path / "two.toml"
    path.write_text(f'''
id = "Test-Two-Slides-v0"
levels = 3
train = ["CMU-1-Small-Region.svs"]
test = ["blank.tif"]

[[slides]]
slide = "{SAMPLE_SLIDE}"
annotations = "{SAMPLE_ANNOTATIONS}"

[[slides]]
slide = "{blank}"
''')
    register_scenario(path)
    env, params = histojax.make("Test-Two-Slides-v0", split="all")
    assert params.slide.num_slides == 2 and len(env.bundles) == 2
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 64), params)
    assert set(np.asarray(states.slide_index).tolist()) == {0, 1}  # both slides are drawn
    train_env, train_params = histojax.make("Test-Two-Slides-v0")  # split="train" by default
    assert train_params.slide.num_slides == 1 and train_env.bundles[0].metadata["source"]["file"] == SAMPLE_SLIDE.name
    test_env, _ = histojax.make("Test-Two-Slides-v0", split="test")
    assert test_env.bundles[0].metadata["source"]["file"] == "blank.tif"


def test_missing_file_and_region_on_a_bundle(tmp_path):
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="needs the slide file"):
        register_scenario(
            Scenario(id="R-v0", slides=(SlideSource(bundle=str(tmp_path)),), region=load_scenario_region())
        )


def load_scenario_region():
    from histojax.scenarios import RegionRule

    return RegionRule(box=(0, 0, 500, 500))
