"""`histojax evaluate` on readers and every published folder, on a C16-style dataset whose slides are wider and
taller than any training slide: a cell-set reader trained with SASHA's reward is scored through the slide head
its ``head_reward.json`` names (the policy reads, the head declares; AUC over all slides and without ITC-only
slides, fraction read); every folder of ``baselines/published`` either runs there or is refused in one line that
says why and what to use instead; ``publish`` keeps a reader's head findable.

Slides made here (no third-party data): pyramidal TIFFs of a pink tissue block with a dark-purple square
lesion (2 µm/px: a 1.13 mm micrometastasis, a 0.11 mm ITC) or none, built as bundles with 16-px views and the
C16 ids' level sets, and a 64-d stand-in for pcam-cnn features (entry 62, the view logit, high on dark views).
Training slides 512 × 640 px (h × w); the scored slides 1024 × 2304 px: 8 × 18 glimpse cells at level 1 of
the 5-level ids, wider than the 16 × 14 grid of the flat c16-v1 glimpse reader.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines.common.env import make_env
from baselines.episodes import rollout
from baselines.evaluate import checks, heads
from baselines.harness.logs import save_checkpoint
from baselines.publish import publish
from baselines.published_agents import PUBLISHED
from histojax.cli import main as histojax_main
from histojax.reading.heads.logit import LogitHead

D, LOGIT, TILE, MPP = 64, 62, 16, 2.0
READER = {
    "algo": "ppo",
    "env_id": "HistoJAX-C16-Diagnosis-v2",
    "action_mode": "glimpse:1",
    "obs_mode": "features",
    "with_position": False,
    "hidden": 16,
    "cell_hidden": 8,
    "obs_norm": None,
    "num_seeds": 1,
}
HEAD = LogitHead(
    cal_a=jnp.float32(1.0),
    cal_b=jnp.float32(0.0),
    prior_logit=jnp.float32(-0.5),
    dim=LOGIT,
    k=3,
    top=1,
    encoder="pcam-cnn",
)


def _features(bundle) -> None:
    """A 64-d stand-in for pcam-cnn's grid at every level: RGB mean / std of each view and, at entry 62, a view
    logit that is high on dark (lesion) views."""
    from data_tools.bundle import load_bundle, read_metadata
    from data_tools.features.store import level_grids, save_array, update_metadata

    meta = read_metadata(bundle)
    pixels = load_bundle(bundle, verify=False).pixels
    written, levels = [], []
    for k, (gh, gw) in enumerate(level_grids(meta, TILE)):
        px = np.full((gh * TILE, gw * TILE, 3), 255.0, np.float32)
        src = np.asarray(pixels[k][: gh * TILE, : gw * TILE], np.float32)
        px[: src.shape[0], : src.shape[1]] = src
        views = px.reshape(gh, TILE, gw, TILE, 3) / 255.0
        grid = np.zeros((gh, gw, D), np.float32)
        grid[..., :3], grid[..., 3:6] = views.mean(axis=(1, 3)), views.std(axis=(1, 3))
        grid[..., LOGIT] = 12.0 * (0.55 - grid[..., :2].mean(-1))
        save_array(Path(bundle) / f"features_{k:02d}.npy", grid)
        written.append(f"features_{k:02d}.npy")
        levels.append({"file": f"features_{k:02d}.npy", "grid": [gh, gw]})
    update_metadata(
        bundle,
        {"encoder": "pcam-cnn", "dim": D, "stride": TILE, "dtype": "float32", "projection": None, "levels": levels},
        written,
    )


def _slide(root: Path, name: str, hw, lesion, seed: int) -> Path:
    from slide_helpers import pyramid

    from data_tools.bundle import build_bundle

    h, w = hw
    image = np.full((h, w, 3), 245, np.uint8)
    image[h // 8 : h - h // 8, w // 10 : w - w // 10] = [230, 160, 200]
    annotations = None
    if lesion is not None:
        y, x, side = lesion
        image[y : y + side, x : x + side] = [110, 40, 140]
        ring = [[x, y], [x + side, y], [x + side, y + side], [x, y + side], [x, y]]
        annotations = root / "slides" / f"{name}.geojson"
        annotations.parent.mkdir(parents=True, exist_ok=True)
        annotations.write_text(
            json.dumps(
                {
                    "type": "FeatureCollection",
                    "features": [
                        {
                            "type": "Feature",
                            "properties": {"classification": {"name": "Tumor"}},
                            "geometry": {"type": "Polygon", "coordinates": [ring]},
                        }
                    ],
                }
            )
        )
    noise = np.random.default_rng(seed).integers(-6, 7, image.shape)
    image = np.clip(image.astype(int) + noise, 0, 255).astype(np.uint8)
    tif = pyramid(root / "slides" / f"{name}.tif", image, mpp=MPP)
    bundle = build_bundle(
        tif,
        root / "bundles" / name,
        annotations_path=annotations,
        level_sets=(5, 7),
        tile_size=TILE,
        magnification_range=16,
        progress=False,
    )
    _features(bundle)
    return bundle


def _dataset(folder: Path, bundles) -> Path:
    folder.mkdir(parents=True)
    spec = {
        "kind": "histojax test slides (C16-style)",
        "format": 2,
        "encoder": "pcam-cnn",
        "train": [str(b) for b in bundles],
        "test": [str(b) for b in bundles],
    }
    (folder / "dataset.json").write_text(json.dumps(spec))
    return folder


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("c16-style")
    small = [
        _slide(root, "small_tumour", (512, 640), (200, 260, 120), 0),
        _slide(root, "small_normal", (512, 640), None, 1),
    ]
    big = [
        _slide(root, "big_micro", (1024, 2304), (300, 900, 400), 2),  # 0.8 mm side: 1.13 mm diameter
        _slide(root, "big_itc", (1024, 2304), (500, 1500, 40), 3),  # 0.11 mm diameter
        _slide(root, "big_normal_a", (1024, 2304), None, 4),
        _slide(root, "big_normal_b", (1024, 2304), None, 5),
    ]
    return {"small": _dataset(root / "small-set", small), "big": _dataset(root / "big-set", big), "root": root}


@pytest.fixture(scope="module")
def reader(data, tmp_path_factory) -> Path:
    """A tiny cell-set reader as `baselines.reading.train_readers` leaves it (untrained parameters of its network, made
    on the small slides; log.csv, head_reward.json naming a head in another folder), published with its head."""
    from baselines.networks import preprocess_obs
    from baselines.ppo import make_network

    tmp = tmp_path_factory.mktemp("reader")
    config = {**READER, "env_kwargs": {"dataset": str(data["small"]), "split": "train", "read_budget": 0.2}}
    env, env_params = make_env(config)
    network = make_network(config, env)
    obs, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 2), env_params)
    params = network.init(jax.random.key(0), preprocess_obs(obs))
    run = tmp / "run"
    save_checkpoint(run, jax.tree.map(lambda a: a[None], params), config)
    (run / "log.csv").write_text("env_steps,mean_return\n0,0.0\n")
    HEAD.save(tmp / "head-fit")
    (run / "head_reward.json").write_text(
        json.dumps(
            {
                "head": str(tmp / "head-fit"),
                "head_name": HEAD.name,
                "gain": "log",
                "final": 1.0,
                "read_cost": 0.0,
                "read_budget": 0.2,
            }
        )
    )
    return publish(run, "tiny-set-reader", root=tmp / "published", chosen_by={"by": "validation (tests)"})


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _grid(dataset) -> np.ndarray:
    import histojax

    _, params = histojax.make(
        READER["env_id"], dataset=str(dataset), split="test", action_mode="glimpse:1", verify=False
    )
    return np.asarray(params.mode_data.slide_grid)


# ----------------------------------------------------------------------------- the cell-set reader through its head
def test_publish_keeps_the_readers_head_and_curve(reader):
    record = json.loads((reader / "head_reward.json").read_text())
    assert record["head"] == "head" and record["head_source"].endswith("head-fit")
    assert LogitHead.load(reader / "head").name == HEAD.name
    assert (reader / "log.csv").is_file() and (reader / "config.json").is_file()


def test_set_reader_is_scored_through_its_head_on_wider_and_taller_slides(data, reader, tmp_path, capsys):
    """Before: the policy's own declaring action scored the slide (no head, no AUC without ITC-only slides)."""
    small, big = _grid(data["small"]), _grid(data["big"])
    assert (big[:, 0].min() > small[:, 0].max()) and (big[:, 1].min() > small[:, 1].max())  # wider and taller
    out = tmp_path / "eval"
    assert (
        histojax_main(["evaluate", str(reader), "--dataset", str(data["big"]), "--episodes", "4", "--out", str(out)])
        == 0
    )
    printed = capsys.readouterr().out.splitlines()
    header = next(line for line in printed if line.startswith("policy"))
    assert header.split()[-11:] == ["read", "fields", "AUC", "[95", "%", "interval]", "AUC", "w/o", "ITC", "[95", "%]"]
    assert any(line.startswith("the head declares") and "'3x3 mean, max'" in line for line in printed)
    rows = json.loads((out / "eval.json").read_text())
    (table,) = rows["results"].values()
    assert rows["head"]["name"] == HEAD.name and Path(rows["head"]["folder"]) == reader / "head"
    assert set(table) == {"ppo (greedy)", "ppo (sampled)", "random"}
    for name, row in table.items():
        line = next(line for line in printed if line.startswith(name))
        assert " ".join(line.split()[-6:]) == (
            f"{row['diagnosis_auc']:.3f} [{row['diagnosis_auc_low']:.3f}, "
            f"{row['diagnosis_auc_high']:.3f}] {row['diagnosis_auc_no_itc']:.3f} "
            f"[{row['diagnosis_auc_no_itc_low']:.3f}, {row['diagnosis_auc_no_itc_high']:.3f}]"
        ), line
        assert f"{row['mean_fraction_read']:.1%}" in line
        assert 0.0 <= row["diagnosis_auc"] <= 1.0 and 0.0 <= row["diagnosis_auc_no_itc"] <= 1.0
        assert 0.0 <= row["mean_fraction_read"] <= 0.2 + 0.05  # the budget (one cell may overshoot it)
    assert table["random"]["mean_fraction_read"] > 0  # random picks read cells before a declaring action


