"""Publish a trained agent: copy a run's ``config.json`` and ``params.msgpack`` (all seeds, or one)
into ``baselines/published/NAME/`` with a ``published.json`` record (source run, seeds kept, the
run's training summary and, when given, the table cell it was chosen from), so it can be scored on
any C16-style dataset without training:

    python -m baselines.publish runs/c16-reference/ppo-features-easy c16-easy-navigator [--seed 1]
    histojax evaluate baselines/published/c16-easy-navigator --dataset DIR [--split test]

The run's learning curve (``log.csv``, ``curve.png``) comes along when it has one. A reader trained with
SASHA's reward (``python -m baselines.reading.train_readers``) keeps its ``head_reward.json``, whose slide head
is made findable wherever the folder goes: a head published in ``baselines/published`` is named as
``baselines/published/HEAD``; any other head is copied into the folder (``NAME/head``), so that
``histojax evaluate baselines/published/NAME --dataset DIR`` scores it through the head it trained with.

Choose the run (and ``--seed``) on validation results (``c16_reference.py --val-fraction``), never
on the test split.

A published folder carries no path of the machine it was trained on: the dataset and slides in ``config.json``
(``env_kwargs.dataset``, ``env_kwargs.slides``, ``slide``) are written as ``null`` and named instead, by folder name
and in words (``--trained-on TEXT``: what the dataset is and the command that builds it), in ``published.json``'s
``trained_on``; ``source_run`` is the run's folder name; ``head_reward.json`` and a copied head keep folder names
only. ``histojax evaluate NAME --dataset DIR`` scores it on any dataset of the kind it trained on.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from baselines import outputs
from baselines.harness.logs import load_checkpoint, save_checkpoint
from baselines.published_agents import PUBLISHED
from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe


def publish(
    run,
    name: str,
    root=PUBLISHED,
    seed: int | None = None,
    note: str | None = None,
    chosen_by: dict | None = None,
    trained_on: str | None = None,
) -> Path:
    """Copy run folder ``run``'s checkpoint into ``root/name`` (``seed``: keep only that seed's
    parameters, still with a leading seed axis of 1); returns the folder. No path of this machine is written
    (:func:`portable_config`): the dataset it trained on is named in ``published.json``'s ``trained_on`` by
    folder name, split and ``trained_on`` (words: what it is and how to build it)."""
    run = Path(run)
    if not (run / "params.msgpack").is_file() or not (run / "config.json").is_file():
        raise ValueError(f"{run}: not a run folder (needs params.msgpack and config.json)")
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"bad name {name!r}: one folder name")
    # the slide head of a reader trained with SASHA's reward, found before anything is written
    head = published_head(run) if (run / "head_reward.json").is_file() else None
    try:
        config = json.loads((run / "config.json").read_text())
    except ValueError as e:
        raise ValueError(f"{run / 'config.json'}: not JSON ({e})") from None
    if not isinstance(config, dict):
        raise ValueError(f"{run / 'config.json'}: not an object of settings")
    config, where = portable_config(config)
    head_config = None
    if head is not None and head[1] is not None:  # a head copied beside the reader: its config read before writing
        try:
            head_config = portable_head_config(json.loads((head[1] / "config.json").read_text()))
        except ValueError as e:
            raise ValueError(f"{head[1] / 'config.json'}: not JSON ({e})") from None
    dest = Path(root) / name
    dest.mkdir(parents=True, exist_ok=True)
    if seed is None:
        outputs.write_bytes(dest / "params.msgpack", (run / "params.msgpack").read_bytes())  # whole or absent
        outputs.write_text(dest / "config.json", json.dumps(json_safe(config), indent=2, allow_nan=False))
        seeds = None
    else:
        params, _ = load_checkpoint(run)
        n = jax.tree.leaves(params)[0].shape[0]
        if not 0 <= seed < n:
            raise ValueError(f"{run} has {n} seed(s); --seed {seed} is not one of them")
        save_checkpoint(dest, jax.tree.map(lambda a: a[seed : seed + 1], params), {**config, "num_seeds": 1})
        seeds = [seed]
    for f in ("log.csv", "curve.png"):  # the learning curve, when the run has one
        if (run / f).is_file():
            outputs.write_bytes(dest / f, (run / f).read_bytes())
    seen = portable_slides_seen(run)
    if seen is not None:  # the slides it trained and validated on, its dataset by folder name
        outputs.write_text(dest / "slides_seen.json", json.dumps(json_safe(seen), indent=1, allow_nan=False) + "\n")
    if head is not None:
        record, copy = head
        if copy is not None:
            (dest / "head").mkdir(exist_ok=True)
            for f in ("params.json", "params.npz"):  # whichever the head's kind keeps
                if (copy / f).is_file():
                    outputs.write_bytes(dest / "head" / f, (copy / f).read_bytes())
            outputs.write_text(
                dest / "head" / "config.json", json.dumps(json_safe(head_config), indent=1, allow_nan=False) + "\n"
            )
        outputs.write_text(dest / "head_reward.json", json.dumps(json_safe(record), indent=1, allow_nan=False) + "\n")
    summary = None
    if (run / "log.json").is_file():
        summary = json.loads((run / "log.json").read_text()).get("summary")
    if trained_on:
        where["what"] = trained_on
    record = {
        "name": name,
        "source_run": run_name(run, config),
        "seeds": seeds,
        "trained_on": where or None,
        "training_summary": summary,
        "chosen_by": chosen_by,
        "note": note,
    }
    outputs.write_text(dest / "published.json", json.dumps(json_safe(record), indent=1, allow_nan=False))
    return dest


def folder_name(path) -> str:
    """The last part of ``path`` (a folder of some machine), as a name that is no path."""
    return Path(str(path)).name


def run_name(run: Path, config: dict) -> str:
    """``run``'s folder name, with its parent's when the run is a trainer's subfolder (``OUT/ppo`` of
    ``baselines.reading.train_readers``: ``nav-map-fid/ppo``): names, never a path of this machine."""
    run = run.resolve()
    if run.name in (str(config.get("algo") or ""), "ppo", "ppo_rnn", "dqn") and run.parent.name:
        return f"{run.parent.name}/{run.name}"
    return run.name


def dataset_scale_record(dataset) -> dict:
    """``{"mpp", "encoder"}`` of the dataset folder ``dataset`` as its ``dataset.json`` records them (``mpp``:
    µm per level-0 px of its slides, :func:`baselines.evaluate.checks.dataset_mpp`; ``encoder``: its feature
    grids'), for ``trained_on``: what ``histojax evaluate``
    compares with the dataset it scores; only the fields it records (``{}`` when it cannot be read)."""
    try:
        record = json.loads((Path(dataset) / "dataset.json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(record, dict):
        return {}
    from baselines.evaluate.checks import dataset_mpp

    out = {}
    mpp = dataset_mpp(record)  # scale.mpp (histojax c16), else the median of the slides' (histojax dataset)
    if mpp is not None:
        out["mpp"] = mpp
    if isinstance(record.get("encoder"), str) and record["encoder"]:
        out["encoder"] = record["encoder"]
    return out


def portable_config(config: dict) -> tuple[dict, dict]:
    """``(config, trained_on)``: a run's ``config.json`` object with the paths of the machine it trained on
    written as ``null`` (``env_kwargs.dataset``, ``env_kwargs.slides``, ``slide``), and what they named as folder
    names (``trained_on``: ``dataset``, ``split``, ``fold``, ``slides``, ``slide``; empty when none), with the dataset's
    scale and encoder when its ``dataset.json`` is readable (:func:`dataset_scale_record`)."""
    config = dict(config)
    kw = dict(config.get("env_kwargs") or {}) if isinstance(config.get("env_kwargs"), dict) else None
    where: dict = {}
    if kw is not None:
        if isinstance(kw.get("dataset"), str) and kw["dataset"]:
            where["dataset"] = folder_name(kw["dataset"])
            where["split"] = kw.get("split", "train")
            where.update(dataset_scale_record(kw["dataset"]))
            if kw.get("fold") is not None:
                where["fold"] = kw["fold"]
            kw["dataset"] = None
        if isinstance(kw.get("slides"), (list, tuple)) and kw["slides"]:
            where["slides"] = [folder_name(s) for s in kw["slides"]]
            kw["slides"] = None
        config["env_kwargs"] = kw
    if isinstance(config.get("slide"), str) and config["slide"]:
        where["slide"] = folder_name(config["slide"])
        config["slide"] = None
    return config, where


def portable_slides_seen(run: Path) -> dict | None:
    """The slides run folder ``run`` trained and validated on (:func:`baselines.reading.provenance.run_record`: its
    ``slides_seen.json``, or what its ``config.json`` names), the dataset named by folder name; the validation slides
    its dataset held back (``held_back``) are recorded as ``validation``: a published run was chosen on them. None
    when it records none."""
    from baselines.reading.provenance import run_record

    record, _ = run_record(run)
    if record is None:
        return None
    dataset = dict(record.get("dataset") or {})
    if isinstance(dataset.get("folder"), str):
        dataset["folder"] = folder_name(dataset["folder"])
    validation = sorted(set(record.get("validation") or []) | set(record.get("held_back") or []))
    record = {k: v for k, v in record.items() if k != "held_back"}
    return {**record, "dataset": dataset, "validation": validation}


def portable_head_config(config):
    """A slide head's ``config.json`` object with the dataset it was fitted on (``fitted_on.dataset``, written
    by the head fits as an absolute path) reduced to its folder name."""
    if (
        isinstance(config, dict)
        and isinstance(config.get("fitted_on"), dict)
        and isinstance(config["fitted_on"].get("dataset"), str)
    ):
        config = {
            **config,
            "fitted_on": {**config["fitted_on"], "dataset": folder_name(config["fitted_on"]["dataset"])},
        }
    seen = config.get("slides_seen") if isinstance(config, dict) else None
    if (
        isinstance(seen, dict)
        and isinstance(seen.get("dataset"), dict)
        and isinstance(seen["dataset"].get("folder"), str)
    ):
        folder = folder_name(seen["dataset"]["folder"])
        config = {**config, "slides_seen": {**seen, "dataset": {**seen["dataset"], "folder": folder}}}
    return config


def published_head(run: Path) -> tuple[dict, Path | None]:
    """``(record, head to copy or None)``: ``run``'s ``head_reward.json`` with its ``head`` findable from the
    published folder — a head inside ``baselines/published`` named ``baselines/published/HEAD`` (nothing to
    copy); any other named ``head``, to be copied beside the reader (``NAME/head``). The head as the run
    named it is kept as ``head_source``. ``HistojaxDataError`` when the head is not there."""
    from baselines.evaluate.checks import head_reward_settings, resolve_head

    record, where = head_reward_settings(run, {})
    head = resolve_head(record["head"], run, where).resolve()
    if isinstance(record.get("dataset"), str):  # the folder trained on, by name (no path of this machine)
        record = {**record, "dataset": folder_name(record["dataset"])}
    if head.is_relative_to(PUBLISHED.resolve()):
        published = f"baselines/published/{head.relative_to(PUBLISHED.resolve()).as_posix()}"
        return {**record, "head": published, "head_source": published}, None
    return {**record, "head": "head", "head_source": folder_name(record["head"])}, head


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run folder (params.msgpack + config.json)")
    p.add_argument("name", help="folder name under --root")
    p.add_argument("--seed", type=int, default=None, help="keep only this seed (default: every seed)")
    p.add_argument("--root", default=str(PUBLISHED), help="default baselines/published")
    p.add_argument("--note", default=None, help="free text kept in published.json (e.g. the validation numbers)")
    p.add_argument(
        "--chosen-by",
        default=None,
        help="how the run and seed were chosen, kept in published.json as chosen_by.by (e.g. 'validation "
        "AUC at 10 %% read, 3 seeds'); never the test split",
    )
    p.add_argument(
        "--trained-on",
        default=None,
        help="what the dataset it trained on is and the command that builds it, kept in published.json as "
        "trained_on.what (e.g. 'CAMELYON16 true-scale set, train split: histojax c16 --features ... "
        "--out DIR'); its folder name and split are kept anyway, its path never",
    )
    args = p.parse_args(argv)
    try:
        dest = publish(
            args.run,
            args.name,
            args.root,
            args.seed,
            args.note,
            chosen_by={"by": args.chosen_by} if args.chosen_by else None,
            trained_on=args.trained_on,
        )
    except (OSError, ValueError, HistojaxDataError) as e:
        raise SystemExit(f"publish: {e}") from None
    print(f"published {args.run} as {dest}; score it with: histojax evaluate {dest} --dataset DIR")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
