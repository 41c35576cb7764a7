"""Running a trainer: seeds vmapped (or sharded), updates in chunks with a runner state saved after each
(``RUN/checkpoint/``) so a stopped run resumes where it stopped, and the run's outputs at the end."""

from __future__ import annotations

import functools
import json
import math
import time
import weakref
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from baselines import outputs
from baselines.common.config import ConfigError, canonical_config
from baselines.common.devices import replicate_on
from baselines.common.env import random_agent_reference
from baselines.harness import run_folder
from baselines.harness.curves import plot_curves
from baselines.harness.logs import (
    _count,
    _tensorboard_scalars,
    finite_mean,
    save_checkpoint,
    smooth,
    tensorboard_writer,
    write_logs,
)
from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe

_PROGRAMS = weakref.WeakKeyDictionary()  # trainer -> its jitted programs, made once (each compiles once)


def _programs(trainer) -> dict:
    """The cache of ``trainer``'s jitted programs (``"seeds"``: :func:`run_seeds`'s; ``"chunked"``:
    :func:`chunked_runner`'s), kept as long as the trainer is."""
    return _PROGRAMS.setdefault(trainer, {})


def _place(trainer):
    """Arrays replicated on ``trainer.mesh``'s devices (a no-op without a mesh, and for arrays already placed
    there; slides sharded over the mesh, see histojax.sharding, stay as they are)."""
    mesh = getattr(trainer, "mesh", None)
    return (lambda x: x) if mesh is None else functools.partial(replicate_on, mesh)


def _checked(trainer, env_params):
    """``env_params`` (or the trainer's own when ``None``) checked against the trainer's env
    (:func:`histojax.registry.check_params`: a ``stride`` or step limit changed after ``make`` is named, not
    trained on)."""
    from histojax.registry import check_params

    p = trainer.env_params if env_params is None else env_params
    if getattr(trainer, "env", None) is not None:
        check_params(trainer.env, p, where="train: env params")
    return p


def train_seed(trainer, key, env_params, params) -> dict:
    """One seed's whole run (unjitted): the runner state of ``params`` and every update of it
    (:func:`scan_updates`): ``{"params", "metrics": {name: (num_updates,)}}``."""
    runner = trainer.init_runner(key, env_params, params)
    runner, metrics = scan_updates(
        lambda c, i: trainer.update(c, i, env_params), runner, 0, trainer.num_updates, trainer.num_updates
    )
    return {"params": trainer.runner_params(runner), "metrics": metrics}


def _seeds_program(trainer):
    """The jitted program of all seeds' runs: ``(keys, env_params) -> {"params", "metrics"}`` with the seeds on
    axis 0 (``jax.vmap`` over keys, or ``lax.map`` with ``config["vmap_seeds"] = False``)."""
    cache = _programs(trainer)
    if "seeds" not in cache:
        vmap_seeds = trainer.config["vmap_seeds"]

        def all_seeds(keys, p):
            # Initial parameters always via lax.map: jit(vmap(init)) of the orthogonal initialisers
            # (batched QR) never finished on jaxlib 0.10's CPU backend.
            params = jax.lax.map(lambda k: trainer.init_params(k, p), keys)
            one = functools.partial(train_seed, trainer)
            if vmap_seeds:
                return jax.vmap(one, in_axes=(0, None, 0))(keys, p, params)
            return jax.lax.map(lambda kq: one(kq[0], p, kq[1]), (keys, params))

        cache["seeds"] = jax.jit(all_seeds)
    return cache["seeds"]


def run_seeds(trainer, keys, env_params=None) -> dict:
    """Train ``len(keys)`` seeds of ``trainer`` (a :class:`~baselines.harness.trainer.Trainer`) in one jitted
    program on ``env_params`` (default: the trainer's): ``{"params": seeds-stacked params, "metrics": {name:
    (seeds, num_updates)}}``. With a mesh (``devices=N``) the keys and env params are placed replicated on its
    devices; the trainer shards the env batch itself."""
    place = _place(trainer)
    trainer.progress.t0 = time.perf_counter()
    return _seeds_program(trainer)(place(keys), place(_checked(trainer, env_params)))


