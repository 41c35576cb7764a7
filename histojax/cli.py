"""The ``histojax`` command: the one entry point for the tools, each a thin wrapper of its module.

    histojax info SLIDE|BUNDLE        pyramid of a slide (levels, px sizes, tiles, compression, µm/px)
    histojax build SLIDE --out DIR    slide bundle (levels, masks; see `histojax build --help`)
    histojax features BUNDLE          feature grid of a bundle (also: histojax import-features BUNDLE FILE.h5)
    histojax synth OUT_DIR            semi-synthetic slides and bundles with a train/test split
    histojax synth-large OUT.tif      a gigapixel semi-synthetic pyramidal TIFF
    histojax c16 --out DIR            the true-scale CAMELYON16-geometry benchmark dataset
    histojax dataset SLIDES --out DIR your own slides (SVS/TIFF/DICOM, CAMELYON16 as downloaded) as a dataset
    histojax train-encoder --out W    train the pcam-cnn encoder on the PCam training pool
    histojax demo [--no-train]        random-agent table, then PPO trained and evaluated on Easy (`make demo`)
    histojax train [--algo ppo|dqn|ppo_rnn]   pure-JAX baselines (`python -m baselines.ppo|dqn|ppo_rnn`);
                                      --dataset DIR --split S; --resume RUN continues a killed run
    histojax evaluate CHECKPOINT      success rate, return, steps to success, trajectory pictures; a reader:
                                      AUC through its slide head (--head DIR), fraction read; --dataset DIR;
                                      CHECKPOINT a run folder or a published agent's name (c16-v2-set-reader)
    histojax published [NAME]         the published agents and slide heads and what each was trained on
    histojax rotation --budget-mb MB  PPO on a dataset larger than the device, slides rotated through it
    histojax budget-curve --dataset DS   diagnosis AUC against the fraction of the slide read
    histojax reproduce [--quick]      the paper's tables: every algorithm trained, evaluated, tabulated
    histojax contract [ENV_ID ...]    the environment contract check (`make contract`, histojax.testing)
    histojax bench                    environment throughput (steps/s) against memory bandwidth (from a
                                      source checkout: the wheel does not install benchmarks/)

Compiled programs are kept in JAX's persistent compilation cache (~/.cache/histojax/jax, or
$XDG_CACHE_HOME/histojax/jax), so a second run starts warm; --no-compile-cache (any command) or
HISTOJAX_NO_COMPILE_CACHE=1 turns it off (histojax.compile_cache).

Each command is its module's (``python -m data_tools <command>``, ``python -m baselines.<module>``,
``python -m histojax.testing``, ``python benchmarks/throughput.py`` are the same commands): the
module's ``add_arguments(parser)`` declares the options, once, and its ``run(args, parser)`` runs
them (:func:`data_tools.cli_output.run_command`). `histojax <command> --help` lists the options.

Units: positions and sizes are pixels (level-0 px for annotations and regions, px of the
current level for views); `--tile-size` is the view side in px. User errors (bad files, unknown
ids or settings) print one line and exit with status 2; HISTOJAX_DEBUG=1 shows tracebacks.

The commands' packages (``data_tools``, ``baselines``) are top-level names installed beside ``histojax``; they
are only ever imported from there (:func:`own_package_refusal`): ``python -m histojax.cli`` puts the working
folder first on the import path, where a folder of the same name would otherwise be imported instead.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from pathlib import Path

from data_tools.cli_output import one_line_messages, os_error_text, print_error, run_command
from data_tools.errors import HistojaxDataError
from histojax import compile_cache

DATA_COMMANDS = (
    "info",
    "build",
    "features",
    "import-features",
    "synth",
    "synth-large",
    "c16",
    "dataset",
    "train-encoder",
)
COMMANDS = {  # histojax <command>: the module whose add_arguments and run it is
    **{name: "data_tools.__main__" for name in DATA_COMMANDS},
    "demo": "baselines.demo",
    "evaluate": "baselines.evaluate.cli",
    "published": "baselines.published_agents",
    "rotation": "baselines.rotation",
    "budget-curve": "baselines.reading.budget_curve",
    "reproduce": "baselines.reproduce",
    "contract": "histojax.testing",
    "bench": "benchmarks.throughput",
}
ALGOS = ("ppo", "dqn", "ppo_rnn")  # histojax train --algo NAME: baselines.NAME
INTERNAL_HINT = " (HISTOJAX_DEBUG=1 shows the traceback)"
"""Ends the line of an error that is not a user error (a ``ValueError`` / ``TypeError`` from inside): user errors
(``HistojaxDataError``, file-system errors) are one line without it."""


def main(argv=None) -> int:
    """Dispatch ``argv`` (default ``sys.argv[1:]``) to a subcommand; returns the exit status."""
    argv = compile_cache.setup(sys.argv[1:] if argv is None else argv)  # --no-compile-cache: removed here
    if not argv or argv[0] in ("-h", "--help"):
        from data_tools.cli_output import plain_text

        print(plain_text(__doc__))  # no reST markup on the terminal
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
            if isinstance(e, OSError):  # a user's file or folder (read-only, missing, disk full): the line says it
                return print_error(os_error_text(e))
            return print_error(e, "" if user_error(e) else INTERNAL_HINT)


def user_error(e: BaseException) -> bool:
    """Whether ``e`` is a user error the project words itself (printed without :data:`INTERNAL_HINT`): a
    ``HistojaxDataError``, or a ``ValueError`` / ``TypeError`` raised by a line of the project's own packages (a
    bad id or setting given to ``histojax.make``, a head file's field). One raised inside a library (NumPy, JAX)
    is unexpected: its line keeps the hint."""
    if isinstance(e, HistojaxDataError):
        return True
    tb = e.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    where = os.path.realpath(tb.tb_frame.f_code.co_filename)
    return any(where.startswith(root + os.sep) for root in _OWN_ROOTS)


_OWN_ROOTS = tuple(
    os.path.realpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", name))
    for name in ("histojax", "data_tools", "baselines", "benchmarks", "experiments")
)


def _dispatch(command: str, rest: list[str]) -> int:
    """Run ``histojax <command> <rest>`` with the command module's own parser (one-line usage errors)."""
    if command == "train":
        algo = _resumed_algo(rest) or "ppo"  # --resume RUN without --algo: the run's own trainer
        if "--algo" in rest:
            i = rest.index("--algo")
            algo = rest[i + 1] if i + 1 < len(rest) else ""
            rest = rest[:i] + rest[i + 2 :]
        if algo not in ALGOS:
            return print_error(f"--algo must be one of {', '.join(ALGOS)}, got {algo!r}")
        if refusal := own_package_refusal("data_tools") or own_package_refusal("baselines"):
            return print_error(refusal)
        return _run(importlib.import_module(f"baselines.{algo}"), rest, f"histojax train --algo {algo}")
    if command not in COMMANDS:
        return print_error(f"unknown command {command!r}; one of: {', '.join([*COMMANDS, 'train'])}")
    for name in ("data_tools", COMMANDS[command].split(".")[0]):
        if refusal := own_package_refusal(name):
            return print_error(refusal)
    module = importlib.import_module(COMMANDS[command])
    if command in DATA_COMMANDS:  # one parser with the data commands as its subcommands
        return _run(module, [command, *rest], "histojax")
    return _run(module, rest, f"histojax {command}")


