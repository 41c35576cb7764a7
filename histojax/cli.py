"""The ``histojax`` command: one entry point for the tools, each a thin wrapper of its module.

    histojax info SLIDE|BUNDLE        pyramid of a slide (levels, px sizes, tiles, compression, µm/px)
    histojax build SLIDE --out DIR    slide bundle (levels, masks; see `histojax build --help`)
    histojax features BUNDLE          feature grid of a bundle (`python -m data_tools features`)
    histojax demo [--no-train]        random-agent table, then PPO trained and evaluated on Easy (`make demo`)
    histojax train [--algo ppo|dqn]   pure-JAX baselines (`python -m baselines.ppo|dqn`)
    histojax evaluate CHECKPOINT      success rate, return, steps to success, trajectory pictures
    histojax bench                    environment throughput (steps/s) against memory bandwidth

Units: positions and sizes are pixels (level-0 px for annotations and regions, px of the
current level for views); `--tile-size` is the view side in px. User errors (bad files, unknown
ids or settings) print one line and exit with status 2; HISTOJAX_DEBUG=1 shows tracebacks.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from data_tools.cli_output import OneLineParser, one_line_messages, os_error_text, print_error
from data_tools.errors import HistojaxDataError

COMMANDS = {
    "info": ("data_tools.__main__", ["info"]),
    "build": ("data_tools.__main__", ["build"]),
    "features": ("data_tools.__main__", ["features"]),
    "demo": ("baselines.demo", []),
    "evaluate": ("baselines.evaluate", []),
    "bench": ("benchmarks.throughput", []),
}


def _run(module_name: str, argv: list[str], prog: str = "histojax") -> int:
    module = importlib.import_module(module_name)
    sys.argv[0] = prog  # argparse names the program after it: "histojax train", not "cli.py"
    original_error = argparse.ArgumentParser.error
    argparse.ArgumentParser.error = OneLineParser.error  # every subcommand's usage errors: one line, exit 2
    try:
        result = module.main(argv)
    finally:
        argparse.ArgumentParser.error = original_error
    return int(result or 0)


def main(argv=None) -> int:
    """Dispatch ``argv`` (default ``sys.argv[1:]``) to a subcommand; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    with one_line_messages():
        try:
            return _dispatch(command, rest)
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        except (HistojaxDataError, FileNotFoundError, ValueError, TypeError, OSError) as e:
            if os.environ.get("HISTOJAX_DEBUG"):
                raise
            text = os_error_text(e) if isinstance(e, OSError) else e
            return print_error(text, " (HISTOJAX_DEBUG=1 shows the traceback)")


def _dispatch(command: str, rest: list[str]) -> int:
    if command == "train":
        algo = "ppo"
        if "--algo" in rest:
            i = rest.index("--algo")
            algo = rest[i + 1] if i + 1 < len(rest) else ""
            rest = rest[:i] + rest[i + 2:]
        if algo not in ("ppo", "dqn"):
            return print_error(f"--algo must be ppo or dqn, got {algo!r}")
        return _run(f"baselines.{algo}", rest, f"histojax train --algo {algo}")
    if command not in COMMANDS:
        return print_error(f"unknown command {command!r}; one of: {', '.join([*COMMANDS, 'train'])}")
    module_name, prefix = COMMANDS[command]
    return _run(module_name, prefix + rest, f"histojax {command}" if not prefix else "histojax")


if __name__ == "__main__":
    sys.exit(main())