def compile_seeds(trainer, keys, env_params=None):
    """:func:`run_seeds`'s program compiled ahead of time for ``keys``: ``call(keys, env_params=None)`` runs it
    (``call.exe``: the ``jax.stages.Compiled``, e.g. for ``.as_text()`` or ``.memory_analysis()``)."""
    place = _place(trainer)
    params = place(_checked(trainer, env_params))
    exe = _seeds_program(trainer).lower(place(keys), params).compile()

    def call(keys, p=None):
        """Run the compiled program for ``keys`` on ``p`` (default: the env params it was compiled with)."""
        trainer.progress.t0 = time.perf_counter()
        return exe(place(keys), params if p is None else place(_checked(trainer, p)))

    call.exe = exe
    return call


# ----------------------------------------------------------------------------- chunks, checkpoints, resume
CHECKPOINT_DIR = "checkpoint"  # RUN/checkpoint/: runner.msgpack, checkpoint.json, config.json


RUNNER_FORMAT = 1


def chunk_plan(num_updates: int, every: int | None) -> tuple[int, int]:
    """``(chunk, n_chunks)``: a run of ``num_updates`` updates split into ``n_chunks`` chunks of ``chunk``
    updates, checkpointed after each; ``chunk`` ≤ ``every`` (``None`` or ≤ 0: one chunk), the chunks as
    even as they can be (``n_chunks × chunk − num_updates < n_chunks`` updates of the last chunk are skipped)."""
    every = num_updates if every is None or every <= 0 else min(int(every), num_updates)
    n_chunks = -(-num_updates // every)
    return -(-num_updates // n_chunks), n_chunks


def scan_updates(update, carry, first_update, n_updates: int, num_updates: int | None):
    """The one loop over updates: ``lax.scan`` of ``update(carry, i) -> (carry, metrics)`` over
    ``i = first_update + arange(n_updates)``. An ``i ≥ num_updates`` is skipped (``lax.cond``: the carry is
    kept, its metrics are NaN), so the last, shorter chunk of a run runs in the same compiled program as the
    others; when no ``i`` can reach ``num_updates`` (``first_update`` a Python int and ``first_update +
    n_updates ≤ num_updates``, or ``num_updates=None``) each update runs unconditioned."""

    def skip(c, i):
        shapes = jax.eval_shape(update, c, i)[1]
        return c, jax.tree.map(
            lambda s: jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.inexact) else 0, s.dtype), shapes
        )

    def body(c, i):
        return jax.lax.cond(i < num_updates, update, skip, c, i)

    never_skips = num_updates is None or (isinstance(first_update, int) and first_update + n_updates <= num_updates)
    return jax.lax.scan(update if never_skips else body, carry, first_update + jnp.arange(n_updates))


def chunked_runner(train):
    """The run of ``train`` (a :class:`~baselines.harness.trainer.Trainer`, or any object with its
    ``init_params``, ``init_runner``, ``update``, ``runner_params``, ``config``, ``num_updates`` and
    ``env_params``) in chunks of ``config["checkpoint_every"]`` updates (:func:`chunk_plan`): ``start(keys)``
    → the seeds' runner states (params, optimizer state, env state, observation, key; seeds on axis 0);
    ``chunk(runners, first_update)`` → ``(runners, metrics (seeds, chunk))``, compiled once (ahead of time,
    on the first call; ``chunk.compile_seconds``). Seeds are vmapped (or ``lax.map``-ed with
    ``vmap_seeds=False``) as in :func:`run_seeds`. Made once per trainer (the same pair back again)."""
    cache = _programs(train)
    if "chunked" in cache:
        return cache["chunked"]
    config = train.config
    size, _ = chunk_plan(train.num_updates, config.get("checkpoint_every"))
    place = _place(train)
    env_params = place(_checked(train, None))

    def start_all(keys, p):
        params = jax.lax.map(lambda k: train.init_params(k, p), keys)  # lax.map: see run_seeds
        if config["vmap_seeds"]:
            return jax.vmap(train.init_runner, in_axes=(0, None, 0))(keys, p, params)
        return jax.lax.map(lambda kp: train.init_runner(kp[0], p, kp[1]), (keys, params))

    def chunk_all(runners, p, first):
        def one(r):
            return scan_updates(lambda c, i: train.update(c, i, p), r, first, size, train.num_updates)

        if config["vmap_seeds"]:
            return jax.vmap(one)(runners)
        return jax.lax.map(one, runners)

    start_jit, chunk_jit = jax.jit(start_all), jax.jit(chunk_all)
    compiled = {}

    def start(keys):
        return start_jit(place(keys), env_params)

    def template(keys):
        """The runner states' structure, shapes and dtypes (``jax.eval_shape``; nothing runs)."""
        return jax.eval_shape(start_all, place(keys), env_params)

    def chunk(runners, first_update: int):
        first = jnp.asarray(first_update, jnp.int32)
        if "exe" not in compiled:
            t0 = time.perf_counter()
            compiled["exe"] = chunk_jit.lower(runners, env_params, first).compile()
            chunk.compile_seconds = time.perf_counter() - t0
        return compiled["exe"](runners, env_params, first)

    chunk.compile_seconds = 0.0  # the compile of the first call, seconds
    start.template, start.size = template, size
    cache["chunked"] = start, chunk
    return start, chunk


