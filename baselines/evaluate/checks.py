"""Checks on what is scored, each a warning or a one-line refusal: ``config.json`` keys and values, the
parameter tree, the slides scored against those trained on (split, scale), retired published agents and
slide head folders given as agents, flat glimpse policies on slides too large for their grid, and the slide
head a reader names."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np

from baselines.published_agents import PUBLISHED
from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError
from data_tools.metrics import UNDEFINED


def check_config(config, path) -> list[str]:
    """Refuse a ``config.json`` that is not an object or whose ``hidden`` is not a positive whole number, or a value
    of the wrong type (``HistojaxDataError`` naming ``path``); return one warning per key no trainer writes (a
    misspelling is otherwise ignored without a word), naming the closest known key
    (:func:`baselines.run_config.read_run_config`'s checks)."""
    warnings: list[str] = []
    read_run_config(config, path, warnings)
    return warnings


def one_class(env_params) -> int | None:
    """The one slide label (0 normal, 1 tumour) when every slide of ``env_params`` has it, else None."""
    if getattr(env_params.slide, "slide_label", None) is None:
        return None
    labels = np.asarray(jax.device_get(env_params.slide.slide_label)).ravel()
    return int(labels[0]) if labels.size and len(set(labels.tolist())) == 1 else None


def undefined_figures(rows: dict, task: str, single: int | None) -> dict:
    """``rows`` with the figures one class of slides cannot define set to None (printed :data:`UNDEFINED`, written
    ``null``): the diagnosis AUCs when every slide is of one class; a detection run's success rate and steps to
    success when no slide has tumour (no target exists to reach)."""
    if single is None:
        return rows
    for row in rows.values():
        for r in [row, *row.get("per_seed", [])]:
            for key in ("diagnosis_auc", "diagnosis_auc_no_itc"):
                if key in r:
                    r[key] = None
            if task != "classification" and single == 0:
                r["success_rate"] = None
                r["mean_steps_to_success"] = None
                if "success_rate_per_seed" in r:
                    r["success_rate_per_seed"] = [None] * len(r["success_rate_per_seed"])
    return rows


def split_warnings(env, env_params, task: str, where: str) -> list[str]:
    """Why a set of slides cannot be scored: a diagnosis needs tumour and normal slides for an AUC; detection
    needs a slide with tumour (no target can be reached on the others)."""
    single = one_class(env_params)
    if single is None:
        return []
    n = np.asarray(jax.device_get(env_params.slide.slide_label)).size
    if task == "classification":
        kind = "tumour" if single else "normal"
        return [
            f"{where}: all {n} slide{'s' if n > 1 else ''} {'are' if n > 1 else 'is'} {kind}: the diagnosis AUC "
            f"is {UNDEFINED} (it needs tumour and normal slides); only the accuracy of the declared diagnosis "
            "means something"
        ]
    if not single:
        return [
            f"{where}: no slide here has tumour annotated: no policy can reach a target, so the success rate is "
            f"{UNDEFINED} (normal slides only); score a split with tumour slides"
        ]
    return []


def _dataset_record(folder) -> dict:
    try:
        record = json.loads((Path(folder) / "dataset.json").read_text())
        return record if isinstance(record, dict) else {}
    except (OSError, ValueError):
        return {}


def provenance_warnings(trained: dict, scored: dict, config_path) -> list[str]:
    """Warnings when a checkpoint is scored on slides it trained on, or at another scale than it trained at,
    from what its ``config.json`` records (``trained``: env_kwargs ``dataset`` and ``split``) and the
    ``dataset.json`` of the set scored (``scored``: the evaluation's config)."""
    trained, scored = read_run_config(trained), read_run_config(scored)
    t_kw, s_kw = trained.env_kwargs or {}, scored.env_kwargs or {}
    t_ds, s_ds = t_kw.get("dataset"), s_kw.get("dataset")
    if not t_ds or not s_ds:
        return []
    t_split, s_split = t_kw.get("split", "train"), s_kw.get("split", "train")
    overlap = s_split == "all" or t_split == "all" or s_split == t_split
    t_rec, s_rec = _dataset_record(t_ds), _dataset_record(s_ds)
    same = Path(t_ds).resolve() == Path(s_ds).resolve()
    c16 = lambda rec, env_id="": "CAMELYON16" in str(rec.get("kind", "")) or "-C16-" in env_id  # noqa: E731
    out = []
    if overlap and (same or (c16(s_rec) and c16(t_rec, str(trained.env_id)))):
        why = (
            "the same dataset"
            if same
            else (
                "a CAMELYON16 set: its split is fixed by slide, so its "
                f"{s_split} split holds slides this agent trained on"
            )
        )
        out.append(
            f"{config_path}: trained on the {t_split} split of {t_ds}; scored on the {s_split} split of "
            f"{s_ds} ({why}): these figures are not held-out; score --split test"
        )
    t_mpp, s_mpp = dataset_mpp(t_rec), dataset_mpp(s_rec)
    if t_mpp and s_mpp and abs(float(t_mpp) - float(s_mpp)) > SCALE_TOLERANCE * float(t_mpp):
        out.append(
            f"{config_path}: trained at {float(t_mpp):.3g} µm/px ({t_ds}); scored at {float(s_mpp):.3g} µm/px "
            f"({s_ds}): another scale than it trained at"
        )
    elif s_mpp and not t_rec and c16(s_rec):
        out.append(
            f"{config_path}: its training dataset {t_ds} is not here and config.json records no scale, so the "
            f"scale cannot be checked: {s_ds} is at {float(s_mpp):.3g} µm/px ({s_rec.get('variant', '?')} "
            "variant); the published C16 agents (c16-v1-* and c16-v2-*) trained on the full set (1.94 µm/px)"
        )
    t_enc, s_enc = t_rec.get("encoder"), s_rec.get("encoder")
    if t_enc and s_enc and not same_encoder(t_enc, s_enc):
        out.append(
            f"{config_path}: trained on {t_enc} features ({t_ds}); {s_ds} holds {s_enc} features: another "
            "encoder than it trained on"
        )
    return out


SCALE_TOLERANCE = 0.05
"""Two datasets whose µm per level-0 px differ by more than this share are at another scale (slides of one scanner
differ by a percent or two; the C16 variants by factors of 2 and 4)."""


def dataset_mpp(record: dict) -> float | None:
    """The µm per level-0 px of a ``dataset.json`` record: its ``scale.mpp`` (``histojax c16``), else the median of its
    slides' ``mpp`` (``histojax dataset`` records each slide's); None when it records none."""
    scale = record.get("scale") if isinstance(record.get("scale"), dict) else {}
    mpp = scale.get("mpp")
    if isinstance(mpp, (int, float)) and not isinstance(mpp, bool) and mpp > 0:
        return float(mpp)
    slides = record.get("slides") if isinstance(record.get("slides"), list) else []
    each = [
        float(r["mpp"])
        for r in slides
        if isinstance(r, dict)
        and isinstance(r.get("mpp"), (int, float))
        and not isinstance(r.get("mpp"), bool)
        and r["mpp"] > 0
    ]
    return float(np.median(each)) if each else None


def same_encoder(a, b) -> bool:
    """Whether two recorded encoder names (a dataset's, a head's, a bundle's) name one encoder: equal, or features
    imported from ``.h5`` files where either record names only the family (``imported``, or one slide's file
    ``imported:NAME.h5`` as older imports recorded) and so cannot tell two imports apart
    (:func:`histojax.reading.heads.same_encoder`)."""
    from histojax.reading.heads import same_encoder as same

    return same(a, b)


def trained_record_warnings(run, scored: dict, config_path) -> list[str]:
    """Warnings when a published agent (its ``published.json``'s ``trained_on``: ``mpp``, ``encoder``) is scored on
    a dataset (``scored``: the evaluation's config; its ``env_kwargs.dataset``'s ``dataset.json``) at another scale
    (µm/px) or of another encoder than it trained on; the published config.json names no dataset path, so
    :func:`provenance_warnings` cannot compare them. ``[]`` when the record or the dataset says nothing."""
    where = published_trained_record(Path(run)) if run is not None else None
    s_ds = (read_run_config(scored).env_kwargs or {}).get("dataset")
    if not where or not s_ds:
        return []
    s_rec = _dataset_record(s_ds)
    t_mpp, s_mpp = where.get("mpp"), dataset_mpp(s_rec)
    named = f"{where['dataset']!r}" if isinstance(where.get("dataset"), str) else "its training dataset"
    out = []
    try:
        t_mpp, s_mpp = (None if v is None else float(v) for v in (t_mpp, s_mpp))
    except (TypeError, ValueError):
        t_mpp = s_mpp = None
    if t_mpp and s_mpp and abs(t_mpp - s_mpp) > SCALE_TOLERANCE * t_mpp:
        out.append(
            f"{config_path}: a published agent trained at {t_mpp:.3g} µm/px ({named}, its published.json); "
            f"scored at {s_mpp:.3g} µm/px ({s_ds}): another scale than it trained at, so its cells, views and "
            "reading budget hold other tissue (score it on a dataset at its scale)"
        )
    t_enc, s_enc = where.get("encoder"), s_rec.get("encoder")
    if isinstance(t_enc, str) and isinstance(s_enc, str) and not same_encoder(t_enc, s_enc):
        out.append(
            f"{config_path}: a published agent trained on {t_enc} features ({named}, its published.json); "
            f"{s_ds} holds {s_enc} features: another encoder than it trained on"
        )
    return out


def encoder_refusal(config: dict, config_path) -> str | None:
    """Why an agent of an id that observes one encoder's features (the C16 -v1 / -v2 ids: pcam-cnn) cannot score
    the dataset in ``config`` (its ``env_kwargs.dataset``), or None: the dataset's ``dataset.json`` records other
    features (or none). One line naming the agent's config, the dataset file and what to build; said before any
    network is loaded, instead of the parameter shapes that would not fit."""
    from histojax import registry
    from histojax.reading.heads import same_encoder

    config = read_run_config(config)
    env_id = config.env_id
    want = registry.spec_of(env_id).settings.get("dataset_encoder") if env_id in registry.registered_envs() else None
    what = f"observes {want} features"
    if not want and config_path is not None:  # an id of any encoder: the head it scores through reads one
        want = _head_encoder(Path(config_path).parent)
        what = f"scores what it reads through a slide head of {want} features (its head_reward.json)"
    dataset = (config.env_kwargs or {}).get("dataset")
    if not want or not dataset or config.obs_mode != "features":
        return None
    index = Path(dataset) / "dataset.json"
    try:
        have = json.loads(index.read_text()).get("encoder")
    except (OSError, ValueError, AttributeError):
        return None
    if have == want or (have and same_encoder(have, want)) or (not have and what.startswith("scores")):
        return None  # a dataset that records no encoder: the head's own check names what its bundles hold
    return (
        f"{config_path}: this agent ({config.env_id}) {what}; {index} holds "
        f"{'no feature grids' if not have else repr(have) + ' features'}: score it on a dataset built with "
        f"--encoder {want} (e.g. `python -m data_tools c16 ... --features`), or train an agent on these features"
    )


# ----------------------------------------------------------------------------- published readers
SET_READER = "c16-v2-set-reader"  # the published cell-set reader: reads slides of any size


# published folders retired, with what replaced them: `histojax evaluate` on the old path names the new one
RETIRED = {
    "c16-v1-glimpse-reader": (
        SET_READER,
        "a flat glimpse policy over a padded 16 × 14 cell grid, it could "
        "not read a slide wider or taller than that grid",
    )
}


def published_path(name: str) -> Path:
    """``baselines/published/NAME``, relative to the working folder when it lies under it."""
    path = PUBLISHED / name
    try:
        return path.relative_to(Path.cwd())
    except ValueError:
        return path


def is_published(run: Path) -> bool:
    """Whether the run folder ``run`` is a published agent: inside ``baselines/published`` or holding the
    ``published.json`` that ``python -m baselines.publish`` writes."""
    run = Path(run)
    try:
        inside = run.resolve().is_relative_to(PUBLISHED.resolve())
    except OSError:
        inside = False
    return inside or (run / "published.json").is_file()


def published_trained_record(run: Path) -> dict | None:
    """The ``trained_on`` object of a published agent's ``published.json``, or None when there is none (or the
    file cannot be read)."""
    try:
        record = json.loads((Path(run) / "published.json").read_text())
    except (OSError, ValueError):
        return None
    where = record.get("trained_on") if isinstance(record, dict) else None
    return where if isinstance(where, dict) else None


def published_trained_on(where: dict | None) -> str | None:
    """What a published agent's ``trained_on`` record (:func:`published_trained_record`) says it trained on
    (``what``, else the dataset's name and split), or None when it names nothing (or there is none)."""
    if where is None:
        return None
    if isinstance(where.get("what"), str) and where["what"]:
        return where["what"]
    if isinstance(where.get("dataset"), str):
        return f"the {where.get('split', 'train')} split of a dataset named {where['dataset']!r}"
    return None


def published_dataset_refusal(run: Path, config: dict) -> str | None:
    """Why a published agent (:func:`is_published`) is not scored without ``--dataset``, as one line naming its
    ``config.json``, the dataset it needs and how to build one; None for any other run. The dataset path its
    ``config.json`` records (``env_kwargs.dataset``) is the machine it was trained on: kept as provenance, never
    used unasked, even when a folder of that name exists here (it may hold other slides, another split or
    scale)."""
    from histojax import registry

    if not is_published(run):
        return None
    config = read_run_config(config)
    recorded = (config.env_kwargs or {}).get("dataset")
    where = published_trained_record(run)  # published.json's trained_on, read once
    env_id = str(config.env_id)
    encoder = (
        registry.spec_of(env_id).settings.get("dataset_encoder") if env_id in registry.registered_envs() else None
    ) or "the same"
    if recorded and not (Path(str(recorded)) / "dataset.json").is_file():
        said = (
            f"records the dataset it trained on as {recorded}, which does not exist here (a folder of the machine it "
        )
        said += "was trained on)"
    elif recorded:
        said = (
            f"records the dataset it trained on as {recorded} (a folder of the machine it was trained on, kept as "
            "provenance: a published agent is never scored on it unasked)"
        )
    elif isinstance(trained_on := published_trained_on(where), str):
        said = f"records no path of the machine it was trained on; its published.json says it trained on {trained_on}"
    else:
        said = "records no dataset"
    if encoder == "the same":  # an any-dataset id: the features its head reads (head_reward.json names the head)
        encoder = _head_encoder(run) or encoder
    trained_on_c16 = str((where or {}).get("dataset", "")).startswith("c16")
    if "-C16-" in env_id or trained_on_c16:  # a C16 set is what to build, whatever the env id
        need = (
            f"a CAMELYON16 dataset with {encoder} feature grids, e.g. the small one (6 slides, about a minute: "
            "`histojax c16 --small --features --out c16-small`) or the true-scale set it trained on (`histojax c16 "
            "--out c16-full --annotations ... --patches ... --features`; docs/c16-benchmark.md#build-it)"
        )
    else:
        need = (
            f"a dataset with {encoder} features of the kind it trained on (`histojax dataset SLIDES --out DIR "
            "--encoder NAME`; docs/your-own-slides.md)"
        )
    return f"{Path(run) / 'config.json'}: a published agent; its config.json {said}: give --dataset DIR, {need}"


def _head_encoder(run: Path) -> str | None:
    """The encoder of the slide head named in the agent's ``head_reward.json`` (:func:`head_reward_settings`,
    :func:`resolve_head`); None without one, or when it cannot be read."""
    try:
        record, where = head_reward_settings(Path(run), {})
        if record is None:
            return None
        encoder = json.loads((resolve_head(record["head"], Path(run), where) / "config.json").read_text()).get(
            "encoder"
        )
    except (OSError, ValueError, AttributeError, HistojaxDataError):
        return None
    return encoder if isinstance(encoder, str) and encoder else None


def refuse_not_an_agent(path: Path) -> None:
    """Refuse, in one line saying why and what to use instead, a published folder that was retired
    (:data:`RETIRED`; the folder is gone) and a slide head folder (``histojax.reading.heads``: it scores what a
    reader read, it does not act)."""
    from histojax.reading.heads import HEADS

    name = path.parent.name if path.name == "params.msgpack" else path.name
    if not path.exists() and name in RETIRED:
        new, why = RETIRED[name]
        raise HistojaxDataError(
            path,
            f"the published agent {name} was retired ({why}); its results stay in "
            f"docs/results/c16.md; use {published_path(new)}, which reads slides of any "
            f"size: histojax evaluate {published_path(new)} --dataset DIR",
        )
    try:
        kind = json.loads((path / "config.json").read_text()).get("kind") if path.is_dir() else None
    except (OSError, ValueError, AttributeError):
        kind = None
    if kind in HEADS:
        raise HistojaxDataError(
            path,
            "a slide head, not an agent: it scores what a reader read, it does not act; "
            f"score a reader through it: histojax evaluate READER --head {path} --dataset DIR "
            f"(or python -m baselines.reading.readers --head {path} --dataset DIR)",
        )


def grid_refusal(error: ValueError, run) -> ValueError:
    """``error`` of a flat glimpse policy (the ``-v1`` observation, a padded cell grid pinned at training) on
    a slide whose cells do not fit that grid, as one line saying that this policy cannot read it by
    construction and which reader to use instead; any other error unchanged."""
    text = str(error)
    if run is None or "do not fit glimpse_grid" not in text:
        return error
    where = text.split(" (the grid a policy was trained with)")[0]
    set_reader = published_path(SET_READER)
    use = (
        f"use the cell-set reader, which reads slides of any size: histojax evaluate {set_reader} --dataset DIR"
        if set_reader.is_dir()
        else "use a cell-set reader, which reads slides of any size (the -v2 ids; python -m baselines.reading.train_readers "
        "trains one)"
    )
    return ValueError(
        f"{where}: {run} is a flat glimpse policy over the padded cell grid it trained on, so it cannot "
        f"read a slide wider or taller than that grid; {use}"
    )


def head_reward_settings(run: Path, config: dict) -> tuple[dict | None, Path | None]:
    """``(settings, file)`` of a reader trained with SASHA's reward (``RUN/head_reward.json`` as
    ``baselines.reading.train_readers`` writes it, or a ``head_reward`` object in ``config.json``): ``head``
    (its slide head folder), ``gain``, ``final``, ``read_cost``; ``(None, None)`` for other runs."""
    f = run / "head_reward.json"
    if f.is_file():
        try:
            record = json.loads(f.read_text())
        except (OSError, ValueError) as e:
            raise HistojaxDataError(f, f"unreadable ({type(e).__name__}: {e})") from None
        if not isinstance(record, dict) or not isinstance(record.get("head"), str) or not record["head"]:
            raise HistojaxDataError(
                f,
                "names no slide head (a 'head' folder, as baselines.reading.train_readers writes it); give --head DIR",
            )
        return record, f
    record = config.get("head_reward")
    if isinstance(record, dict) and isinstance(record.get("head"), str) and record["head"]:
        return record, run / "config.json"
    return None, None


def resolve_head(recorded: str, run: Path, where) -> Path:
    """The slide head folder a run names (``recorded``), as ``histojax evaluate --head`` resolves a head's name
    (:func:`baselines.published_agents.published_or_path`): a published head's bare name or its package name
    (``baselines/published/NAME``, as the published agents record theirs) is the installed package's copy first, so
    a folder of that name under the working folder is never taken for it (name it ``./baselines/published/NAME`` or
    by an absolute path to use it); any other name is the folder as given when absolute, else beside the run, in the
    working folder or in the repository. A folder that is in none of these is refused (``HistojaxDataError`` naming
    ``where``, the file that names it, and the missing folder), never replaced by a published head that merely
    shares its folder name."""
    from baselines.published_agents import published_or_path

    p = Path(recorded)
    published = Path(published_or_path(str(recorded)))
    tries = [published] if published != p else []
    tries += [p] if p.is_absolute() else [run / p, p, Path(__file__).resolve().parents[2] / p]
    for c in tries:
        if (c / "config.json").is_file():
            return c
    missing = p if p.is_absolute() else run / p
    raise HistojaxDataError(
        where,
        f"names the slide head {recorded!r}, which is not here (no {missing / 'config.json'}; looked beside the "
        "run, in the working folder and the repository; a published head is named by its own name); give "
        f"--head DIR, e.g. --head {published_path('c16-v2-head')}",
    )


def check_params_tree(params, path) -> None:
    """Refuse a checkpoint that holds no parameter arrays stacked over seeds (a foreign msgpack)."""
    leaves = jax.tree.leaves(params) if isinstance(params, dict) else []
    if not leaves or any(np.ndim(a) < 1 for a in leaves) or len({np.shape(a)[0] for a in leaves}) != 1:
        raise HistojaxDataError(
            path,
            "not a histojax checkpoint (no network parameters stacked over seeds, as the "
            "trainers write them); give the params.msgpack of a histojax training run",
        )
