"""`histojax evaluate`: pictures of the episode's own slide, the start at the start, reading maps, the printed
table, warnings (unknown config keys, slides that cannot be scored, training split / scale) and one-line
errors (exit 2) for bad checkpoints and options; `make` refusing bundles that cannot make one dataset."""

from __future__ import annotations

import json
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from baselines.common.env import make_env
from baselines.episodes import rollout
from baselines.evaluate import checks, cli, pictures
from baselines.harness.logs import save_checkpoint
from histojax.cli import main as histojax_main
from histojax.core import actions
from histojax.render import _canvas, render_trajectory, slide_name, trajectory_figure

EASY = {
    "env_id": "HistoJAX-Easy-v0",
    "action_mode": "discrete",
    "obs_mode": "pixels",
    "with_position": False,
    "hidden": 16,
}


@pytest.fixture(scope="module")
def two_slides(tmp_path_factory):
    """Two small semi-synthetic bundles (320 × 256 px, tile 32, Easy levels) that look different."""
    from data_tools.datasets.synth.dataset import make_dataset

    root = tmp_path_factory.mktemp("two-slides")
    ds = make_dataset(
        root, n_slides=2, size=(320, 256), seed=3, tile_size=32, level_sets=(3,), progress=False, previews=False
    )
    return [str(root / s["bundle"]) for s in ds["slides"]]


@pytest.fixture(scope="module")
def two_slide_env(two_slides):
    return rollout.eval_env({**EASY, "env_kwargs": {"slides": two_slides}})[1]


def test_trajectories_start_with_the_view_at_reset():
    """Entry 0 of a recorded trajectory is the view at reset (Easy starts at the coarsest level, 0), not the
    episode's last view (before: the final state was recorded where the first belongs)."""
    _, (env, params) = rollout.eval_env(EASY)
    zoom = lambda k, obs: jnp.full(jax.tree.leaves(obs)[0].shape[0], actions.ZOOM_IN, jnp.int32)  # noqa: E731
    ep = rollout.run_episodes(env, params, zoom, jax.random.PRNGKey(0), 4)
    assert (ep["z"][0] == 0).all()
    assert (ep["z"][1] == 1).all() and (ep["z"][-1] == env.n_levels - 1).all()


def test_pictures_of_a_two_slide_evaluation_show_the_episodes_slide(two_slide_env, tmp_path):
    """Every episode on slide 1: the trajectory picture, reading map and GIF are of slide 1 (before: slide 0)."""
    env, params = two_slide_env
    slides = np.ones(4, int)
    per, axes = rollout.per_episode_params(params, slides)
    rand = lambda k, obs: jax.random.randint(k, (jax.tree.leaves(obs)[0].shape[0],), 0, 7)  # noqa: E731
    ep = rollout.run_episodes(env, per, rand, jax.random.PRNGKey(1), 4, params_axes=axes)
    assert (ep["slide"] == 1).all()
    written = pictures.write_pictures(env, params, {"random": ep}, tmp_path, "HistoJAX-Easy-v0")
    assert {p.name for p in written} == {"trajectory_random.png", "reading_random_tumour.png", "trajectory.gif"}
    i = pictures._shown_episode(ep)
    z, x, y = rollout.trajectory(ep, i)
    picked = pictures.picked_words(ep, i)  # how it was picked among the 4 episodes, in the title
    assert picked.endswith("among 4 episodes") if ep["success"][i] else picked.startswith("none of 4 episodes")
    title = (
        f"HistoJAX-Easy-v0, random, {len(z) - 1} steps, {'success' if ep['success'][i] else 'no success'} ({picked})"
    )
    on = [render_trajectory(env, z, x, y, slide_index=s, title=title) for s in (0, 1)]
    with Image.open(tmp_path / "trajectory_random.png") as im:
        drawn = np.asarray(im.convert("RGB"))
    assert drawn.shape == on[1].shape and np.array_equal(drawn, on[1])
    assert drawn.shape != on[0].shape or not np.array_equal(drawn, on[0])
    fig = trajectory_figure(env, z, x, y, title=title, slide_index=1)
    ax = fig.axes[0]
    assert ax.get_title().endswith(f"slide {slide_name(env, 1)}") and slide_name(env, 0) != slide_name(env, 1)
    background = ax.images[0].get_array()
    assert np.array_equal(np.asarray(background), np.asarray(_canvas(env, 640, 1)[0]))
    assert not np.array_equal(np.asarray(background), np.asarray(_canvas(env, 640, 0)[0]))
    with Image.open(tmp_path / "trajectory.gif") as im:  # (Pillow merges repeated frames: a stay is one frame)
        assert 2 <= im.n_frames <= len(z)


