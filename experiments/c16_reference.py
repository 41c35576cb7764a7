"""Reference results on a slide dataset with a train/test split by slide (the CAMELYON16-geometry
benchmark): random agent, scripted coarse-to-fine policy, PPO on pixels + position, PPO on
features (+ position), recurrent PPO; detection success and steps to success on Easy / Medium /
Hard, diagnosis accuracy and AUC on Diagnosis, all on the test split, mean ± std over seeds.

    python -m experiments.c16_reference --dataset DIR [--steps 262144] [--seeds 3] [--episodes 128]
                                       [--methods random scripted ppo-pixels ppo-features ppo-rnn]
                                       [--scenarios Easy Medium Hard Diagnosis] [--out runs/c16-reference]
                                       [--version v1|v0] [--val-fraction 0.2] [--val-seed 0]
                                       [--env NAME=ID] [--env-kwargs NAME=JSON] [--rnn-obs features|pixels]
    python -m experiments.c16_reference --quick      # a small slice of every table in minutes (small variant)

Scenarios map to env ids ``HistoJAX-C16-{Easy,Medium,Hard,Diagnosis}-v1`` (``--version v0`` for
older datasets; ``--env NAME=ID`` for others, ``--env-kwargs NAME=JSON`` for extra ``histojax.make``
settings of one scenario, e.g. ``--env Diagnosis=HistoJAX-Easy-v0 --env-kwargs
'Diagnosis={"task": "classification"}'`` on a dataset without the C16 ids). Evaluation uses
``split="test"``: the test split is one env whose resets draw a test slide uniformly, so a success
rate is pooled over test slides.

Validation (``--val-fraction``, default 0.2; 0 turns it off): a seeded share of the *training*
slides is held back (:mod:`baselines.validation`: per class, tumour slides with their tissue
donors) into ``OUT/validation/dataset.json``; trained cells train on the rest and are scored on the
validation slides too (``validation`` in ``reference.json``). Choose hyperparameters and the agent
to publish on those numbers, never on the test split.

Each trained method runs ``baselines.ppo`` / ``baselines.ppo_rnn`` (``--steps`` env steps per seed,
one value or one per scenario; ``--seeds`` seeds in one program) into ``OUT/<method>-<scenario>/``
(its learning curves ``curve.png`` and ``log.csv`` there), then evaluates every seed's **sampled**
policy on ``--episodes`` fresh test episodes per seed (``baselines.evaluate``; the greedy row is
kept in the JSON) and reports mean ± std over seeds (``seeds`` in the JSON) and the compiled
training program's env steps/s. Random and scripted rows come from the same evaluation; the
scripted policy walks toward the darkest stain on pixels, and on features zooms where the view's
tumour logit is high (:func:`baselines.episodes.policies.scripted_features_policy`); it never declares a
diagnosis, so it has no Diagnosis cell. Detection success and steps to success count the episodes
on test *tumour* slides only (labels from ``dataset.json``); the JSON keeps the rate over all
slides and per slide too. Success on Diagnosis = a right diagnosis (declaring ends the episode; an
episode that never declares counts as wrong); its AUC is that of the policy's p(tumour) at the step
it declared.

Rows are resumable: every finished cell goes into ``OUT/reference.json`` with its budget, and a
rerun with the same dataset, env id, settings and budget keeps it (``--redo`` recomputes). The
table (``OUT/reference.md``) is rewritten after every cell and printed at the end. This is a
benchmark (hours of CPU at real budgets), never a test; ``--quick`` is its smoke slice.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines import outputs, ppo, ppo_rnn  # noqa: E402
from baselines.evaluate.scoring import evaluate  # noqa: E402
from baselines.harness.logs import load_checkpoint  # noqa: E402
from baselines.run_config import read_run_config  # noqa: E402
from data_tools.metrics import auc_interval, json_safe  # noqa: E402

SCENARIOS = ("Easy", "Medium", "Hard", "Diagnosis")
METHODS = ("random", "scripted", "ppo-pixels", "ppo-features", "ppo-rnn")
REFERENCE = ("random", "scripted")  # rows of the untrained evaluation


def default_env_id(scenario: str, version: str = "v1") -> str:
    return f"HistoJAX-C16-{scenario}-{version}"


def method_settings(method: str, rnn_obs: str) -> dict:
    """The trainer and observation of a trained ``method``."""
    if method == "ppo-pixels":
        return {"trainer": "ppo", "obs_mode": "pixels"}
    if method == "ppo-features":
        return {"trainer": "ppo", "obs_mode": "features"}
    if method == "ppo-rnn":
        return {"trainer": "ppo_rnn", "obs_mode": rnn_obs}
    raise ValueError(f"unknown trained method {method!r}")


def cell_key(method: str, scenario: str) -> str:
    return f"{method}/{scenario}"


def cell_budget(
    dataset: Path,
    env_id: str,
    env_kwargs: dict,
    method: str,
    steps: int,
    seeds: int,
    episodes: int,
    extra: list[str],
    rnn_obs: str,
    validation: dict | None = None,
) -> dict:
    """What a stored cell must match to be kept on a rerun."""
    budget = {"dataset": str(Path(dataset).resolve()), "env_id": env_id, "env_kwargs": env_kwargs, "episodes": episodes}
    if method not in REFERENCE:
        budget.update(steps=steps, seeds=seeds, set=list(extra), **method_settings(method, rnn_obs))
        if validation:
            budget["validation"] = validation
    return budget


def seed_stats(row: dict, labels: dict, scenario: str) -> dict:
    """Mean and standard deviation over seeds of a trained row's headline numbers (its ``per_seed``
    evaluation rows): detection success on tumour slides and steps to success, or diagnosis accuracy
    and AUC. ``{name: {"mean", "std", "per_seed"}}``; empty when the row has no per-seed rows."""
    per = row.get("per_seed") or []
    if not per:
        return {}
    if scenario == "Diagnosis":
        values = {
            "accuracy": [r["success_rate"] for r in per],
            "auc": [r.get("diagnosis_auc", float("nan")) for r in per],
        }
    else:
        t = [on_tumour_slides(r, labels) for r in per]
        values = {
            "success": [r["success_rate"] for r in t],
            "steps_to_success": [r["mean_steps_to_success"] for r in t],
        }
    out = {}
    for k, v in values.items():
        a = np.asarray(v, np.float64)
        ok = a[np.isfinite(a)]
        out[k] = {
            "mean": float(ok.mean()) if ok.size else float("nan"),
            "std": float(ok.std()) if ok.size else float("nan"),
            "per_seed": a.tolist(),
        }
    return out


def slide_labels(spec: dict) -> dict:
    """Bundle folder name → 1 (tumour) / 0 (normal) from ``dataset.json``: its ``slides[].label``
    entries, or its ``labels`` mapping; empty when it has neither (then every slide counts as a
    tumour slide, as for ``data_tools synth``)."""
    labels = {
        Path(s["bundle"]).name: int(s["label"])
        for s in spec.get("slides", [])
        if isinstance(s, dict) and "bundle" in s and "label" in s
    }
    if not labels and isinstance(spec.get("labels"), dict):
        labels = {Path(k).name: int(v) for k, v in spec["labels"].items()}
    return labels


def on_tumour_slides(row: dict, labels: dict) -> dict:
    """Detection row restricted to the episodes on tumour slides (on a normal slide there is nothing
    to find): ``success_rate``, ``mean_steps_to_success``, ``episodes``; the row itself when it has
    no per-slide counts (one slide) or no slide is labelled normal."""
    by = row.get("by_slide")
    if not by or not any(labels.get(name, 1) == 0 for name in by):
        return {k: row[k] for k in ("episodes", "success_rate", "mean_steps_to_success")}
    keep = [v for name, v in by.items() if labels.get(name, 1) == 1]
    n, wins = sum(v["episodes"] for v in keep), sum(v["successes"] for v in keep)
    steps = sum(v["steps_to_success_sum"] for v in keep)
    return {
        "episodes": n,
        "success_rate": wins / n if n else float("nan"),
        "mean_steps_to_success": steps / wins if wins else float("nan"),
    }


def reference_cells(
    dataset: Path, env_id: str, env_kwargs: dict, episodes: int, seed: int = 0, obs_mode: str = "pixels"
) -> dict:
    """Random and scripted rows on the test split (``obs_mode`` + position; the scripted policy needs
    pixels, so a features evaluation has the random row only), ``episodes`` episodes each."""
    config = {
        "env_id": env_id,
        "with_position": True,
        "action_mode": "discrete",
        "obs_mode": obs_mode,
        "hidden": 256,
        "env_kwargs": {**env_kwargs, "dataset": str(dataset), "split": "test"},
    }
    t0 = time.perf_counter()
    rows = evaluate(config, None, num_episodes=episodes, seed=seed)
    wall = time.perf_counter() - t0
    return {name: {**row, "wall_s": wall} for name, row in rows.items()}


def trained_cell(
    method: str,
    dataset: Path,
    env_id: str,
    env_kwargs: dict,
    steps: int,
    seeds: int,
    episodes: int,
    out: Path,
    extra: list[str],
    rnn_obs: str,
    augment: bool,
    train_dataset: Path | None = None,
) -> dict:
    """Train ``method`` on the train split of ``train_dataset`` (default ``dataset``; a validation
    dataset of :mod:`baselines.validation` holds part of the training slides back) into ``out``,
    evaluate its sampled (and greedy) policy on the test split of ``dataset`` and, with a
    ``train_dataset``, on its validation slides (``validation``); returns the row (``sampled`` /
    ``greedy`` evaluation rows, per-seed rows, training summary, learning-curve files)."""
    settings = method_settings(method, rnn_obs)
    trainer = ppo if settings["trainer"] == "ppo" else ppo_rnn
    train_kwargs = {**env_kwargs, "dataset": str(train_dataset or dataset), "split": "train"}
    if augment and settings["obs_mode"] == "pixels":
        train_kwargs["augment"] = True
    argv = [
        "--env",
        env_id,
        "--obs-mode",
        settings["obs_mode"],
        "--with-position",
        "--seeds",
        str(seeds),
        "--total-steps",
        str(steps),
        "--out",
        str(out),
        "--set",
        f"env_kwargs={json.dumps(train_kwargs)}",  # json-not-written (an option)
        "--set",
        "print_progress=false",
        *extra,
    ]
    t0 = time.perf_counter()
    trainer.main(argv)
    train_wall = time.perf_counter() - t0
    params, record = load_checkpoint(out)
    config = read_run_config(record, Path(out) / "config.json")
    config = config.replace(
        env_kwargs={
            k: v for k, v in {**train_kwargs, "dataset": str(dataset), "split": "test"}.items() if k != "augment"
        }
    )
    t0 = time.perf_counter()
    rows = evaluate(config, params, num_episodes=episodes, label=settings["trainer"], references=False)
    name = f"{settings['trainer']} (sampled)"
    validation = None
    if train_dataset is not None:
        config = config.replace(
            env_kwargs={**config.env_kwargs, "dataset": str(train_dataset)}
        )  # its "test" list: the validation slides
        validation = evaluate(config, params, num_episodes=episodes, label=settings["trainer"], references=False)[name]
    summary = json.loads((out / "log.json").read_text())["summary"]
    return {
        **rows[name],
        "greedy": rows[f"{settings['trainer']} (greedy)"],
        "validation": validation,
        "train_wall_s": train_wall,
        "eval_wall_s": time.perf_counter() - t0,
        "train_success_final": summary["final"]["success"],
        "train_steps_per_s": summary["env_steps_per_second_all_seeds"],
        "compile_s": summary.get("compile_seconds"),
        "run": str(out),
        "curve_png": str(out / "curve.png"),
        "curve_csv": str(out / "log.csv"),
    }


def total_wall(cells: dict) -> float:
    """Seconds spent on the cells: training + evaluation of trained cells, and each scenario's one
    evaluation of the reference policies (random and scripted share it)."""
    trained = sum(c["train_wall_s"] + c["eval_wall_s"] for k, c in cells.items() if k.split("/")[0] not in REFERENCE)
    reference = {}
    for k, c in cells.items():
        if k.split("/")[0] in REFERENCE:
            reference[k.split("/")[1]] = c["wall_s"]
    return trained + sum(reference.values())


def _pct(v) -> str:
    return "–" if v is None or v != v else f"{v:.1%}"


def _num(v) -> str:
    return "–" if v is None or v != v else f"{v:.1f}"


def _interval(cell: dict, stats: dict | None) -> str:
    """`` [low, high]``: the 95 % interval over the test slides of the Diagnosis AUC shown (the mean over seeds, or
    the one run's), from the slides the evaluation scored; empty for a record without their counts."""
    n_tumour, n_normal = cell.get("diagnosis_tumour_slides"), cell.get("diagnosis_normal_slides")
    auc = stats["auc"]["mean"] if stats and "auc" in stats else cell.get("diagnosis_auc")
    if not n_tumour or not n_normal or auc is None or auc != auc:
        return ""
    low, high = auc_interval(float(auc), int(n_tumour), int(n_normal))
    return f" [{low:.3f}, {high:.3f}]"


def _pm(stats: dict | None, name: str, fmt) -> str | None:
    """``mean ± std`` over seeds of ``stats[name]`` (:func:`seed_stats`), or None without it."""
    if not stats or name not in stats:
        return None
    m, sd = stats[name]["mean"], stats[name]["std"]
    if m != m:
        return "–"
    if fmt is _pct:
        return f"{m:.1%} ± {sd:.1%}"
    if fmt is _num2:
        return f"{m:.3f} ± {sd:.3f}"
    return f"{m:.1f} ± {sd:.1f}"


def markdown(cells: dict, methods: list[str], scenarios: list[str], meta: dict) -> str:
    """The reference table: one row per method; per detection scenario the test-split success on
    tumour slides and mean steps to success, for Diagnosis the accuracy and AUC (the policy's
    probability of declaring tumour) — trained rows as mean ± std over seeds — then the training
    env steps/s (compiled program, all seeds) and the training wall time."""
    head = ["method"]
    for s in scenarios:
        head += [f"{s} accuracy", f"{s} AUC"] if s == "Diagnosis" else [f"{s} success", f"{s} steps to success"]
    head += ["train steps/s", "training wall time"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        row, wall, rates = [m], 0.0, []
        for s in scenarios:
            c = cells.get(cell_key(m, s))
            if c is None:
                row += ["n/a" if (m == "scripted" and s == "Diagnosis") else "not run", ""]
                continue
            st = c.get("seeds")
            if s == "Diagnosis":
                row += [
                    _pm(st, "accuracy", _pct) or _pct(c["success_rate"]),
                    (_pm(st, "auc", _num2) or _num2(c.get("diagnosis_auc"))) + _interval(c, st),
                ]
            else:
                d = c.get("tumour_slides", c)
                row += [
                    _pm(st, "success", _pct) or _pct(d["success_rate"]),
                    _pm(st, "steps_to_success", _num) or _num(d["mean_steps_to_success"]),
                ]
            wall += c.get("train_wall_s", 0.0)
            if c.get("train_steps_per_s"):
                rates.append(c["train_steps_per_s"])
        ran = any(cell_key(m, s) in cells for s in scenarios)
        row.append(f"{np.mean(rates):,.0f}" if rates else "–")
        row.append(f"{wall:,.0f} s" if m not in REFERENCE and ran else "–")
        lines.append("| " + " | ".join(row) + " |")
    val = meta.get("validation")
    lines += [
        "",
        f"Dataset `{meta['dataset']}` (test split: {meta['test_slides']} slides, "
        f"{meta['test_tumour_slides']} with tumour; train split: {meta['train_slides']}"
        + (
            f", of which {len(val['validation'])} held back for validation (fraction {val['fraction']}, seed "
            f"{val['seed']}; trained rows train on the other {len(val['train'])})"
            if val
            else ""
        )
        + "). Detection "
        f"success counts the episodes on test tumour slides only (a normal slide has nothing to find); "
        f"{meta['reachable']} Env ids: " + ", ".join(f"{s} `{meta['env_ids'][s]}`" for s in scenarios) + ".",
        f"Budget per trained cell: {meta['steps']} env steps per seed × {meta['seeds']} seed(s); "
        f"{meta['episodes']} test episodes per seed (per policy for random / scripted). Trained rows: the "
        f"sampled policy, mean ± std over seeds. Steps: mean episode length of the successful episodes. "
        f"Diagnosis AUC: of the policy's p(tumour) = p(DECLARE_TUMOUR) / (p(DECLARE_TUMOUR) + "
        f"p(DECLARE_NO_TUMOUR)) at the step it declared (or its last step), over test episodes; [low, high]: "
        f"its 95 % interval over the test slides (Newcombe's, of the mean over seeds). Learning "
        f"curves: `<out>/<method>-<scenario>/curve.png` and `log.csv`.",
        f"Machine: {platform.machine()}, {jax.device_count()} {jax.devices()[0].platform} device(s), "
        f"JAX {jax.__version__}. Total wall time of the cells: {meta['wall_s']:,.0f} s.",
    ]
    return "\n".join(lines)


def _num2(v) -> str:
    return "–" if v is None or v != v else f"{v:.3f}"


def parse_pairs(items: list[str], what: str) -> dict:
    out = {}
    for item in items:
        k, sep, v = item.partition("=")
        if not sep or k not in SCENARIOS:
            raise SystemExit(f"{what} takes SCENARIO=VALUE with SCENARIO one of {', '.join(SCENARIOS)}; got {item!r}")
        out[k] = v
    return out


QUICK_SET = ["num_envs=16", "num_steps=32", "num_minibatches=4", "hidden=64", "log_every=1000"]


def quick_dataset(out: Path) -> tuple[Path, str]:
    """The small C16 variant for ``--quick``, built on the fly into ``OUT/data`` (kept between runs):
    ``(folder, id version)`` — with pcam-cnn features (``-v1`` ids) when its weights ship, else
    colour-stats features (``-v0`` ids)."""
    from data_tools.features import pcam_cnn

    v1 = pcam_cnn.WEIGHTS.is_file()
    folder = out / "data" / ("c16-small-pcam" if v1 else "c16-small-colour")
    if not (folder / "dataset.json").is_file():
        import subprocess

        cmd = [sys.executable, "-m", "data_tools", "c16", "--small", "--out", str(folder), "--no-pixels"]
        cmd += [] if v1 else ["--encoder", "colour-stats"]
        print("building the small C16 variant:", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT)
    return folder, "v1" if v1 else "v0"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", default=None, help="dataset folder with dataset.json (train/test split by slide)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="a small slice of every table in minutes on 2 CPU cores: the small C16 variant built on the "
        "fly (OUT/data), 8,192 env steps per seed, 3 seeds, 16 episodes, small networks",
    )
    p.add_argument("--version", default="v1", choices=("v0", "v1"), help="C16 env ids HistoJAX-C16-*-VERSION")
    p.add_argument(
        "--val-fraction",
        type=float,
        default=0.2,
        help="share of the training slides held back for validation (tumour slides and their tissue "
        "donors kept together; 0: train on every training slide)",
    )
    p.add_argument("--val-seed", type=int, default=0, help="seed of the validation draw")
    p.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument(
        "--steps",
        type=int,
        nargs="+",
        default=[262_144],
        help="env steps per seed of each trained cell: one value, or one per scenario",
    )
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--episodes", type=int, default=128, help="test episodes per seed (per policy for the references)")
    p.add_argument("--env", action="append", default=[], metavar="SCENARIO=ID", help="env id of a scenario")
    p.add_argument(
        "--env-kwargs",
        action="append",
        default=[],
        metavar="SCENARIO=JSON",
        help="extra histojax.make settings of a scenario (JSON object)",
    )
    p.add_argument(
        "--rnn-obs",
        default="features",
        choices=("features", "pixels"),
        help="observation of the recurrent PPO (with the view position)",
    )
    p.add_argument("--no-augment", action="store_true", help="train pixel policies without dihedral view augmentation")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed to every trainer")
    p.add_argument("--out", default="runs/c16-reference")
    p.add_argument("--redo", action="store_true", help="recompute cells already in OUT/reference.json")
    args = p.parse_args(argv)
    if args.quick:
        if args.dataset is None:
            args.dataset, args.version = quick_dataset(Path(args.out))
        if args.steps == [262_144]:
            args.steps = [8192]
        if args.episodes == 128:
            args.episodes = 16
        args.set = QUICK_SET + args.set
    if args.dataset is None:
        p.error("give --dataset DIR (or --quick)")
    if len(args.steps) not in (1, len(args.scenarios)):
        p.error("give one --steps value, or one per scenario")
    steps = dict(zip(args.scenarios, args.steps * len(args.scenarios) if len(args.steps) == 1 else args.steps))
    env_ids = {s: default_env_id(s, args.version) for s in args.scenarios} | parse_pairs(args.env, "--env")
    try:
        env_kwargs = {s: json.loads(v) for s, v in parse_pairs(args.env_kwargs, "--env-kwargs").items()}
    except json.JSONDecodeError as e:
        raise SystemExit(f"--env-kwargs: not a JSON object ({e})") from None
    dataset = Path(args.dataset)
    try:
        spec = json.loads((dataset / "dataset.json").read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"--dataset {dataset}: cannot read dataset.json ({e})") from None
    if not spec.get("train") or not spec.get("test"):
        raise SystemExit(f"--dataset {dataset}: dataset.json needs non-empty 'train' and 'test' lists")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "reference.json"
    cells = json.loads(store.read_text()).get("cells", {}) if store.exists() and not args.redo else {}
    extra = [a for s in args.set for a in ("--set", s)]
    labels = slide_labels(spec)
    val_dataset, validation = None, None
    if args.val_fraction > 0:
        from baselines.validation import write_validation_dataset

        try:
            val_dataset = write_validation_dataset(dataset, args.val_fraction, args.val_seed, out / "validation")
        except ValueError as e:
            raise SystemExit(
                f"--val-fraction {args.val_fraction}: {e} (give --val-fraction 0 to train on every training slide)"
            ) from None
        validation = json.loads((val_dataset / "dataset.json").read_text())["validation"]
    test_names = [Path(t).name for t in spec["test"]]
    tumour_test = [n for n in test_names if labels.get(n, 1) == 1]
    views = {
        Path(s["bundle"]).name: s["finest_views_ge50"]
        for s in spec.get("slides", [])
        if isinstance(s, dict) and "finest_views_ge50" in s and "bundle" in s
    }
    reachable = (
        f"{sum(views.get(n, 0) > 0 for n in tumour_test)} of the {len(tumour_test)} test tumour slides "
        f"have a finest-level view ≥ 50 % tumour on the bundle's grid (dataset.json "
        f"`finest_views_ge50`)."
        if views
        else ""
    )
    pixels_kept = spec.get("pixels_kept", True)
    needs_pixels = {"ppo-pixels"} | ({"ppo-rnn"} if args.rnn_obs == "pixels" else set())
    no_pixels_note = ""
    if not pixels_kept:
        gib = spec.get("device_bytes", {}).get("pixels", 0) / 2**30
        no_pixels_note = (
            f" The dataset keeps no pixels (`data_tools c16 --no-pixels`, features "
            f"`{spec.get('encoder')}`), so the rows that need them ({', '.join(sorted(needs_pixels))}) "
            f"were not run; with their pixels, every level of every bundle would need {gib:,.1f} GiB on the device "
            f"(per level set: `benchmarks/c16_device_bytes.py`)."
        )
    meta = {
        "dataset": str(dataset),
        "train_slides": len(spec["train"]),
        "test_slides": len(spec["test"]),
        "test_tumour_slides": len(tumour_test),
        "reachable": reachable + no_pixels_note,
        "env_ids": env_ids,
        "steps": ", ".join(f"{s} {steps[s]:,}" for s in args.scenarios),
        "seeds": args.seeds,
        "episodes": args.episodes,
        "wall_s": 0.0,
        "validation": validation,
    }

    def save():
        meta["wall_s"] = total_wall(cells)
        outputs.write_text(
            store, json.dumps(json_safe({"meta": meta, "cells": cells}), indent=1, default=float, allow_nan=False)
        )
        text = markdown(cells, args.methods, args.scenarios, meta)
        outputs.write_text(out / "reference.md", text + "\n")
        return text

    for s in args.scenarios:
        kw = env_kwargs.get(s, {})
        for m in args.methods:
            if m == "scripted" and s == "Diagnosis" or (not pixels_kept and m in needs_pixels):
                continue
            budget = cell_budget(
                dataset, env_ids[s], kw, m, steps[s], args.seeds, args.episodes, args.set, args.rnn_obs, validation
            )
            key = cell_key(m, s)
            if key in cells and cells[key].get("budget") == budget:
                print(f"kept {key} from {store}")
                continue
            print(f"\n=== {key} ({env_ids[s]}) ===", flush=True)
            if m in REFERENCE:
                rows = reference_cells(
                    dataset, env_ids[s], kw, args.episodes, obs_mode="pixels" if pixels_kept else "features"
                )
                for ref in REFERENCE:
                    if ref in rows and ref in args.methods and not (ref == "scripted" and s == "Diagnosis"):
                        cells[cell_key(ref, s)] = {
                            **rows[ref],
                            "tumour_slides": on_tumour_slides(rows[ref], labels),
                            "budget": cell_budget(
                                dataset,
                                env_ids[s],
                                kw,
                                ref,
                                steps[s],
                                args.seeds,
                                args.episodes,
                                args.set,
                                args.rnn_obs,
                            ),
                        }
            else:
                run = out / f"{m}-{s.lower()}"
                c = trained_cell(
                    m,
                    dataset,
                    env_ids[s],
                    kw,
                    steps[s],
                    args.seeds,
                    args.episodes,
                    run,
                    extra,
                    args.rnn_obs,
                    not args.no_augment,
                    train_dataset=val_dataset,
                )
                cells[key] = {
                    **c,
                    "tumour_slides": on_tumour_slides(c, labels),
                    "seeds": seed_stats(c, labels, s),
                    "budget": budget,
                }
                if c.get("validation"):
                    cells[key]["validation"] = {**c["validation"], "seeds": seed_stats(c["validation"], labels, s)}
            save()
    text = save()
    print("\n" + text)
    print(f"\nwrote {out}/reference.md, reference.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
