"""The trainers' shared command line: options, the config they make (``--set key=value``, ``--dataset``),
``--resume RUN``, and ``python -m baselines.<algo>``'s entry point."""

from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path

import jax

from baselines.common.config import ConfigError, EnvConfig
from baselines.harness import distributed, run_folder
from baselines.harness.runner import resume_config, run_and_save
from data_tools.cli_output import build_parser, command_main, positive_float, print_error
from data_tools.errors import HistojaxDataError


# ----------------------------------------------------------------------------- the command line and a run
def non_negative_int(text: str) -> int:
    """argparse type: a whole number >= 0 (``--checkpoint-every``: 0 saves only at the end)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0 (0: a checkpoint only at the end)")
    return value


def add_arguments(p, defaults: dict) -> None:
    """Declare a trainer's options on the parser (or argument group) ``p``, with ``defaults`` its
    config defaults: the one declaration behind ``python -m baselines.ppo|dqn|ppo_rnn``,
    ``histojax train --algo ...`` and ``baselines.rotation``."""
    p.add_argument("--env", default=defaults["env_id"], help="registered env id")
    p.add_argument("--slide", default=None, help="bundle folder (default: the embedded sample slide)")
    p.add_argument(
        "--dataset",
        default=None,
        metavar="DIR",
        help="a dataset folder (histojax dataset / data_tools c16 / synth; its dataset.json): "
        "train on its slides (make(env, dataset=DIR))",
    )
    p.add_argument(
        "--split", default=None, metavar="S", help="with --dataset: the split to train on (default: the env's, 'train')"
    )
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="with --dataset built with --folds K: train on fold I's train side (the other K - 1 folds); "
        "make(..., fold=I)",
    )
    p.add_argument(
        "--action-mode",
        default="discrete",
        help="discrete | continuous | glimpse[:LEVEL] | zoom_select[:K] (histojax.core.modes.factory)",
    )
    p.add_argument(
        "--obs-mode",
        "--obs",
        dest="obs_mode",
        default="pixels",
        help="the env's obs_mode: pixels | features | ... (--obs: the older spelling)",
    )
    p.add_argument("--with-position", action="store_true", help="observation dict with the view position")
    p.add_argument("--reward", default=None, help="reward preset (default: the env's, 'dense')")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--total-steps", type=int, default=defaults["total_timesteps"], help="env steps per seed")
    p.add_argument("--num-envs", type=int, default=defaults["num_envs"])
    p.add_argument("--lr", type=positive_float, default=defaults["lr"], help="learning rate (finite, > 0)")
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        help="shard the env batch over the first N devices (PPO; on CPU set "
        "XLA_FLAGS=--xla_force_host_platform_device_count=N)",
    )
    p.add_argument(
        "--shard-slides",
        action="store_true",
        help="with --devices N: split the dataset's slides over the devices (each device holds and "
        "draws only its own slides; docs/scaling.md)",
    )
    distributed.add_arguments(p)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other config entry, value parsed as JSON (e.g. --set ent_coef=0.02)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="run folder (default runs/<algo>-<env>, or the next free runs/<algo>-<env>-N when that one "
        "is used). The same command rerun continues the unfinished run of this config there from its last "
        "checkpoint (a finished one: nothing to train); a folder holding another config's run or other files "
        "is refused",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a finished run or another config's run in --out (only the files histojax wrote there; "
        "its final files stay until the new run's are written); an unfinished run of this config still "
        "continues",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="start again in --out: the run there (finished or not, any config) is moved aside whole into "
        "OUT/previous-N/, never deleted",
    )
    if "checkpoint_every" in defaults:
        p.add_argument(
            "--checkpoint-every",
            type=non_negative_int,
            default=None,
            metavar="N",
            help=f"save the whole training state to OUT/checkpoint/ every N updates "
            f"(default {defaults['checkpoint_every']}; 0: only at the end)",
        )
        p.add_argument(
            "--resume",
            default=None,
            metavar="RUN",
            help="continue the killed run in folder RUN from its last checkpoint, with its own "
            "config (RUN/checkpoint/config.json; other options are ignored); the result equals an "
            "uninterrupted run's",
        )


def parse_args(argv=None, defaults: dict | None = None, description: str = ""):
    """Parse a baseline's command line (``defaults``: its config defaults; :func:`add_arguments`)."""
    add = functools.partial(add_arguments, defaults=defaults)
    return build_parser(add, description=description.split("\n\n")[0], one_line=False).parse_args(argv)


