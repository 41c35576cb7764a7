"""Train learned readers on any dataset through any slide head, with SASHA's reward
(:class:`histojax.reading.head_reward.HeadReward`), and score them on validation slides with the same head as
every other reader. A baseline with a ``histojax train``-style command line::

    python -m baselines.reading.train_readers --dataset DIR --head HEAD --seeds 3 --total-steps N --out DIR \\
        [--algo ppo|ppo_rnn] [--fold I] [--resume] [--read-budget 0.2] [--gain log] [--final 1] [--read-cost 0] \\
        [--val-fraction 0.3] [--env ID] [--levels N] [--compare NAME RUN] [-- TRAINER OPTIONS]

``DIR``: any dataset ``histojax dataset`` or ``histojax c16`` builds, with any encoder's feature grids (pcam-cnn,
your own ``--encoder module:function``, or ``.h5`` features imported from TRIDENT / CLAM); ``HEAD``: any slide
head folder (the learned attention-MIL head of :mod:`baselines.reading.learned_head_fit` for any features, or a
pcam-cnn logit head). The env id is ``HistoJAX-Reading-v0`` (any dataset; ``--env HistoJAX-C16-Diagnosis-v2``
still trains on a C16 set as before), its zoom levels the most the bundles were built for, up to 5 (``--levels``).

1. Holds back a validation share of ``DIR``'s training split (``--fold I``: of fold I's train side;
   :func:`baselines.validation.split_train`, per class) and writes ``OUT/dataset.json``: the same bundles, splits
   ``train`` (what is kept), ``validation`` and ``test`` (never read here), and
   ``OUT/validation-set/dataset.json`` whose ``test`` split is the validation slides (what the scoring step reads;
   it holds no test slide).
2. Trains the cell-set reader (``glimpse`` with ``step_obs=True``:
   :class:`baselines.cell_set_networks.CellSetActorCritic`, or its recurrent twin with ``--algo ppo_rnn``) on
   the kept training slides, the env wrapped in ``HeadReward(env, head, gain, final, read_cost)``, with the
   trainer's progress lines (``return``: the head reward; ``success``: the head's diagnosis right at the episode's
   end, as ``histojax evaluate`` reports it: :func:`progress_words`) and checkpoints; the trainer's run folder
   ``OUT/<algo>`` (``log.csv``, ``curve.png``,
   ``params.msgpack``, ``config.json``) plus ``OUT/<algo>/head_reward.json`` (the reward's settings) and
   ``OUT/<algo>/curve-seeds.png`` / ``.csv`` (the learning curve as mean ± std over seeds: :func:`seed_curve`).
   The same command rerun after a kill continues the trainer's run in ``OUT/<algo>`` from its last checkpoint (a
   finished one is not trained again, its ``head_reward.json`` kept, and the scoring runs); ``--resume`` does so
   with the stopped run's own config; ``--restart`` moves the old run aside into ``OUT/<algo>/previous-N/``.
3. Scores the trained seeds with :mod:`baselines.reading.readers` on the **validation** split at 5/10/20/50 %
   (overview only, random, scripted, the learned reader, read everything; the same head for every row):
   ``OUT/validation/readers.csv``, ``readers.png``, ``readers.json``. A head fitted on the training split saw these
   slides: they are scored with ``--allow-fitting-slides`` (one warning says so), to compare readers, not the head.

**Navigators** (``--action-mode discrete`` or ``continuous``): the
same training, the env wrapped in ``HeadReward`` (it tracks the finest views the navigator stood on; with
``HeadReward`` the head declares, the navigator's own declare only ends the episode; no ``read_budget``),
and the scoring step is :mod:`baselines.reading.diagnosis` on the validation split instead: each seed rolled
greedily once per validation slide, its read masks scored by the head beside the readers at the fraction
it read, plus any ``--compare NAME RUN`` navigator (e.g. a published one) scored the same way.

Prints wall times (training, compile, scoring) and env steps per second.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from baselines.reading import slides
from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError
from histojax import compile_cache
from histojax.registry import READING_ID

ENV_ID = READING_ID
MAX_LEVELS = 5  # zoom levels the reading id uses at most (the C16 ids' five)
NAVIGATION_MODES = ("discrete", "continuous")


def progress_words(gain: str, final: float, read_cost: float) -> str:
    """What the trainer's progress lines mean here, said once before them: ``return`` is the head reward it optimises
    (``gain`` per read, ``final`` when the head is right at the end, minus ``read_cost`` per read), ``success`` the
    head's diagnosis right at the episode's end (:class:`histojax.reading.head_reward.HeadReward`'s ``success``, what
    ``histojax evaluate`` reports through the head), never the env's own declared diagnosis."""
    terms = [
        f"the head's {gain} gain per read" if gain != "none" else None,
        f"{final:g} when the head is right at the end" if final else None,
        f"minus {read_cost:g} per read" if read_cost else None,
    ]
    said = ", ".join(t for t in terms if t) or "no term (gain none, final 0)"
    return (
        f"progress lines: return = the head reward per episode ({said}); success = the head's diagnosis right at "
        "the episode's end (p(tumour) >= 0.5 is the slide's label), as histojax evaluate reports it through the "
        "head; the AUC on validation slides follows training"
    )