def test_reading_map_draws_each_view_once_by_first_visit(two_slide_env, tmp_path):
    from histojax.render import reading_map_figure, reading_order, render_reading_map

    env, params = two_slide_env
    record = {
        "z": np.array([0, 1, 2, 2, 1, 2, 9]),
        "x": np.array([0, 10, 30, 62, 10, 30, 9]),
        "y": np.array([0, 10, 30, 30, 10, 30, 9]),
        "length": 5,
    }  # entries past length + 1 are not steps
    views = reading_order(*[record[k][:6] for k in "zxy"])
    assert [(v, first, n) for v, first, n in views] == [
        ((0, 0, 0), 0, 1),
        ((1, 10, 10), 1, 2),
        ((2, 30, 30), 2, 2),
        ((2, 62, 30), 3, 1),
    ]
    fig = reading_map_figure(env, params, record, slide_index=1, score=0.25, title="scripted")
    ax = fig.axes[0]
    boxes = [p for p in ax.patches if type(p).__name__ == "Rectangle"]
    assert len(boxes) == 4
    assert ax.collections[-1].get_array().tolist() == [0, 1, 2, 3]  # the dots, coloured by first visit
    title = ax.get_title()
    assert "scripted" in title and "tumour slide" in title and "tumour score 0.250" in title
    assert title.endswith(f"slide {slide_name(env, 1)}")
    picture = render_reading_map(env, params, record, slide_index=1, score="target reached", path=tmp_path / "r.png")
    with Image.open(tmp_path / "r.png") as im:
        assert im.size == (picture.shape[1], picture.shape[0]) and 500 <= im.size[0] <= 1200


def test_gif_of_a_feature_only_slide_shows_a_feature_heat_map(two_slides, colour_feature_grid, tmp_path):
    """Levels without pixels: the view panel is the features as a heat map (before: plain grey)."""
    import dataclasses

    from histojax.render import animate, feature_heatmap

    bundle = colour_feature_grid(two_slides[0], tmp_path / "b")
    _, (env, params) = rollout.eval_env({**EASY, "obs_mode": "features", "slide": str(bundle)})
    heat = feature_heatmap(env, params, 0, env.n_levels - 1)
    assert heat is not None and "no tumour logit" in heat[2] and np.isfinite(heat[0]).all()

    class NoPixels:  # a level whose pixels were dropped (a feature-only bundle keeps the coarsest only)
        has_pixels = False

        def __init__(self, level):
            self.shape = level.shape

    host = env.bundles[0]
    dropped = dataclasses.replace(host, pixels=[host.pixels[0], *map(NoPixels, host.pixels[1:])])
    env = dataclasses.replace(env, _bundle=dropped, _bundles=(dropped,))
    z, x, y = [0, 1, 2], [0, 32, 96], [0, 32, 96]
    with Image.open(animate(env, z, x, y, tmp_path / "t.gif", params=params)) as im:
        im.seek(2)
        frame = np.asarray(im.convert("RGB"))
    panel = frame[:, frame.shape[1] - frame.shape[0] :]
    assert len(np.unique(panel.reshape(-1, 3), axis=0)) > 8  # a heat map and its caption, not one grey


def test_print_table_shows_auc_and_fraction_read(capsys):
    row = {
        "episodes": 8,
        "success_rate": 0.461,
        "mean_return": 0.1,
        "mean_length": 2.0,
        "mean_steps_to_success": 2.0,
        "mean_fraction_read": 0.1,
        "mean_fields_of_view": 1.0,
    }
    cli.print_table(
        "t",
        {
            "ppo (greedy)": {**row, "diagnosis_auc": 1.0, "diagnosis_auc_low": 0.585, "diagnosis_auc_high": 1.0},
            "random": row,
        },
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].split()[-6:] == ["read", "fields", "AUC", "[95", "%", "interval]"]
    assert lines[3].split()[-5:] == ["10.0%", "1.0", "1.000", "[0.585,", "1.000]"] and lines[4].split()[-1] == "-"


