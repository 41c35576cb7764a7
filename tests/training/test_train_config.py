"""The trainers' typed configs (``PPOConfig``, ``DQNConfig``, ``PPORNNConfig``): every published agent's
``config.json`` loads and records back the same, an unknown entry or a wrong type is one line naming it, and
``make_train`` given a dict builds what it builds from the typed config."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from ppo_configs import TINY

from baselines import dqn, ppo, ppo_rnn
from baselines.common.config import ConfigError
from baselines.harness.runner import resume_config

PUBLISHED = Path(__file__).resolve().parents[2] / "baselines" / "published"
CLASSES = {"ppo": ppo.PPOConfig, "ppo_rnn": ppo_rnn.PPORNNConfig, "dqn": dqn.DQNConfig}
DEFAULTS = {"ppo": ppo.DEFAULTS, "ppo_rnn": ppo_rnn.DEFAULTS, "dqn": dqn.DEFAULTS}
TRAINER_CONFIGS = sorted(p for p in PUBLISHED.glob("*/config.json") if "algo" in json.loads(p.read_text()))


def test_the_published_agents_are_found():
    assert len(TRAINER_CONFIGS) >= 5  # c16-v1-*, c16-v2-head-navigator, c16-v2-set-reader (heads have no "algo")


@pytest.mark.parametrize("path", TRAINER_CONFIGS, ids=lambda p: p.parent.name)
def test_every_published_config_round_trips(path):
    """Each published trainer config loads, and its record is what the trainer wrote before the configs were
    typed: the trainer's defaults completed with the file's entries (every entry kept as it is)."""
    recorded = json.loads(path.read_text())
    config = CLASSES[recorded["algo"]].from_dict(recorded, where=str(path))
    assert config.as_dict() == {**DEFAULTS[recorded["algo"]], **recorded}
    assert type(config).from_dict(config.as_dict()) == config
    assert json.loads(json.dumps(config.as_dict())) == config.as_dict()  # JSON as it is


def test_defaults_and_record_order_are_those_of_before():
    """``DEFAULTS`` is the default config's record: the fields in order, no ``seed`` (recorded last, when set);
    recurrent PPO's lacks ``devices`` and ``minibatch_by`` (always whole env sequences) and has its own ``algo``,
    ``hidden`` and ``num_minibatches``."""
    assert list(ppo.DEFAULTS)[:3] == ["algo", "env_id", "slide"] and "seed" not in ppo.DEFAULTS
    assert list(ppo_rnn.DEFAULTS) == [k for k in ppo.DEFAULTS if k not in ("devices", "minibatch_by")]
    assert (ppo_rnn.DEFAULTS["algo"], ppo_rnn.DEFAULTS["hidden"], ppo_rnn.DEFAULTS["num_minibatches"]) == (
        "ppo_rnn",
        128,
        4,
    )
    record = ppo.PPOConfig(seed=3).as_dict()
    assert list(record)[-1] == "seed" and record["seed"] == 3
    assert ppo.PPOConfig.from_dict({"obs": "features"}).obs_mode == "features"  # the older spelling


def test_an_unknown_entry_is_refused_in_one_line_naming_it():
    with pytest.raises(
        ConfigError,
        match=r"^run/config\.json: unknown config entry 'lrr' for ppo "
        r"\(did you mean 'lr'\?\); known: ",
    ) as e:
        ppo.PPOConfig.from_dict({"lrr": 0.1}, where="run/config.json")
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match="unknown config entry 'num_steps' for dqn"):
        dqn.DQNConfig.from_dict({**ppo.DEFAULTS, "algo": "dqn"})
    with pytest.raises(ConfigError, match="unknown config entry 'bogus'"):
        ppo.make_train({**TINY, "bogus": 1})
    assert ppo.PPOConfig.from_dict({"bogus": 1}, strict=False) == ppo.PPOConfig()  # a record read leniently


@pytest.mark.parametrize(
    "entry, value, words",
    [
        ("lr", "fast", "lr='fast' must be a number, not a str"),
        ("num_envs", 4.0, "num_envs=4.0 must be a whole number, not a float"),
        ("anneal_lr", 1, "anneal_lr=1 must be true or false, not a int"),
        ("env_kwargs", [1], "env_kwargs=[1] must be an object or null, not a list"),
        ("devices", "2", "devices='2' must be a whole number or null, not a str"),
        ("slide", 3, "slide=3 must be a string or a path or null, not a int"),
    ],
)
def test_a_wrong_type_is_refused_in_one_line(entry, value, words):
    with pytest.raises(ConfigError) as e:
        ppo.PPOConfig.from_dict({entry: value}, where="the options (--set)")
    assert str(e.value) == f"the options (--set): {words}"


def test_a_stopped_runs_notes_load_and_are_not_kept():
    """``experiments.checkpoint_to_run`` notes in config.json where a stopped run stopped: such a folder loads."""
    config = ppo.PPOConfig.from_dict({**ppo.DEFAULTS, "stopped_at_update": 7, "checkpoint_train_seconds": 1.5})
    assert config == ppo.PPOConfig() and config.as_dict() == ppo.DEFAULTS


def test_a_number_where_a_float_goes_and_null_where_allowed_load():
    config = ppo.PPOConfig.from_dict(
        {"lr": 1, "ent_coef_final": None, "max_steps_in_episode": None, "devices": 2, "slide": Path("bundle")}
    )
    assert config.lr == 1 and config.devices == 2 and config.slide == Path("bundle")  # a slide folder as a Path


def test_resume_refuses_a_checkpoint_config_of_a_wrong_type_naming_the_file(tmp_path):
    (tmp_path / "checkpoint").mkdir()
    path = tmp_path / "checkpoint" / "config.json"
    path.write_text(json.dumps({**ppo.DEFAULTS, "num_envs": "many"}))
    with pytest.raises(HistojaxDataError, match=r"config\.json: num_envs='many' must be a whole number"):
        resume_config(tmp_path, "ppo", ppo.PPOConfig)
    path.write_text(json.dumps({**ppo.DEFAULTS, "seed": 2}))
    assert resume_config(tmp_path, "ppo", ppo.PPOConfig) == ppo.PPOConfig(seed=2)


def test_the_command_line_refuses_a_wrong_type_in_one_line(tmp_path, capsys):
    assert ppo.main(["--set", 'lr="fast"', "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: the options (--set): lr='fast' must be a number, not a str"
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "module, extra",
    [
        (ppo, {}),
        (ppo_rnn, {}),
        (dqn, {"buffer_size": 64, "batch_size": 8, "learning_starts": 16, "iterations_per_log": 4}),
    ],
)
def test_make_train_of_a_dict_equals_make_train_of_the_typed_config(module, extra):
    """``make_train`` converts a dict once at its top: the built config (typed and recorded), env and network
    are those of the typed config (no training run)."""
    entries = {k: v for k, v in {**TINY, **extra}.items() if k in module.DEFAULTS}
    cls = {ppo: ppo.PPOConfig, ppo_rnn: ppo_rnn.PPORNNConfig, dqn: dqn.DQNConfig}[module]
    from_dict, typed = module.make_train(dict(entries, seed=5)), module.make_train(cls(**entries, seed=5))
    assert isinstance(typed.train_config, cls) and from_dict.train_config == typed.train_config
    assert from_dict.config == typed.config == typed.train_config.as_dict()
    assert from_dict.config == {**module.DEFAULTS, **entries, "seed": 5}
    assert from_dict.network == typed.network and from_dict.num_updates == typed.num_updates
    assert type(from_dict.env) is type(typed.env)


def test_the_env_is_made_through_make_options():
    """A config's env settings become ``make``'s own arguments and the typed ``MakeOptions``; an ``env_kwargs``
    entry ``make`` has not is ``make``'s one line."""
    config = ppo.PPOConfig(
        action_mode="glimpse:1",
        obs_mode="features",
        reward="sparse",
        max_steps_in_episode=9,
        env_kwargs={"dataset": "DS", "split": "test", "read_budget": 0.25},
    )
    arguments, options = config.make_arguments(auto_reset=False)
    assert arguments == {"slide": None, "dataset": "DS", "split": "test"}
    assert options.given() == {
        "action_mode": "glimpse:1",
        "obs_mode": "features",
        "with_position": False,
        "reward": "sparse",
        "auto_reset": False,
        "max_steps_in_episode": 9,
        "read_budget": 0.25,
    }
    with pytest.raises(TypeError, match=r"make\('HistoJAX-Easy-v0'\) got unknown settings \['bogus'\]"):
        ppo.PPOConfig(env_kwargs={"bogus": 1}).make_arguments()