def config_from_args(args, defaults: dict) -> dict:
    """The trainer config of parsed arguments: ``defaults`` with the options and ``--set`` entries applied."""
    config = {
        **defaults,
        "env_id": args.env,
        "slide": args.slide,
        "action_mode": args.action_mode,
        "obs_mode": args.obs_mode,
        "with_position": args.with_position,
        "reward": args.reward,
        "num_seeds": args.seeds,
        "seed": args.seed,
        "total_timesteps": args.total_steps,
        "num_envs": args.num_envs,
        "lr": args.lr,
    }
    if getattr(args, "checkpoint_every", None) is not None:
        config["checkpoint_every"] = args.checkpoint_every
    if args.devices is not None:
        if "devices" not in defaults:
            raise SystemExit("--devices is supported by the PPO baseline only")
        config["devices"] = args.devices
    if getattr(args, "shard_slides", False):
        if "shard_slides" not in defaults:
            raise SystemExit("--shard-slides is supported by the PPO baseline only")
        config["shard_slides"] = True
    for item in args.set:
        k, _, v = item.partition("=")
        if k not in defaults:
            raise SystemExit(f"unknown config entry {k!r}; known: {', '.join(defaults)}")
        try:
            config[k] = json.loads(v)
        except json.JSONDecodeError:
            config[k] = v
    fold = getattr(args, "fold", None)
    if getattr(args, "dataset", None) is not None or getattr(args, "split", None) is not None or fold is not None:
        if args.dataset is None:
            raise SystemExit(
                f"{'--split' if getattr(args, 'split', None) is not None else '--fold'} needs --dataset DIR"
            )
        config["env_kwargs"] = {
            **(config.get("env_kwargs") or {}),
            "dataset": args.dataset,
            **({"split": args.split} if args.split is not None else {}),
            **({"fold": fold} if fold is not None else {}),
        }
    return config


def train_and_save(algo: str, make_train_fn, args, config_class: type[EnvConfig], unit: str) -> int:
    """The command of a baseline (shared by every algorithm file), on ``args`` parsed with
    :func:`add_arguments`: the typed config (``config_class``, e.g. :class:`~baselines.ppo.PPOConfig`) made once
    from the options (an entry of the wrong type is one line, exit 2), then compile, train all seeds in one program,
    and write logs, curve and checkpoint with :func:`finish_run`. The run folder is claimed with
    :func:`~baselines.harness.run_folder.claim_run`: the same command rerun after a kill continues the unfinished
    run of its config from the last checkpoint (``--resume RUN`` does the same for a named folder, with the run's
    own config), ``--restart`` moves the old run aside and starts again."""
    defaults = config_class.defaults()
    if getattr(args, "resume", None) is not None:
        run = Path(args.resume)
        try:
            if not run.is_dir():
                raise run_folder.RunFolderError(run, "no such run folder; nothing to resume")
            run_folder.lock(run)  # one writer per run folder: a second --resume / --out RUN is refused
            config = resume_config(run, algo, config_class)
        except HistojaxDataError as e:
            run_folder.release(run)  # a refused resume leaves the folder as it was (no lock file)
            return print_error(e)
        try:
            run_and_save(algo, make_train_fn, config, run, unit, resume=True)
        finally:
            run_folder.release(run)
        return 0
    try:
        config = config_class.from_dict(config_from_args(args, defaults=defaults), where="the options (--set)")
    except ConfigError as e:
        return print_error(e)
    if (args.coordinator is not None or args.distributed) and "devices" not in defaults:
        raise SystemExit("several processes (--coordinator / --distributed) are supported by the PPO baseline only")
    distributed.from_args(args)
    out, state = Path(args.out or f"runs/{algo}-{config.env_id}"), "new"
    if jax.process_index() == 0:  # the process that writes the run's files holds its folder
        try:
            out, state = run_folder.claim_run(
                out,
                config.as_dict(),
                overwrite=getattr(args, "overwrite", False),
                default=args.out is None,
                restart=getattr(args, "restart", False),
            )
            if state in ("resume", "done") and jax.process_count() > 1:  # no checkpoints along the way there
                raise run_folder.RunFolderError(
                    out,
                    "holds a run of this config, which runs on several processes cannot continue; "
                    "--restart moves it aside, or choose another --out",
                )
            if state == "resume":  # a rerun of the command after a kill: continue with the run's own config
                config = resume_config(out, algo, config_class)
        except HistojaxDataError as e:
            run_folder.release(out)  # a refusal leaves the folder as it was (no lock file)
            return print_error(e)
    try:
        if state != "done":  # a finished run of this config: nothing to train
            run_and_save(algo, make_train_fn, config, out, unit, resume=state == "resume")
    finally:
        run_folder.release(out)
    return 0


def trainer_command(algo: str, make_train_fn, config_class: type[EnvConfig], unit: str, doc: str):
    """A trainer module's command: ``(add_arguments, run, main)`` for ``python -m baselines.<algo>`` and
    ``histojax train --algo <algo>``, the options :func:`add_arguments` with the defaults of the trainer's typed
    config ``config_class``."""

    def add(parser) -> None:
        """The trainer's options (:func:`add_arguments` with its defaults)."""
        add_arguments(parser, config_class.defaults())

    def run(args, parser=None) -> int:
        """Train on parsed ``args`` and write the run folder (:func:`train_and_save`)."""
        return train_and_save(algo, make_train_fn, args, config_class, unit)

    return add, run, command_main(add, run, f"python -m baselines.{algo}", doc)
