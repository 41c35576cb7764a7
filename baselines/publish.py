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
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from baselines import common, outputs
from baselines.published_agents import PUBLISHED
from data_tools.errors import HistojaxDataError


def publish(run, name: str, root=PUBLISHED, seed: int | None = None, note: str | None = None,
            chosen_by: dict | None = None) -> Path:
    """Copy run folder ``run``'s checkpoint into ``root/name`` (``seed``: keep only that seed's
    parameters, still with a leading seed axis of 1); returns the folder."""
    run = Path(run)
    if not (run / "params.msgpack").is_file() or not (run / "config.json").is_file():
        raise ValueError(f"{run}: not a run folder (needs params.msgpack and config.json)")
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"bad name {name!r}: one folder name")
    # the slide head of a reader trained with SASHA's reward, found before anything is written
    head = published_head(run) if (run / "head_reward.json").is_file() else None
    dest = Path(root) / name
    dest.mkdir(parents=True, exist_ok=True)
    if seed is None:
        for f in ("params.msgpack", "config.json"):  # whole or absent (baselines.outputs)
            outputs.write_bytes(dest / f, (run / f).read_bytes())
        seeds = None
    else:
        params, config = common.load_checkpoint(run)
        n = jax.tree.leaves(params)[0].shape[0]
        if not 0 <= seed < n:
            raise ValueError(f"{run} has {n} seed(s); --seed {seed} is not one of them")
        common.save_checkpoint(dest, jax.tree.map(lambda a: a[seed:seed + 1], params),
                               {**json.loads((run / "config.json").read_text()), "num_seeds": 1})
        seeds = [seed]
    for f in ("log.csv", "curve.png"):  # the learning curve, when the run has one
        if (run / f).is_file():
            outputs.write_bytes(dest / f, (run / f).read_bytes())
    if head is not None:
        record, copy = head
        if copy is not None:
            (dest / "head").mkdir(exist_ok=True)
            for f in ("config.json", "params.json"):
                outputs.write_bytes(dest / "head" / f, (copy / f).read_bytes())
        outputs.write_text(dest / "head_reward.json", json.dumps(record, indent=1) + "\n")
    summary = None
    if (run / "log.json").is_file():
        summary = json.loads((run / "log.json").read_text()).get("summary")
    record = {"name": name, "source_run": str(run.resolve()), "seeds": seeds, "training_summary": summary,
              "chosen_by": chosen_by, "note": note}
    outputs.write_text(dest / "published.json", json.dumps(record, indent=1))
    return dest


def published_head(run: Path) -> tuple[dict, Path | None]:
    """``(record, head to copy or None)``: ``run``'s ``head_reward.json`` with its ``head`` findable from the
    published folder — a head inside ``baselines/published`` named ``baselines/published/HEAD`` (nothing to
    copy); any other named ``head``, to be copied beside the reader (``NAME/head``). The head as the run
    named it is kept as ``head_source``. ``HistojaxDataError`` when the head is not there."""
    from baselines.evaluate import head_reward_settings, resolve_head

    record, where = head_reward_settings(run, {})
    head = resolve_head(record["head"], run, where).resolve()
    if head.is_relative_to(PUBLISHED.resolve()):
        return {**record, "head": f"baselines/published/{head.relative_to(PUBLISHED.resolve()).as_posix()}",
                "head_source": record["head"]}, None
    return {**record, "head": "head", "head_source": record["head"]}, head


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run folder (params.msgpack + config.json)")
    p.add_argument("name", help="folder name under --root")
    p.add_argument("--seed", type=int, default=None, help="keep only this seed (default: every seed)")
    p.add_argument("--root", default=str(PUBLISHED), help="default baselines/published")
    p.add_argument("--note", default=None, help="free text kept in published.json (e.g. the validation numbers)")
    p.add_argument("--chosen-by", default=None,
                   help="how the run and seed were chosen, kept in published.json as chosen_by.by (e.g. 'validation "
                        "AUC at 10 %% read, 3 seeds'); never the test split")
    args = p.parse_args(argv)
    try:
        dest = publish(args.run, args.name, args.root, args.seed, args.note,
                       chosen_by={"by": args.chosen_by} if args.chosen_by else None)
    except (OSError, ValueError, HistojaxDataError) as e:
        raise SystemExit(f"publish: {e}") from None
    print(f"published {args.run} as {dest}; score it with: histojax evaluate {dest} --dataset DIR")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