def dataset_levels(dataset: Path, spec: dict, most: int = MAX_LEVELS) -> int:
    """The most zoom levels (≤ ``most``) the first training bundle of ``dataset`` was built for (its
    ``metadata.json``'s ``level_sets``; 3 when it records none), read through the checked loader."""
    from data_tools.bundle_files.reading import read_metadata

    entries = spec.get("train") or []
    if not entries:
        return 3
    bundle = Path(entries[0]) if Path(entries[0]).is_absolute() else dataset / entries[0]
    sets = [int(n) for n in (read_metadata(bundle).level_sets or []) if int(n) <= most]
    return max(sets) if sets else 3


def is_navigator(action_mode: str) -> bool:
    """Whether ``action_mode`` (e.g. ``"discrete"``, ``"glimpse:1"``) moves a view (a navigator) rather than
    picking cells (a reader)."""
    return action_mode.split(":")[0] in NAVIGATION_MODES


def scale_warning(dataset: Path, spec: dict) -> str | None:
    """The one-line warning repeated from ``dataset.json``'s ``encoder_scale`` (written by ``histojax dataset``)
    when slides lie outside the built-in encoder's training scale, as printed (``warning: ...``; the words of
    :func:`baselines.reading.slides.scale_warning`, which every tool reading a dataset repeats), else None."""
    line = slides.scale_warning(dataset, spec)
    return f"warning: {line}" if line else None


def split_dataset(dataset: Path, out: Path, fraction: float, seed: int, fold: int | None = None) -> Path:
    """``out/dataset.json``: ``dataset``'s spec (``fold=i``: fold i's sides) with its training split cut into
    ``train`` and ``validation`` (bundle paths made absolute); returns ``out``. ``HistojaxDataError`` naming the
    file on a missing, edited or malformed ``dataset.json``."""
    from baselines.validation import split_train

    spec = slides.read_spec(dataset, fold)  # its seal checked; fold i's sides
    kept, val = split_train(spec, fraction, seed)

    def absolute(entries):
        return [str((dataset / e).resolve()) if not Path(e).is_absolute() else e for e in entries]

    derived = {
        **spec,
        "train": absolute(kept),
        "validation": absolute(val),
        "test": absolute(spec.get("test") or []),
        "derived_from": str(dataset.resolve()),
        "validation_split": {
            "fraction": fraction,
            "seed": seed,
            "rule": "baselines.validation.split_train",
            **({"fold": fold} if fold is not None else {}),
        },
    }
    # the envs know the splits train / test: the validation slides are scored as the test split of a second
    # folder (OUT/validation-set), which holds no test slide at all
    scoring = {**derived, "test": derived["validation"], "validation": [], "note_split": "test = the validation slides"}
    for folder, obj in ((out, derived), (out / "validation-set", scoring)):
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / ".dataset.json.tmp"
        tmp.write_text(json.dumps(obj, indent=1, allow_nan=False))
        tmp.replace(folder / "dataset.json")
    return out