def test_split_warnings_say_why_a_split_cannot_be_scored():
    params = lambda labels: types.SimpleNamespace(slide=types.SimpleNamespace(slide_label=np.array(labels)))  # noqa: E731
    assert "AUC is undefined" in checks.split_warnings(None, params([1, 1]), "classification", "s")[0]
    assert "success rate is undefined: one class" in checks.split_warnings(None, params([0, 0]), "detection", "s")[0]
    assert checks.split_warnings(None, params([0, 1]), "classification", "s") == []
    assert checks.split_warnings(None, params([0, 1]), "detection", "s") == []


def test_provenance_warnings_training_split_and_scale(tmp_path):
    def dataset(name, mpp):
        d = tmp_path / name
        d.mkdir()
        (d / "dataset.json").write_text(
            json.dumps(
                {
                    "kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
                    "scale": {"mpp": mpp},
                    "variant": "small",
                    "train": [],
                    "test": [],
                }
            )
        )
        return str(d)

    full, small = dataset("full", 1.944), dataset("small", 7.776)
    trained = {"env_id": "HistoJAX-C16-Diagnosis-v1", "env_kwargs": {"dataset": full, "split": "train"}}
    scored = lambda ds, split: {"env_kwargs": {"dataset": ds, "split": split}}  # noqa: E731
    assert checks.provenance_warnings(trained, scored(full, "test"), "c.json") == []
    (same,) = checks.provenance_warnings(trained, scored(full, "all"), "c.json")
    assert "not held-out" in same and "the same dataset" in same
    both = checks.provenance_warnings(trained, scored(small, "train"), "c.json")
    assert len(both) == 2 and "split is fixed by slide" in both[0] and "another scale" in both[1]
    gone = {**trained, "env_kwargs": {"dataset": str(tmp_path / "gone"), "split": "train"}}
    (unknown,) = checks.provenance_warnings(gone, scored(small, "test"), "c.json")
    assert "scale cannot be checked" in unknown and "7.78" in unknown


def test_default_output_folder_is_never_inside_the_package(tmp_path):
    published = Path(cli.__file__).parents[1] / "published" / "c16-v1-diagnosis"
    assert cli.default_out(published, "X") == Path("runs/eval-c16-v1-diagnosis")
    assert cli.default_out(tmp_path, "X") == tmp_path / "eval"
    assert cli.default_out(None, "HistoJAX-Easy-v0") == Path("runs/eval-HistoJAX-Easy-v0")


# ----------------------------------------------------------------------------- the command, end to end
def _checkpoint(folder: Path, config: dict, hidden: int | None = None) -> Path:
    """A run folder like a trainer's: untrained parameters of ``config``'s network (one seed) and its config."""
    from baselines.networks import preprocess_obs
    from baselines.ppo import make_network

    env, env_params = make_env(config)
    network = make_network({**config, "hidden": hidden or config["hidden"]}, env)
    obs, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 2), env_params)
    params = network.init(jax.random.PRNGKey(0), preprocess_obs(obs))
    save_checkpoint(folder, jax.tree.map(lambda a: a[None], params), config)
    return folder


