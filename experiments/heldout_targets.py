"""The baseline targets on slides the agent never trained on (issue: PPO, discrete, held-out
success ≥ 90 % Easy, ≥ 70 % Medium, ≥ 50 % Hard), and PPO's training throughput.

    python -m experiments.heldout_targets [--dataset /tmp/synth] [--scenarios Easy Medium Hard]
                                         [--steps 262144 786432 1048576] [--seeds 2] [--out runs/heldout]
                                         [--extra-dataset /tmp/synth_new] [--reuse] [--report-only]

Data: a semi-synthetic CAMELYON16-geometry slide set (pixels synthetic, geometry real) with a
train/test split by slide; made first with ``python -m data_tools synth DATASET --slides 8 --size 4096``
when ``DATASET/dataset.json`` is missing (~2 min, ~850 MB). Each scenario trains
``baselines.ppo`` on the train split (pixels + position, dihedral view augmentation), then
evaluates the sampled policy of every seed on every held-out slide *as it is* (no augmentation),
with the random agent and the scripted policy as reference rows. Held-out slides are the test
split (other CAMELYON16 tumours than the train split's) and, with ``--extra-dataset``, every slide
of other slide sets (e.g. ``data_tools synth --tumour-xml`` with annotations no training slide
used, another pixel seed). ``--reuse`` evaluates finished run folders again instead of retraining
(and keeps the rows of slides already evaluated for the same run). Writes ``targets.md`` and
``targets.json`` to ``--out`` and prints the table. Training throughput is printed with and without
compile time. This is a benchmark (hours of CPU at full budgets), not a test.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines import ppo  # noqa: E402
from baselines.evaluate.scoring import evaluate  # noqa: E402
from baselines.harness.logs import load_checkpoint  # noqa: E402
from baselines.run_config import read_run_config  # noqa: E402
from data_tools.cli_output import print_error  # noqa: E402
from data_tools.errors import HistojaxDataError  # noqa: E402
from data_tools.metrics import json_safe  # noqa: E402
from experiments import read_dataset  # noqa: E402

TARGETS = {"Easy": 0.90, "Medium": 0.70, "Hard": 0.50}
DEFAULT_STEPS = {"Easy": 262_144, "Medium": 786_432, "Hard": 1_048_576}


def ensure_dataset(path: Path, slides: int, size: int) -> dict:
    """``dataset.json`` of ``path``, making the slide set first if it is missing."""
    if not (path / "dataset.json").exists():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "data_tools",
                "synth",
                str(path),
                "--slides",
                str(slides),
                "--size",
                str(size),
                "--seed",
                "0",
            ],
            check=True,
            cwd=ROOT,
        )
    return read_dataset(path, ("train", "test"))


def heldout_slides(dataset: Path, spec: dict, extra: list[Path]) -> list[tuple[str, Path]]:
    """``(group, bundle)`` of every held-out slide: the dataset's test split, then every slide of
    each ``extra`` dataset (made from tumour annotations the training slides never used)."""
    slides = [("test split", dataset / rel) for rel in spec["test"]]
    for ds in extra:
        other = read_dataset(ds, ("slides",))
        slides += [("unseen geometry", ds / s["bundle"]) for s in other["slides"] if "bundle" in s]
    return slides


def run_scenario(
    name: str,
    dataset: Path,
    heldout: list,
    steps: int,
    seeds: int,
    episodes: int,
    out: Path,
    extra_args: list[str],
    reuse: bool = False,
    previous: dict | None = None,
) -> dict:
    """Train on the train split (or, with ``reuse``, take a finished run folder trained with the same
    scenario, dataset, steps and seeds), evaluate on each held-out slide (with ``reuse``, rows of
    ``previous`` results of the same training run are kept); returns the scenario's result."""
    env_id = f"HistoJAX-{name}-v0"
    run = out / f"ppo-{name.lower()}"
    kwargs = {"dataset": str(dataset), "split": "train", "augment": True}
    argv = [
        "--env",
        env_id,
        "--with-position",
        "--seeds",
        str(seeds),
        "--total-steps",
        str(steps),
        "--out",
        str(run),
        "--set",
        f"env_kwargs={json.dumps(kwargs)}",  # json-not-written (an option)
        *extra_args,
    ]
    if not (reuse and _same_run(run, env_id, kwargs, steps, seeds)):
        ppo.main(argv)
        previous = None
    else:
        print(f"reusing {run} (same scenario, dataset, steps and seeds)")
    summary = json.loads((run / "log.json").read_text())["summary"]
    params, record = load_checkpoint(run)
    config = read_run_config(record, run / "config.json")
    same_training = previous is not None and previous.get("train_seconds") == summary["train_seconds"]
    per_slide = {}
    for group, bundle in heldout:
        old = (previous or {}).get("per_slide", {}).get(bundle.name) if same_training else None
        if old is not None and old["random"]["episodes"] == episodes:
            per_slide[bundle.name] = {**old, "group": group}
            continue
        rows = evaluate(
            config, params, slide=str(bundle), num_episodes=episodes, out=run / "eval" / bundle.name, label="ppo"
        )
        per_slide[bundle.name] = {
            "group": group,
            **{k: rows[k] for k in ("ppo (sampled)", "ppo (greedy)", "random", "scripted") if k in rows},
        }

    def mean(key, group=None):
        vals = [r[key]["success_rate"] for r in per_slide.values() if group in (None, r["group"])]
        return float(np.mean(vals)) if vals else float("nan")

    return {
        "env_id": env_id,
        "steps_per_seed": steps,
        "seeds": seeds,
        "target": TARGETS[name],
        "heldout_success_sampled": mean("ppo (sampled)"),
        "heldout_success_greedy": mean("ppo (greedy)"),
        "test_split_success_sampled": mean("ppo (sampled)", "test split"),
        "unseen_geometry_success_sampled": mean("ppo (sampled)", "unseen geometry"),
        "random_success": mean("random"),
        "scripted_success": mean("scripted"),
        "train_success_final": summary["final"]["success"],
        "train_seconds": summary["train_seconds"],
        "compile_seconds": summary["compile_seconds"],
        "steps_per_s": summary["env_steps_per_second_all_seeds"],
        "steps_per_s_with_compile": steps * seeds / (summary["train_seconds"] + summary["compile_seconds"]),
        "per_slide": per_slide,
    }