def same_split(out: Path, run_dir: Path, dataset: Path, fraction: float, seed: int, fold: int | None) -> None:
    """Refuse (``HistojaxDataError`` naming ``out/dataset.json``, one line) to split ``out`` again with other
    settings than the run in ``run_dir`` (a checkpoint or final params) trained on: a rerun would continue that
    run on other slides. Nothing to check when no run is there or ``out/dataset.json`` is absent."""
    path = out / "dataset.json"
    if not path.is_file() or not ((run_dir / "checkpoint").is_dir() or (run_dir / "params.msgpack").is_file()):
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return  # not readable: split_dataset writes it again (and the trainer's config still guards its run)
    was = old.get("validation_split") if isinstance(old, dict) else None
    if not isinstance(was, dict):
        return
    now = {"fraction": fraction, "seed": seed, **({"fold": fold} if fold is not None else {})}
    then = {k: was.get(k) for k in ("fraction", "seed", "fold") if k in was}
    source = old.get("derived_from")
    if then != now or (isinstance(source, str) and source != str(Path(dataset).resolve())):
        raise HistojaxDataError(
            path,
            f"the run in {run_dir} trained on the split of {source} with {then}, not of {Path(dataset).resolve()} "
            f"with {now}; rerun with those options, --restart (moves the run aside), or choose another --out",
        )


def with_head_reward(head, gain, final: float, read_cost: float):
    """Make the trainers' and the evaluation roll-out's :func:`~baselines.common.env.make_env` (the name each of
    :data:`ENV_MAKERS` calls) return the env wrapped in :class:`~histojax.reading.head_reward.HeadReward`; returns
    a function that restores the originals."""
    import importlib

    from baselines.common.env import make_env as original
    from histojax.reading.head_reward import HeadReward

    def make_env(config, auto_reset=True, mesh=None):
        env, params = original(config, auto_reset=auto_reset, mesh=mesh)
        return HeadReward(env, head, gain=gain, final=final, read_cost=read_cost, params=params), params

    modules = [importlib.import_module(name) for name in ENV_MAKERS]
    for module in modules:
        module.make_env = make_env

    def restore():
        for module in modules:
            module.make_env = original

    return restore


ENV_MAKERS = ("baselines.ppo", "baselines.ppo_rnn", "baselines.dqn", "baselines.episodes.rollout")
"""The modules whose ``make_env`` (:func:`baselines.common.env.make_env`, imported by name) makes a trainer's or a
roll-out's env: :func:`with_head_reward` wraps it in each."""