def test_the_head_scores_what_each_episode_read(data):
    """``head_score`` of an episode is the head on the finest views under the cells it revealed (computed here
    from the final state), not an earlier step's; success is that score's diagnosis; slides in turn."""
    from baselines.reading.reader_scores import masks_from_instances
    from histojax.reading.heads import score_logits

    config = {**READER, "env_kwargs": {"dataset": str(data["big"]), "split": "test", "read_budget": 0.2}}
    _, (env, env_params) = rollout.eval_env(config)
    wrapped, classes = heads.head_env(env, env_params, HEAD, {"gain": "log", "final": 1.0, "read_cost": 0.0})
    assert classes == ["micro", "ITC", "normal", "normal"]
    n = 8
    per, axes = rollout.per_episode_params(env_params, np.arange(n) % 4)
    rand = lambda k, obs: jax.random.randint(k, (obs["slide"].shape[0],), 0, env.num_actions - 2)  # noqa: E731
    ep = rollout.run_episodes(wrapped, per, rand, jax.random.key(5), n, params_axes=axes, final=True)
    ep = heads.head_scored(ep, env_params, classes)
    assert ep["slide"].tolist() == [0, 1, 2, 3] * 2 and ep["lesion"].tolist() == classes * 2
    host = env.action.host_tables(env, env_params, env.bundles)
    from baselines.reading.slides import load_slide

    for e in range(n):
        i = int(ep["slide"][e])
        revealed = np.flatnonzero(np.asarray(ep["final_state"].memory.revealed[e]))
        slide = load_slide(env.bundles[i].path, dim=LOGIT)
        mask = masks_from_instances(slide, np.flatnonzero(np.isin(host[i]["instance_cell"], revealed)))
        assert mask.any() and ep["fraction_read"][e] > 0
        by_hand = float(score_logits(HEAD, slide["logits"], mask))
        assert ep["head_score"][e] == pytest.approx(by_hand, abs=1e-5)
        assert ep["success"][e] == ((by_hand >= 0) == bool(ep["label"][e]))