def _same_run(run: Path, env_id: str, kwargs: dict, steps: int, seeds: int) -> bool:
    try:
        config = read_run_config(run / "config.json")
        summary = json.loads((run / "log.json").read_text())["summary"]
    except (OSError, ValueError, KeyError, HistojaxDataError):
        return False
    return (
        config.env_id == env_id
        and config.env_kwargs == kwargs
        and config.with_position
        and summary.get("env_steps_per_seed") == steps
        and summary.get("seeds") == seeds
    )


def markdown(results: dict, dataset: Path) -> str:
    lines = [
        "| scenario | target | held-out success (sampled; all held-out slides) | test split | unseen geometry | "
        "greedy | random agent | scripted | "
        "steps to success (PPO sampled / random) | "
        "train success | env steps/s (w/o, with compile) | steps × seeds |",
        "|" + "---|" * 12,
    ]
    for name, r in results.items():
        ok = "met" if r["heldout_success_sampled"] >= r["target"] else "NOT met"
        steps = {
            k: np.nanmean([v[k]["mean_steps_to_success"] for v in r["per_slide"].values()])
            for k in ("ppo (sampled)", "random")
        }
        pct = lambda v: "–" if v is None or v != v else f"{v:.1%}"  # noqa: E731
        lines.append(
            f"| {name} | ≥ {r['target']:.0%} | **{r['heldout_success_sampled']:.1%}** ({ok}) | "
            f"{pct(r.get('test_split_success_sampled'))} | {pct(r.get('unseen_geometry_success_sampled'))} | "
            f"{r['heldout_success_greedy']:.1%} | {r['random_success']:.1%} | {r['scripted_success']:.1%} | "
            f"{steps['ppo (sampled)']:.1f} / {steps['random']:.1f} | "
            f"{r['train_success_final']:.1%} | {r['steps_per_s']:,.0f} / {r['steps_per_s_with_compile']:,.0f} | "
            f"{r['steps_per_seed']:,} × {r['seeds']} |"
        )
    lines += ["", "Per held-out slide (sampled policy success):", ""]
    for name, r in results.items():
        cells = ", ".join(
            f"{s}{' (unseen geometry)' if v.get('group') == 'unseen geometry' else ''} "
            f"{v['ppo (sampled)']['success_rate']:.1%}"
            for s, v in r["per_slide"].items()
        )
        lines.append(f"- {name}: {cells}")
    lines += [
        "",
        f"Dataset {dataset} (pixels synthetic, geometry real CAMELYON16; split by slide). "
        f"Machine: {platform.machine()}, {jax.device_count()} {jax.devices()[0].platform} device(s), "
        f"JAX {jax.__version__}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", default="/tmp/synth", help="semi-synthetic slide set (made if missing)")
    p.add_argument("--slides", type=int, default=8, help="slides to make when the dataset is missing")
    p.add_argument("--size", type=int, default=4096, help="canvas px when the dataset is missing")
    p.add_argument("--scenarios", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    p.add_argument("--steps", type=int, nargs="+", default=None, help="env steps per seed, one per scenario")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--episodes", type=int, default=128, help="evaluation episodes per seed and test slide")
    p.add_argument("--out", default="runs/heldout")
    p.add_argument(
        "--extra-dataset",
        nargs="*",
        default=[],
        metavar="DATASET",
        help="more held-out slides: every slide of these slide sets (e.g. made with "
        "`data_tools synth --tumour-xml` from annotations the training slides never used)",
    )
    p.add_argument("--report-only", action="store_true", help="rewrite targets.md from --out's targets.json")
    p.add_argument("--reuse", action="store_true", help="evaluate finished runs in --out again instead of retraining")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed to baselines.ppo")
    args = p.parse_args(argv)
    steps = args.steps or [DEFAULT_STEPS[s] for s in args.scenarios]
    if len(steps) != len(args.scenarios):
        p.error("give one --steps value per scenario")
    dataset = Path(args.dataset)
    if args.report_only:
        text = markdown(json.loads((Path(args.out) / "targets.json").read_text()), dataset)
        (Path(args.out) / "targets.md").write_text(text + "\n")
        print(text)
        return 0
    try:  # a malformed dataset.json: one line naming it
        spec = ensure_dataset(dataset, args.slides, args.size)
        heldout = heldout_slides(dataset, spec, [Path(d) for d in args.extra_dataset])
    except HistojaxDataError as e:
        return print_error(e)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extra = [a for s in args.set for a in ("--set", s)]
    previous = {}
    if args.reuse and (out / "targets.json").exists():
        previous = json.loads((out / "targets.json").read_text())
    results = {}
    t0 = time.perf_counter()
    for name, n in zip(args.scenarios, steps):
        results[name] = run_scenario(
            name, dataset, heldout, n, args.seeds, args.episodes, out, extra, args.reuse, previous.get(name)
        )
        text = markdown(results, dataset)
        (out / "targets.md").write_text(text + "\n")
        (out / "targets.json").write_text(json.dumps(json_safe({**previous, **results}), indent=1, allow_nan=False))
    print("\n" + text)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; wrote {out}/targets.md, targets.json")
    return 0


def run_main(argv=None) -> int:
    """:func:`main`, a slide set it cannot read (a missing or malformed bundle found while training or scoring) one
    line naming the file, exit 2."""
    try:
        return main(argv)
    except HistojaxDataError as e:
        return print_error(e)


if __name__ == "__main__":
    raise SystemExit(run_main())