def seed_curve(run_dir: Path, png: Path, csv_path: Path, smooth: int = 8) -> tuple[Path, Path]:
    """The learning curve of a multi-seed run as mean ± std over seeds (``log.json``'s ``per_seed``
    ``return`` and ``length``, a running mean over ``smooth`` log points, skipping points without a value: an
    update in which no episode ended logs NaN): ``csv_path`` (step, return mean, std, per seed; length mean,
    std) and ``png``. Steps are env steps per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    log = json.loads((run_dir / "log.json").read_text())
    steps = np.asarray(log["step"], float)
    ret = np.asarray(log["per_seed"]["return"], float)  # (seeds, points)
    length = np.asarray(log["per_seed"]["length"], float)
    if ret.shape[-1] != len(steps):  # stored (points, seeds): make it (seeds, points)
        ret, length = ret.T, length.T
    smooth = max(1, min(smooth, len(steps)))  # a short run has fewer log points than the window
    kernel = np.ones(smooth)

    def sm(a):  # running mean over the log points that have a value (NaN: no episode ended in that update)
        seen = ~np.isnan(a)
        total = np.stack([np.convolve(np.where(k, r, 0.0), kernel, mode="valid") for r, k in zip(a, seen)])
        count = np.stack([np.convolve(k.astype(float), kernel, mode="valid") for k in seen])
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)

    x = steps[smooth - 1 :]
    r, n = sm(ret), sm(length)
    with open(csv_path, "w") as f:
        f.write(
            "env_steps_per_seed,return_mean,return_std,"
            + ",".join(f"return_seed{i}" for i in range(len(r)))
            + ",length_mean,length_std\n"
        )
        for j in range(len(x)):
            f.write(
                f"{int(x[j])},{r[:, j].mean():.4f},{r[:, j].std():.4f},"
                + ",".join(f"{v:.4f}" for v in r[:, j])
                + f",{n[:, j].mean():.3f},{n[:, j].std():.3f}\n"
            )
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, a, label in ((axes[0], r, "head-reward return"), (axes[1], n, "episode length (steps)")):
        m, sd = a.mean(0), a.std(0)
        ax.plot(x, m, color="C0", label=f"mean over {len(a)} seeds")
        ax.fill_between(x, m - sd, m + sd, color="C0", alpha=0.25, linewidth=0, label="± std over seeds")
        ax.set_ylabel(label)
        ax.grid(alpha=0.4)
    axes[0].legend(fontsize="small")
    axes[1].set_xlabel("env steps per seed")
    cfg = read_run_config(run_dir) if (run_dir / "config.json").is_file() else None
    title = f"{cfg.algo.upper()} {cfg.env_id} {cfg.action_mode}" if cfg is not None else f" {run_dir.name} "
    fig.suptitle(f"{title}, head reward: running mean over {smooth} log points", fontsize="small")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png, csv_path


def _params_stamp(run_dir: Path):
    """``(inode, size, mtime)`` of ``run_dir/params.msgpack`` beside a ``head_reward.json`` (a finished run's
    record), None otherwise: unchanged after the trainer ran, the run was not trained again."""
    try:
        if not (run_dir / "head_reward.json").is_file():
            return None
        st = (run_dir / "params.msgpack").stat()
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


def main(argv=None) -> int:
    from baselines.published_agents import published_or_path

    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(
        prog="python -m baselines.reading.train_readers",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--dataset", required=True, type=Path)
    p.add_argument("--head", required=True, type=published_or_path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--algo", choices=("ppo", "ppo_rnn"), default="ppo")
    p.add_argument("--env", default=ENV_ID, help=f"env id (default {ENV_ID}: any dataset)")
    p.add_argument(
        "--levels",
        type=int,
        default=None,
        help=f"zoom levels (default: the most the bundles were built for, up to {MAX_LEVELS})",
    )
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: train on fold I's train side (minus the validation share)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the stopped run in OUT/<algo> from its last checkpoint (its own config; the same command "
        "rerun without --resume continues it too)",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="train again: the run in OUT/<algo> (finished or not) is moved aside into OUT/<algo>/previous-N/",
    )
    p.add_argument("--action-mode", default="glimpse:1")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--total-steps", type=int, default=200_000, help="env steps per seed")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--read-budget", type=float, default=0.2)
    p.add_argument("--gain", default="log", choices=("log", "prob", "fidelity", "none"))
    p.add_argument("--final", type=float, default=1.0)
    p.add_argument("--read-cost", type=float, default=0.0)
    p.add_argument("--val-fraction", type=float, default=0.3)
    p.add_argument("--split-seed", type=int, default=0)
    p.add_argument("--skip-training", action="store_true", help="score the run already in OUT/<algo>")
    p.add_argument(
        "--compare",
        nargs=2,
        action="append",
        default=[],
        metavar=("NAME", "RUN"),
        help="navigation modes: another navigator scored beside on validation (repeatable)",
    )
    args = p.parse_args(argv)

    from baselines.reading import readers
    from histojax.reading import heads

    try:
        head = heads.load(args.head)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    navigator = is_navigator(args.action_mode)
    run_dir = args.out / args.algo
    if args.resume and not (run_dir / "checkpoint").is_dir():
        print(
            f"error: {run_dir}: no checkpoint to resume (no {run_dir / 'checkpoint'}); start the run without --resume",
            file=sys.stderr,
        )
        return 2
    try:
        if args.resume and (args.out / "dataset.json").is_file():
            data = args.out  # the split the stopped run trained on
        else:
            if not args.restart and not args.skip_training:
                same_split(args.out, run_dir, args.dataset, args.val_fraction, args.split_seed, args.fold)
            data = split_dataset(args.dataset, args.out, args.val_fraction, args.split_seed, args.fold)
        spec = json.loads((data / "dataset.json").read_text())
        levels = args.levels or dataset_levels(args.dataset, spec)
        warning = scale_warning(args.dataset, spec)
        if warning:
            print(warning, file=sys.stderr)
    except (HistojaxDataError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    if not args.skip_training:
        print(progress_words(args.gain, args.final, args.read_cost), flush=True)
        module = __import__(f"baselines.{args.algo}", fromlist=["main"])
        gain = None if args.gain == "none" else args.gain
        restore = with_head_reward(head, gain, args.final, args.read_cost)
        try:
            env_kwargs = {"dataset": str(data), "split": "train"}
            if args.env == READING_ID:  # any dataset: the levels its bundles were built for
                env_kwargs["n_levels"] = levels
            if not navigator:  # a navigator's episode reads what it stands on: no reading budget
                env_kwargs["read_budget"] = args.read_budget
            trainer_argv = (
                ["--resume", str(run_dir)]
                if args.resume
                else [
                    "--env",
                    args.env,
                    "--dataset",
                    str(data),
                    "--split",
                    "train",
                    "--action-mode",
                    args.action_mode,
                    "--obs",
                    "features",
                    "--seeds",
                    str(args.seeds),
                    "--total-steps",
                    str(args.total_steps),
                    "--num-envs",
                    str(args.num_envs),
                    "--set",
                    f"env_kwargs={json.dumps(env_kwargs)}",  # json-not-written (an option)
                    "--out",
                    str(run_dir),
                    *(["--restart"] if args.restart else []),
                    *extra,
                ]
            )
            before = _params_stamp(run_dir)
            code = module.main(trainer_argv)
        finally:
            restore()
        if code:
            return code
    if not args.skip_training and not (before is not None and _params_stamp(run_dir) == before):
        # written when the trainer trained; a finished run it did not train again keeps its record (and wall time)
        (run_dir / "head_reward.json").write_text(
            json.dumps(
                {
                    "head": str(args.head),
                    "head_name": head.name,
                    "gain": gain,
                    "final": args.final,
                    "read_cost": args.read_cost,
                    "read_budget": None if navigator else args.read_budget,
                    "action_mode": args.action_mode,
                    "train_wall_s": round(time.perf_counter() - t0, 1),
                    "dataset": str(data),
                    "validation_fraction": args.val_fraction,
                    "split_seed": args.split_seed,
                },
                indent=1,
                allow_nan=False,
            )
            + "\n"
        )
    if (run_dir / "log.json").is_file():
        seed_curve(run_dir, run_dir / "curve-seeds.png", run_dir / "curve-seeds.csv")
    t1 = time.perf_counter()
    if navigator:
        from baselines.reading import diagnosis

        code = diagnosis.main(
            [
                "--dataset",
                str(data / "validation-set"),
                "--head",
                str(args.head),
                "--split",
                "test",
                "--navigator",
                f"navigator ({args.algo}, head reward)",
                str(run_dir),
                *[a for name, r in args.compare for a in ("--navigator", name, r)],
                "--policy-seeds",
                str(args.seeds),
                "--out",
                str(args.out / "validation"),
                "--allow-fitting-slides",
            ]
        )  # the head saw them: compares readers, says so
        print(f"training {t1 - t0:.0f} s, scoring on validation {time.perf_counter() - t1:.0f} s")
        return code
    code = readers.main(
        [
            "--dataset",
            str(data / "validation-set"),
            "--head",
            str(args.head),
            "--split",
            "test",
            "--reader",
            f"set reader ({args.algo}, head reward)",
            str(run_dir),
            "--policy-seeds",
            str(args.seeds),
            "--out",
            str(args.out / "validation"),
            "--allow-fitting-slides",
        ]
    )  # the head was fitted on the whole train split: a warning says so
    print(f"training {t1 - t0:.0f} s, scoring on validation {time.perf_counter() - t1:.0f} s")
    return code


if __name__ == "__main__":
    raise SystemExit(main(compile_cache.setup(sys.argv[1:])))  # the persistent compilation cache, --no-compile-cache