def test_configs_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        ppo.PPOConfig().lr = 1.0


# ----------------------------------------------------------------------------- a run's recorded config, read leniently
from baselines.run_config import read_run_config  # noqa: E402
from data_tools.errors import HistojaxDataError  # noqa: E402


@pytest.mark.parametrize("path", TRAINER_CONFIGS, ids=lambda p: p.parent.name)
def test_every_published_config_reads_as_its_trainers_config_without_a_word(path):
    warnings = []
    config = read_run_config(path, warnings=warnings)
    recorded = json.loads(path.read_text())
    assert type(config) is CLASSES[recorded["algo"]] and warnings == []
    assert config == CLASSES[recorded["algo"]].from_dict(recorded)
    assert read_run_config(path.parent) == config  # the run folder holding it reads the same
    assert read_run_config(config) is config


def test_a_record_without_algo_is_ppos_or_dqns_when_it_records_a_replay_buffer(tmp_path):
    ppo_record = {k: v for k, v in ppo.DEFAULTS.items() if k != "algo"}
    config = read_run_config(ppo_record)
    assert type(config) is ppo.PPOConfig and config.algo == "ppo"
    dqn_record = {k: v for k, v in dqn.DEFAULTS.items() if k != "algo"}
    config = read_run_config(dqn_record)
    assert type(config) is dqn.DQNConfig and config.algo == "dqn"
    assert type(read_run_config({"algo": "ppo_rnn", "hidden": 32})) is ppo_rnn.PPORNNConfig
    (tmp_path / "config.json").write_text(json.dumps({"env_id": "HistoJAX-Easy-v0", "obs": "features"}))
    config = read_run_config(tmp_path)  # an older run: no algo, obs spelled "obs"
    assert type(config) is ppo.PPOConfig and config.obs_mode == "features"