def _one_error_line(capsys) -> str:
    """The one ``error: ...`` line on stderr (progress lines aside), with no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.slow  # compiles four policies' rollouts: about a minute on 2 CPU cores
def test_evaluate_command_table_warnings_and_pictures(tmp_path, capsys):
    """A diagnosis checkpoint on the sample slide (one tumour slide: no AUC) with a misspelt config key."""
    run = _checkpoint(tmp_path / "run", {**EASY, "hiden": 8, "env_kwargs": {"task": "classification"}})
    assert histojax_main(["evaluate", str(run), "--episodes", "2"]) == 0
    captured = capsys.readouterr()
    assert "warning: " in captured.err and "unknown key 'hiden'" in captured.err and "'hidden'" in captured.err
    assert "AUC is undefined" in captured.err
    assert "evaluating HistoJAX-Easy-v0 on embedded sample slide" in captured.err and "ppo (greedy): 2" in captured.err
    header, greedy = [line.split() for line in captured.out.splitlines() if line.startswith(("policy", "ppo (gr"))]
    assert (
        header[-6:] == ["read", "fields", "AUC", "[95", "%", "interval]"] and greedy[-1] == "undef."
    )  # one class: no AUC, and it says why
    assert "undef.: undefined: one class" in captured.out
    names = {p.name for p in (run / "eval").iterdir()}
    assert {
        "eval.json",
        "eval.csv",
        "trajectory_ppo_greedy.png",
        "reading_ppo_greedy_tumour.png",
        "trajectory.gif",
    } <= names
    record = json.loads((run / "eval" / "eval.json").read_text(), parse_constant=lambda c: pytest.fail(c))  # no NaN
    assert any("hiden" in w for w in record["warnings"]) and any("AUC is undefined" in w for w in record["warnings"])
    assert all(
        r["diagnosis_auc"] is None for rows in record["results"].values() for r in rows.values() if "diagnosis_auc" in r
    )


@pytest.mark.parametrize("argv", [["--episodes", "0"], ["--episodes", "-3"]])
def test_no_episodes_is_a_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as e:  # argparse's usage error: exit status 2, before anything runs
        histojax_main(["evaluate", "--env", "HistoJAX-Easy-v0", *argv])
    assert e.value.code == 2
    assert f"--episodes: '{argv[1]}' must be >= 1" in _one_error_line(capsys)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_checkpoint_that_does_not_fit_its_config(tmp_path, capsys):
    run = _checkpoint(tmp_path / "run", EASY, hidden=8)  # params of width 8, config says 16
    assert histojax_main(["evaluate", str(run), "--episodes", "1", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert str(run / "params.msgpack") in line and "do not fit the network" in line and "hidden=16" in line
    assert not (tmp_path / "o").exists()


def test_foreign_msgpack_and_bad_configs(tmp_path, capsys):
    from flax import serialization

    run = tmp_path / "run"
    run.mkdir()
    (run / "params.msgpack").write_bytes(serialization.msgpack_serialize({"weights": [1, 2, 3]}))
    (run / "config.json").write_text(json.dumps(EASY))
    assert histojax_main(["evaluate", str(run), "--episodes", "1"]) == 2
    assert "not a histojax checkpoint" in _one_error_line(capsys)
    good = _checkpoint(tmp_path / "good", EASY)
    for config, words in (
        ({**EASY, "hidden": -5}, "hidden=-5"),
        ([EASY], "holds a JSON list"),
        ({**EASY, "hidden": "wide"}, "hidden='wide'"),
    ):
        (good / "config.json").write_text(json.dumps(config))
        assert histojax_main(["evaluate", str(good), "--episodes", "1"]) == 2
        line = _one_error_line(capsys)
        assert str(good / "config.json") in line and words in line
    assert not (good / "eval").exists()


# ----------------------------------------------------------------------------- make over unlike bundles
def test_make_refuses_bundles_of_two_encoders_naming_both(two_slides, colour_feature_grid, tmp_path):
    import histojax
    from data_tools.bundle_files.reading import read_metadata
    from data_tools.errors import BundleError
    from data_tools.features.store import update_metadata

    a = colour_feature_grid(two_slides[0], tmp_path / "a")
    b = colour_feature_grid(two_slides[1], tmp_path / "b")
    histojax.make("HistoJAX-Easy-v0", slides=[str(a), str(b)], obs_mode="features")  # one encoder: fine
    record = dict(read_metadata(b)["features"])
    update_metadata(b, {**record, "encoder": "another encoder, 6-d"}, [])
    with pytest.raises(BundleError) as e:
        histojax.make("HistoJAX-Easy-v0", slides=[str(a), str(b)], obs_mode="features")
    assert str(a) in str(e.value) and str(b) in str(e.value) and "'another encoder, 6-d'" in str(e.value)
    # imported grids record their file, not their encoder: one dataset's imported files load together ...
    update_metadata(a, {**record, "encoder": "imported:a.h5", "source": "imported"}, [])
    update_metadata(b, {**record, "encoder": "imported:b.h5", "source": "imported"}, [])
    histojax.make("HistoJAX-Easy-v0", slides=[str(a), str(b)], obs_mode="features")
    # ... but not beside a named encoder's grid of the same D
    update_metadata(a, record, [])
    with pytest.raises(BundleError, match="imported:b.h5"):
        histojax.make("HistoJAX-Easy-v0", slides=[str(a), str(b)], obs_mode="features")


def test_make_names_two_bundles_of_different_tile_sizes(two_slides, tmp_path):
    import histojax
    from data_tools.datasets.synth.dataset import make_dataset
    from data_tools.errors import BundleError

    ds = make_dataset(
        tmp_path, n_slides=1, size=(640, 512), seed=3, tile_size=64, level_sets=(3,), progress=False, previews=False
    )
    other = str(tmp_path / ds["slides"][0]["bundle"])
    with pytest.raises(BundleError) as e:
        histojax.make("HistoJAX-Easy-v0", slides=[two_slides[0], other])
    assert other in str(e.value) and two_slides[0] in str(e.value) and "tile size 64" in str(e.value)


def test_glimpse_policy_on_a_slide_wider_than_its_grid_is_one_line(two_slides, colour_feature_grid, tmp_path, capsys):
    """`python -m baselines.evaluate` (before: a ValueError traceback) says it in one line naming the bundle."""
    bundle = colour_feature_grid(two_slides[0], tmp_path / "b")
    run = tmp_path / "run"
    config = {
        **EASY,
        "action_mode": "glimpse:1",
        "obs_mode": "features",
        "algo": "ppo",
        "env_kwargs": {"task": "classification", "slides": [str(bundle)], "glimpse_grid": [1, 1]},
    }
    save_checkpoint(run, {"params": {"w": np.zeros((1, 2), np.float32)}}, config)
    assert cli.main([str(run), "--episodes", "1", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert str(bundle) in line and "do not fit glimpse_grid=[1, 1]" in line
    assert not (tmp_path / "o").exists()


def test_pixels_of_a_feature_only_dataset_bundle_point_to_histojax_dataset(two_slides, tmp_path):
    """A `histojax dataset ... --no-pixels` bundle asked for pixels: the hint names `histojax dataset` (before:
    `data_tools c16 ... --slides`, a command that cannot remake a user's own slides)."""
    import histojax
    from data_tools.bundle import build_bundle, drop_pixels
    from data_tools.datasets.build import KIND
    from data_tools.errors import BundleError
    from data_tools.features.grid import compute_features

    slide = next((Path(two_slides[0]).parents[1] / "slides").glob("*.tif"))
    bundle = build_bundle(
        slide, tmp_path / "ds" / "bundles" / "s1", level_sets=(3,), tile_size=32, progress=False, storage="tiled"
    )
    compute_features(bundle, encoder_name="colour-stats", image_size=None, progress=False)
    drop_pixels(bundle)
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps({"kind": KIND, "train": ["bundles/s1"], "test": []}))
    with pytest.raises(BundleError) as e:
        histojax.make("HistoJAX-Easy-v0", slide=str(bundle))
    text = str(e.value)
    assert str(bundle) in text and "histojax dataset" in text and "data_tools c16" not in text
    histojax.make("HistoJAX-Easy-v0", slide=str(bundle), obs_mode="features")  # what it is for


