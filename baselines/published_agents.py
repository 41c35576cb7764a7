"""The published agents and slide heads: where they live, how a bare name reaches one, and ``histojax published``,
the command that lists them with what each was trained on.

    histojax published                 every published agent and head: what it is, what it was trained on
    histojax published NAME            one in full: the slides it trained on, how to build them, how it was chosen
    histojax evaluate NAME --dataset DIR   evaluate one by name (``baselines/published/NAME`` of the installed package)

A leaf of ``baselines``: ``evaluate`` and ``publish`` both read it, so neither imports the other back."""

from __future__ import annotations

import json
import os
from pathlib import Path

PUBLISHED = Path(__file__).resolve().parent / "published"
"""``baselines/published``: one folder per published agent or slide head."""
PACKAGE_NAME = "baselines/published/"
"""How docs and published records name a folder of :data:`PUBLISHED` (``baselines/published/NAME``)."""


def published_names() -> list[str]:
    """The names of the published agents and heads (the folders of :data:`PUBLISHED` holding a ``config.json``),
    sorted."""
    return sorted(p.name for p in PUBLISHED.iterdir() if (p / "config.json").is_file()) if PUBLISHED.is_dir() else []


def published_or_path(text: str) -> str:
    """A run or head folder given on a command line: the installed package's ``baselines/published/NAME`` when
    ``text`` is the bare ``NAME`` of a published agent or head, or its package name ``baselines/published/NAME``
    (so ``histojax evaluate c16-v2-set-reader`` works from any folder, the wheel's included, and a folder of that
    name under the working folder is never taken for it: name that one ``./NAME``); else ``text`` as given.
    argparse ``type=`` of such arguments."""
    name = text[len(PACKAGE_NAME) :].rstrip("/") if text.startswith(PACKAGE_NAME) else text
    if not name or "/" in name or os.sep in name or name in (".", ".."):
        return text
    folder = PUBLISHED / name
    return str(folder) if (folder / "config.json").is_file() else text


def _json(path: Path) -> dict:
    """The JSON object in ``path``, ``{}`` when the file is missing, unreadable or not an object."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def describe(name: str) -> dict:
    """What the published folder ``name`` is, as ``histojax published`` prints it: ``name``; ``kind``
    (``"agent"`` or ``"head"``); ``what`` (an agent's trainer, env id, action and observation modes and the head it
    reads through; a head's kind, structure and encoder); ``trained_on`` (dataset, split and number of slides:
    ``published.json``'s ``trained_on`` of an agent, ``config.json``'s ``fitted_on`` of a head); ``detail`` (the
    ``[(label, text)]`` of the slides it trained on, how to build them and how it was chosen, as recorded, and how
    many slides it records having seen: ``slides_seen.json`` of an agent, ``config.json``'s ``slides_seen`` of a
    head);
    ``folder`` (its path in the installed package)."""
    folder = PUBLISHED / name
    config = _json(folder / "config.json")
    if "kind" in config and "algo" not in config:  # a slide head (histojax.reading.heads)
        kind, fitted = "head", config.get("fitted_on") or {}
        what = f"{config.get('kind')} ({config.get('name')})" if config.get("name") else str(config.get("kind"))
        what += f", {config['encoder']} features" if config.get("encoder") else ""
        detail = []
    else:
        kind, record = "agent", _json(folder / "published.json")
        fitted = record.get("trained_on") or {}
        head = _json(folder / "head_reward.json").get("head")
        what = ", ".join(
            str(v)
            for v in (config.get("algo"), config.get("env_id"), config.get("action_mode"), config.get("obs_mode"))
            if v
        )
        what += f"; diagnoses through {Path(head).name}" if isinstance(head, str) and head else ""
        chosen = record.get("chosen_by") or {}
        detail = [
            (label, str(text))
            for label, text in (
                ("slides", fitted.get("what")),
                ("build", fitted.get("build")),
                ("chosen by", chosen.get("by")),
            )
            if text
        ]
    seen = _json(folder / "slides_seen.json") if kind == "agent" else config.get("slides_seen")
    if isinstance(seen, dict) and (seen.get("fitted") or seen.get("validation")):  # what every scorer refuses
        fit, val = ({str(n) for n in seen.get(k) or []} for k in ("fitted", "validation"))
        verb = "trained" if kind == "agent" else "fitted"
        detail.append(
            (
                "slides seen",
                f"{len(fit | val)} ({len(fit)} {verb} on, {len(val)} validated on): every scorer refuses them "
                "(--allow-fitting-slides: warned)",
            )
        )
    fitted = fitted if isinstance(fitted, dict) else {}
    trained_on = ", ".join(
        str(v)
        for v in (
            fitted.get("dataset"),
            fitted.get("split"),
            f"{fitted['slides']} slides" if fitted.get("slides") else None,
        )
        if v
    )
    return {
        "name": name,
        "kind": kind,
        "what": what,
        "trained_on": trained_on or "not recorded",
        "detail": detail,
        "folder": str(folder),
    }


def add_arguments(p) -> None:
    """The options of ``histojax published`` (``python -m baselines.published_agents``)."""
    p.add_argument("name", nargs="?", default=None, help="one published agent or head, shown in full")


def run(args, parser) -> int:
    """Print the published agents and heads (or the one ``args.name`` in full); one ``error:`` line (status 2) for a
    name that is none of them."""
    from data_tools.cli_output import print_error

    names = published_names()
    if args.name is not None:
        if args.name not in names:
            return print_error(
                f"no published agent or head is named {args.name!r}; the published ones: "
                f"{', '.join(names) or 'none (no baselines/published in this installation)'}"
            )
        d = describe(args.name)
        print(f"{d['name']} ({d['kind']}): {d['what']}\ntrained on: {d['trained_on']}")
        for label, text in d["detail"]:
            print(f"{label}: {text}")
        print(f"folder: {d['folder']}")
        return 0
    rows = [describe(n) for n in names]
    width = max([len(r["name"]) for r in rows] + [4])
    trained = max([len(r["trained_on"]) for r in rows] + [10])
    print(
        f"published agents and slide heads ({PUBLISHED}); evaluate an agent by name: histojax evaluate NAME "
        "--dataset DIR; one in full: histojax published NAME\n"
    )
    print(f"{'name':<{width}}  {'kind':<5}  {'trained on':<{trained}}  what")
    for r in rows:
        print(f"{r['name']:<{width}}  {r['kind']:<5}  {r['trained_on']:<{trained}}  {r['what']}")
    return 0


if __name__ == "__main__":
    from data_tools.cli_output import command_main

    raise SystemExit(command_main(add_arguments, run, "python -m baselines.published_agents", __doc__)())