# ----------------------------------------------------------------------------- every published folder
def _kind(folder: Path) -> str:
    """What `histojax evaluate` does with a folder of baselines/published on the wider slides."""
    if not folder.exists():
        return "retired"
    config = json.loads((folder / "config.json").read_text())
    from histojax.reading.heads import HEADS

    if config.get("kind") in HEADS:  # slide heads of every kind
        return "head"
    if str(config.get("action_mode", "")).startswith("glimpse") and (config.get("env_kwargs") or {}).get(
        "glimpse_grid"
    ):
        return "flat glimpse"
    return "runs"


FOLDERS = sorted({p.name for p in PUBLISHED.iterdir() if p.is_dir()} | set(checks.RETIRED))
REFUSED = [n for n in FOLDERS if _kind(PUBLISHED / n) != "runs"]
RUNS = [n for n in FOLDERS if _kind(PUBLISHED / n) == "runs"]


def test_the_published_folders_are_known():
    assert {"c16-v2-head", "c16-v1-zoom-reader", "c16-v1-diagnosis", "c16-v1-hard-navigator"} <= set(FOLDERS)
    assert "c16-v1-glimpse-reader" in REFUSED  # a flat grid (present) or retired (removed): refused either way


@pytest.mark.parametrize("name", REFUSED)
def test_published_folder_refused_in_one_line_saying_what_to_use(name, data, tmp_path, capsys):
    folder = PUBLISHED / name
    kind = _kind(folder)
    code = histojax_main(
        ["evaluate", str(folder), "--dataset", str(data["big"]), "--episodes", "1", "--out", str(tmp_path / "o")]
    )
    assert code == 2
    line = _one_error_line(capsys)
    set_reader = PUBLISHED / checks.SET_READER
    if kind == "head":
        assert "a slide head, not an agent" in line and f"--head {folder}" in line
    elif kind == "flat glimpse":
        assert "do not fit glimpse_grid=[16, 14]" in line and "cannot read a slide wider or taller" in line
        assert (
            f"histojax evaluate {checks.published_path(checks.SET_READER)}" in line
            if set_reader.is_dir()
            else "baselines.reading.train_readers" in line
        )
    else:
        assert "retired" in line and "docs/results/c16.md" in line and checks.SET_READER in line
    assert not (tmp_path / "o").exists()