def test_make_names_two_bundles_of_different_feature_dimensions(two_slides, colour_feature_grid, tmp_path):
    """Pixel observations still load the grids: 6-d and 8-d ones are refused naming both bundles (before: a
    ValueError naming neither)."""
    import shutil

    import histojax
    from data_tools.errors import BundleError
    from data_tools.features.grid import compute_features

    a = colour_feature_grid(two_slides[0], tmp_path / "a")
    b = tmp_path / "b"
    shutil.copytree(two_slides[1], b)
    compute_features(b, encoder_name="colour-stats", image_size=None, progress=False)
    with pytest.raises(BundleError) as e:
        histojax.make("HistoJAX-Easy-v0", slides=[str(a), str(b)])
    assert str(a) in str(e.value) and str(b) in str(e.value) and "6-d" in str(e.value) and "8-d" in str(e.value)


def test_held_out_without_a_training_dataset_is_exit_2(tmp_path, capsys):
    """Was: exit status 1. Now one error line and status 2, as every user error."""
    run = _checkpoint(tmp_path / "run", EASY)
    with pytest.raises(SystemExit, match="not trained on a dataset") as e:
        histojax_main(["evaluate", str(run), "--slides", "held-out"])
    assert e.value.code == 2
    assert "--slides held-out" in _one_error_line(capsys)