def save_runner(
    folder: Path, runners, update: int, metrics: dict, train_seconds: float, config: dict, num_updates: int, chunk: int
) -> Path:
    """Write a run's state after ``update`` updates into ``folder`` (``RUN/checkpoint``): ``runner.msgpack``
    (flax msgpack: every array of the seeds' runner states, the metrics so far, the update index), then
    ``checkpoint.json`` (a summary for people). Each file atomically; the msgpack holds all that
    :func:`load_runner` needs, so a run killed between the two resumes from the msgpack."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    leaves = jax.tree.leaves(jax.device_get(runners))
    state = {
        "format": RUNNER_FORMAT,
        "update": int(update),
        "num_updates": int(num_updates),
        "chunk": int(chunk),
        "config_sha256": config_digest(config),
        "train_seconds": float(train_seconds),
        "leaves": {str(i): np.asarray(a) for i, a in enumerate(leaves)},
        "metrics": {k: np.asarray(v) for k, v in metrics.items()},
    }
    path = outputs.write_bytes(folder / "runner.msgpack", serialization.msgpack_serialize(state))
    outputs.write_text(
        folder / "checkpoint.json",
        json.dumps(
            {
                "update": int(update),
                "num_updates": int(num_updates),
                "checkpoint_every": int(chunk),
                "train_seconds": round(float(train_seconds), 3),
                "saved": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "resume": f"histojax train --algo {config.get('algo', 'ppo')} --resume {folder.parent}",
            },
            indent=1,
            allow_nan=False,
        ),
    )
    return path


def config_digest(config: dict) -> str:
    """SHA-256 of a run config (JSON, keys sorted): ties a checkpoint to the run that wrote it."""
    import hashlib

    text = json.dumps(config, sort_keys=True, default=str)  # json-not-written (a hash)
    return hashlib.sha256(text.encode()).hexdigest()


def load_runner(folder: Path, template, num_updates: int, chunk: int, config: dict | None = None):
    """``(runners, update, metrics, train_seconds)`` from ``folder/runner.msgpack`` (:func:`save_runner`),
    checked against ``template`` (:func:`chunked_runner`'s ``start.template``: the runner states this config
    makes) and the run's ``num_updates`` / ``chunk``. A missing, corrupt or mismatching file raises
    HistojaxDataError naming it."""
    path = Path(folder) / "runner.msgpack"
    try:
        state = serialization.msgpack_restore(run_folder.read_own(path, "checkpoint"))  # never a FIFO or a link
    except HistojaxDataError:
        raise
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the run's checkpoint ({e.strerror or e}); nothing to resume") from e
    except Exception as e:  # msgpack's errors share no base
        raise HistojaxDataError(path, f"not a readable checkpoint, truncated or corrupt ({e})") from e
    if not isinstance(state, dict) or state.get("format") != RUNNER_FORMAT or "leaves" not in state:
        raise HistojaxDataError(path, f"not a histojax training checkpoint (no runner state of format {RUNNER_FORMAT})")
    ints = {k: state.get(k) for k in ("update", "num_updates", "chunk")}
    seconds, leaves, metrics = state.get("train_seconds"), state["leaves"], state.get("metrics")
    if (
        any(type(v) is not int for v in ints.values())
        or not 0 <= ints["update"] <= ints["num_updates"]
        or type(seconds) not in (int, float)
        or not math.isfinite(seconds)
        or not isinstance(leaves, dict)
        or not isinstance(metrics, dict)
        or any(np.ndim(v) != 2 or np.shape(v)[1] != ints["update"] for v in metrics.values())
    ):  # a crafted or damaged file: never a KeyError or a NumPy shape error further on
        raise HistojaxDataError(
            path, "its update counts, time, arrays or metrics are missing or of the wrong kind (damaged); train again"
        )
    if config is not None and state.get("config_sha256") != config_digest(config):
        raise HistojaxDataError(
            path,
            f"written by a run of another config than {Path(folder) / 'config.json'} (a new "
            "run started in this folder before its first checkpoint?); train again",
        )
    if (state["num_updates"], state["chunk"]) != (num_updates, chunk):
        raise HistojaxDataError(
            path,
            f"saved for {state['num_updates']} updates in chunks of {state['chunk']}, "
            f"but the run's config.json makes {num_updates} in chunks of {chunk}",
        )
    want, treedef = jax.tree.flatten(template)
    got = [state["leaves"].get(str(i)) for i in range(len(want))]
    if len(state["leaves"]) != len(want) or any(
        g is None or tuple(np.shape(g)) != tuple(w.shape) or np.asarray(g).dtype != w.dtype for g, w in zip(got, want)
    ):
        raise HistojaxDataError(
            path,
            "its arrays do not match the runner state of the run's config.json "
            "(another trainer, network or env); train again",
        )
    return (
        jax.tree.unflatten(treedef, [jnp.asarray(g) for g in got]),
        int(state["update"]),
        {k: np.asarray(v) for k, v in state["metrics"].items()},
        float(state["train_seconds"]),
    )


def run_chunked(train, out: Path, keys=None, resume: bool = False, on_checkpoint=None):
    """Run ``train`` in chunks (:func:`chunked_runner`), writing ``out/checkpoint/`` after each
    (:func:`save_runner`; the run's config in ``out/checkpoint/config.json`` first) and TensorBoard scalars
    into ``out`` when tensorboardX is installed. ``resume``: continue from ``out/checkpoint`` (same config);
    the result equals the uninterrupted run's bit for bit (the same compiled chunk on the same states).
    ``on_checkpoint(update)`` is called after each checkpoint. Returns ``({"params", "metrics"},
    compile seconds, train seconds)`` with metrics ``(seeds, num_updates)``."""
    out, config, num_updates = Path(out), train.config, train.num_updates
    folder = out / CHECKPOINT_DIR
    keys = jax.random.split(jax.random.PRNGKey(config.get("seed", 0)), config["num_seeds"]) if keys is None else keys
    start, chunk = chunked_runner(train)  # made once per trainer: the chunk compiles once
    if resume:
        runners, done, metrics, train_s = load_runner(folder, start.template(keys), num_updates, start.size, config)
        print(f"resuming {out} at update {done}/{num_updates}", flush=True)
        compile_s = 0.0
    else:
        folder.mkdir(parents=True, exist_ok=True)
        outputs.write_text(
            folder / "config.json", json.dumps(json_safe(config), indent=2, default=str, allow_nan=False)
        )
        t0 = time.perf_counter()
        runners = jax.block_until_ready(start(keys))
        compile_s, train_s, done, metrics = time.perf_counter() - t0, 0.0, 0, {}
    writer = tensorboard_writer(out) if jax.process_index() == 0 else None
    try:
        while done < num_updates:
            t0, compiled_before = time.perf_counter(), chunk.compile_seconds
            runners, m = chunk(runners, done)
            m = jax.block_until_ready(m)
            compiled_now = chunk.compile_seconds - compiled_before  # > 0 on the first call only
            compile_s += compiled_now
            train_s += time.perf_counter() - t0 - compiled_now
            n = min(start.size, num_updates - done)  # the last chunk's skipped updates are dropped
            m = {k: np.asarray(v)[:, :n] for k, v in jax.device_get(m).items()}
            if writer is not None:
                _tensorboard_scalars(writer, m, done, train.steps_per_update)
            metrics = {k: np.concatenate([metrics[k], v], axis=1) if k in metrics else v for k, v in m.items()}
            done += n
            save_runner(folder, runners, done, metrics, train_s, config, num_updates, start.size)
            if on_checkpoint is not None:
                on_checkpoint(done)
    finally:
        if writer is not None:
            writer.close()
    return {"params": train.runner_params(runners), "metrics": metrics}, compile_s, train_s


def finish_run(
    algo: str,
    config: dict,
    out: Path,
    params,
    metrics: dict,
    steps_per_update: int,
    train_seconds: float,
    compile_seconds: float,
    env_and_params=None,
) -> dict:
    """Logs, curve, checkpoint and a printed summary (shared by PPO and DQN). ``env_and_params``:
    the trainer's, for the random-agent reference of slides sharded over devices."""
    metrics = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
    n_updates = metrics["success"].shape[1]
    steps = (np.arange(n_updates) + 1) * steps_per_update
    k = max(1, n_updates // 40)  # smooth over ~1/40 of the run for the curve and the final figure
    tail = slice(max(0, n_updates - k), None)
    final = {name: finite_mean(metrics[name][:, tail]) for name in ("return", "success", "length", "steps_to_success")}
    final_per_seed = {name: finite_mean(metrics[name][:, tail], axis=1).tolist() for name in ("return", "success")}
    ref = random_agent_reference(config, env_and_params=env_and_params)
    summary = {
        "algo": algo,
        "env_id": config["env_id"],
        "env_steps_per_seed": int(steps[-1]),
        "seeds": int(metrics["success"].shape[0]),
        "train_seconds": train_seconds,
        "compile_seconds": compile_seconds,
        "env_steps_per_second_all_seeds": float(steps[-1] * metrics["success"].shape[0] / train_seconds),
        "final_window_updates": k,
        "final": final,
        "final_per_seed": final_per_seed,
        "random_agent": ref,
    }
    panels = {
        "mean return": smooth(metrics["return"], k),
        "success rate": smooth(metrics["success"], k),
        "mean steps to success": smooth(metrics["steps_to_success"], k),
    }
    title = (
        f"{algo.upper()} on {config['env_id']} ({config['action_mode']}, obs {config['obs_mode']}"
        f"{' + position' if config['with_position'] else ''}), {_count(metrics['success'].shape[0], 'seed')}"
    )
    # the run's files as a whole: on a full disk (the error names the file) the previous run's stay together
    with outputs.staged() as stage:
        write_logs(out, steps, metrics, summary, stage=stage)
        with stage.writing(out / "curve.png") as tmp:
            plot_curves(
                tmp,
                steps,
                panels,
                title=title,
                reference={"mean return": ref["return"], "success rate": ref["success"]},
            )
        save_checkpoint(out, params, config, stage=stage)
    from baselines.reading.provenance import write_run_record

    write_run_record(out, config)  # the slides it trained and validated on: every scorer refuses them unasked
    print(
        f"\n{algo} {config['env_id']}: {steps[-1]:,} env steps/seed x {summary['seeds']} seeds in "
        f"{train_seconds:.0f} s (+{compile_seconds:.0f} s compile), "
        f"{summary['env_steps_per_second_all_seeds']:,.0f} env steps/s"
    )
    print(
        f"final (last {k} updates, training policy): return {final['return']:.3f}  success {final['success']:.1%}  "
        f"mean length {final['length']:.1f}  steps to success {final['steps_to_success']:.1f}"
    )
    print(f"random agent: return {ref['return']:.3f}  success {ref['success']:.1%}")
    print(f"wrote {out}/log.csv, log.json, curve.png, params.msgpack, config.json, slides_seen.json")
    return summary


def resume_config(run: Path, algo: str, config_class=None):
    """The config of the run to resume in folder ``run`` (``run/checkpoint/config.json``, written when it
    started): its dict, or typed as ``config_class`` (e.g. :class:`~baselines.ppo.PPOConfig`) when given. A missing
    or unreadable file, another trainer's run, or (typed) an entry the trainer has not or of the wrong type raises
    HistojaxDataError naming it."""
    path = Path(run) / CHECKPOINT_DIR / "config.json"
    try:  # the run's own regular file: a FIFO would block the read, a link may point anywhere
        config = json.loads(run_folder.read_own(path, "config", run_folder.MAX_CONFIG_BYTES).decode("utf-8"))
    except OSError as e:
        raise HistojaxDataError(
            path,
            f"cannot read the run's config ({e.strerror or e}): not a run started with checkpoints, nothing to resume",
        ) from e
    except (ValueError, RecursionError) as e:  # RecursionError: arrays nested deeper than the parser recurses
        raise HistojaxDataError(path, f"not valid JSON, truncated or corrupt ({e})") from None
    if not isinstance(config, dict):
        raise HistojaxDataError(path, "not a run config (a JSON object)")
    if config.get("algo", algo) != algo:
        raise HistojaxDataError(path, f"a {config['algo']} run; resume it with --algo {config['algo']}")
    if config_class is None:
        return canonical_config(config)
    try:
        return config_class.from_dict(config, where=str(path))
    except ConfigError as e:
        raise HistojaxDataError(path, e.detail) from None


def compile_and_run(train, keys) -> tuple[dict, float, float]:
    """Compile ``train`` (a :class:`~baselines.harness.trainer.Trainer`) ahead of time for ``keys``
    (:func:`compile_seeds`) and run it once: ``(result, compile seconds, run seconds)``, the run timed to
    completion (``block_until_ready``)."""
    t0 = time.perf_counter()
    compiled = compile_seeds(train, keys)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = jax.block_until_ready(compiled(keys))
    return result, compile_s, time.perf_counter() - t0


def seeds_line(algo: str, config: dict, num_updates: int, steps_per_update: int, unit: str = "updates") -> str:
    """The first line a training prints: how many seeds it trains (``--seeds``, default 4) and that the env steps
    (``--total-steps``) are per seed, with the total over the seeds, e.g. ``PPO on HistoJAX-Easy-v0: 4 seeds
    (--seeds), 65,536 env steps each (--total-steps is per seed; 262,144 in all): 32 updates x 2,048 env steps``."""
    seeds, per = int(config["num_seeds"]), int(num_updates) * int(steps_per_update)
    each = " each" if seeds != 1 else ""
    return (
        f"{algo.upper()} on {config['env_id']}: {seeds} seed{'s' if seeds != 1 else ''} (--seeds), {per:,} env "
        f"steps{each} (--total-steps is per seed; {seeds * per:,} in all): {num_updates} {unit} x "
        f"{steps_per_update:,} env steps"
    )


def run_and_save(
    algo: str, make_train_fn, config, out: Path, unit: str = "updates", resume: bool = False, on_checkpoint=None
):
    """Make, compile and run the trainer for ``config`` (its typed config, or a dict ``make_train_fn`` makes one of;
    all seeds in one program, compile time measured apart), then :func:`finish_run` into ``out``. On one process
    the run goes in chunks and saves its whole state to ``out/checkpoint/`` every ``checkpoint_every`` updates
    (:func:`run_chunked`); ``resume`` continues from there. On several it is one program (:func:`compile_seeds`).
    Returns ``(config, params, summary)`` with the trainer's full config (its record, ``config.json``'s dict)."""
    train = make_train_fn(config)
    config = train.config
    if config.get("shard_slides"):
        from histojax.sharding import device_bytes, local_slides

        n, nbytes = local_slides(train.env_params.slide)
        per = device_bytes(train.env_params.slide)
        print(
            f"process {jax.process_index()} of {jax.process_count()}: {n} slide(s), {nbytes:,} bytes of slide arrays "
            f"on its {len(per)} device(s), {max(per.values()):,} on each",
            flush=True,
        )
    keys = jax.random.split(jax.random.PRNGKey(config.get("seed", 0)), config["num_seeds"])
    chunked = jax.process_count() == 1
    if resume and not chunked:
        raise ValueError(f"{algo} runs on several processes cannot resume (no checkpoints along the way)")
    if chunked:
        chunk, n_chunks = chunk_plan(train.num_updates, config.get("checkpoint_every"))
        print(
            f"{seeds_line(algo, config, train.num_updates, train.steps_per_update, unit)}, checkpoint every {chunk} "
            f"{unit} in {out}/{CHECKPOINT_DIR}; compiling ...",
            flush=True,
        )
        result, compile_s, train_s = run_chunked(train, out, keys, resume=resume, on_checkpoint=on_checkpoint)
    else:
        print(f"{seeds_line(algo, config, train.num_updates, train.steps_per_update, unit)}; compiling ...", flush=True)
        result, compile_s, train_s = compile_and_run(train, keys)
    if jax.process_index() > 0:  # several processes: process 0 writes the run, the others their parameters
        save_checkpoint(out / f"process-{jax.process_index()}", result["params"], config)
        print(
            f"process {jax.process_index()}: {train_s:.1f} s; wrote {out}/process-{jax.process_index()}/params.msgpack"
        )
        return config, result["params"], None
    summary = finish_run(
        algo,
        config,
        out,
        result["params"],
        result["metrics"],
        train.steps_per_update,
        train_s,
        compile_s,
        env_and_params=(train.env, train.env_params),
    )
    return config, result["params"], summary