def test_a_retired_folder_points_to_the_set_reader(tmp_path, capsys):
    """The old path, once the folder is removed: one line naming the reader that replaced it."""
    gone = tmp_path / "c16-v1-glimpse-reader"
    assert histojax_main(["evaluate", str(gone), "--dataset", str(tmp_path)]) == 2
    line = _one_error_line(capsys)
    assert str(gone) in line and "retired" in line and "16 × 14 cell grid" in line
    assert f"histojax evaluate {checks.published_path(checks.SET_READER)} --dataset DIR" in line


# 10-60 s each on 2 CPU cores (greedy, sampled, random rollouts): all under `make test-all` (the default run stays
# under CI's 10 minutes); in `make test`, test_set_reader_is_scored_through_its_head_on_wider_and_taller_slides
# runs the same `histojax evaluate` path with a cell-set reader on these slides
@pytest.mark.slow
@pytest.mark.parametrize("name", RUNS)
def test_published_agent_runs_on_wider_slides(name, data, tmp_path, capsys):
    out = tmp_path / "eval"
    assert (
        histojax_main(
            # the published heads and agents record c16-full's slides by CAMELYON16 name: not these (the flag is moot)
            ["evaluate", str(PUBLISHED / name), "--dataset", str(data["big"]), "--episodes", "2", "--out", str(out)]
            + ["--allow-fitting-slides"]
        )
        == 0
    )
    (table,) = json.loads((out / "eval.json").read_text())["results"].values()
    assert "random" in table and all(np.isfinite(r["mean_fraction_read"]) for r in table.values())
    header = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("policy"))
    assert "read" in header.split()


def test_a_head_that_is_not_there_is_one_line(reader, data, tmp_path, capsys):
    import shutil

    run = tmp_path / "moved"
    shutil.copytree(reader, run, ignore=shutil.ignore_patterns("head"))  # the reader without its head folder
    assert histojax_main(["evaluate", str(run), "--dataset", str(data["big"]), "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert str(run / "head_reward.json") in line and "names the slide head 'head'" in line and "--head DIR" in line
    (run / "head_reward.json").write_text("[1, 2]")
    assert histojax_main(["evaluate", str(run), "--dataset", str(data["big"]), "--out", str(tmp_path / "o")]) == 2
    assert "names no slide head" in _one_error_line(capsys)
    assert not (tmp_path / "o").exists()