def test_an_unknown_key_is_a_warning_naming_the_file_not_a_refusal(tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**ppo.DEFAULTS, "hiden": 64, "zzz": "x"}))
    warnings = []
    config = read_run_config(path, warnings=warnings)
    assert config == ppo.PPOConfig()  # read, the unknown keys ignored
    assert warnings == [
        f"{path}: unknown key 'hiden' ignored (did you mean 'hidden'?)",
        f"{path}: unknown key 'zzz' ignored",
    ]
    # another trainer's entries are known (no warning) and ignored by this one
    warnings = []
    assert read_run_config({**ppo.DEFAULTS, "eps_end": 0.1}, "c.json", warnings) == ppo.PPOConfig()
    assert warnings == []


@pytest.mark.parametrize(
    "entry, value",
    [
        ("lr", "fast"),
        ("num_envs", 2.5),
        ("with_position", "yes"),
        ("hidden", 0),
        ("action_mode", 3),
        ("env_kwargs", [1]),
    ],
)
def test_a_wrong_type_is_one_line_naming_the_file(tmp_path, entry, value):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**ppo.DEFAULTS, entry: value}))
    with pytest.raises(HistojaxDataError) as e:
        read_run_config(path)
    text = str(e.value)
    assert "\n" not in text and text.startswith(f"{path}: ") and entry in text


def test_a_record_that_is_not_an_object_or_not_json_is_one_line_naming_the_file(tmp_path):
    path = tmp_path / "config.json"
    for text in ("[1, 2]", "{not json"):
        path.write_text(text)
        with pytest.raises(HistojaxDataError) as e:
            read_run_config(path)
        assert "\n" not in str(e.value) and str(e.value).startswith(f"{path}: ")