HOME = Path(__file__).resolve().parents[1]
"""The folder ``histojax`` is installed in (site-packages, or a source checkout): the commands' packages are
imported from here and nowhere else."""


def package_home(name: str) -> Path | None:
    """The folder the top-level package ``name`` is (or would be) imported from: the parent of its package folder;
    None when it cannot be imported. Found without importing it."""
    module = sys.modules.get(name)
    spec = module.__spec__ if module is not None else importlib.util.find_spec(name)
    if spec is None:
        return None
    if spec.origin not in (None, "namespace"):  # a regular package: .../name/__init__.py
        return Path(spec.origin).resolve().parent.parent
    places = list(spec.submodule_search_locations or [])  # a namespace package: a folder without __init__.py
    return Path(places[0]).resolve().parent if places else None


def own_package_refusal(name: str) -> str | None:
    """One line when the top-level package ``name`` a command needs would not be histojax's own (from
    :data:`HOME`): a folder of that name in the working folder first on the import path (``python -m``), or the
    package not installed (``benchmarks``: a wheel does not install it, ``histojax bench`` runs from a source
    checkout, where it is found beside ``histojax``); None when it is histojax's own."""
    home = package_home(name)
    if home is None and name == "benchmarks" and (HOME / "benchmarks" / "throughput.py").is_file():
        sys.path.append(str(HOME))  # a source checkout whose install does not map benchmarks: its own folder
        home = package_home(name)
    if home == HOME:
        return None
    if home is None and name == "benchmarks":
        return (
            "histojax bench runs from a source checkout: the wheel does not install benchmarks/ "
            "(in a clone of the repository: make bench, or python benchmarks/throughput.py)"
        )
    if home is None:
        return f"{HOME / name}: not installed beside histojax (reinstall histojax: pip install histojax)"
    return (
        f"{home / name}: a folder named {name} in the import path ahead of histojax's own ({HOME / name}); "
        "python -m puts the working folder first: run the histojax command, or from another folder"
    )


def _resumed_algo(rest: list[str]) -> str | None:
    """The trainer recorded in ``RUN/checkpoint/config.json`` of ``--resume RUN`` in ``rest`` (None when absent
    or unreadable: the trainer's own resume then names the file)."""
    import json
    from pathlib import Path

    if "--resume" not in rest or rest.index("--resume") + 1 >= len(rest):
        return None
    try:
        algo = json.loads((Path(rest[rest.index("--resume") + 1]) / "checkpoint" / "config.json").read_text()).get(
            "algo"
        )
    except (OSError, ValueError, AttributeError):
        return None
    return algo if algo in ALGOS else None


def _run(module, argv: list[str], prog: str) -> int:
    """The command ``module`` (its ``add_arguments`` and ``run``) on ``argv``, usage errors one line."""
    return run_command(module.add_arguments, module.run, argv, prog=prog, doc=module.__doc__)


if __name__ == "__main__":
    sys.exit(main())
