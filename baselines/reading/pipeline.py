"""The one reading pipeline behind the readers (:mod:`baselines.reading.readers`) and the budget curve
(:mod:`baselines.reading.budget_curve`): one loader of a split's slides, one run loop over readers × budgets, and
the trained readers' roll-outs. Both commands are this pipeline with their own heads and tables:

1. :func:`load_split` reads a split (``fold=i``: fold i's side of it) through the checked bundle loader (no links,
   nothing outside a bundle, checksums verified) into a :class:`Split`: its 0/1 ``labels (B,)`` and per slide a
   cell table (:mod:`baselines.reading.orders`: ``valid (C,)``, ``cell_views (C,)``, ``total``). With a head
   (the readers) the cells are a bundle level's views and each slide is the finest grid
   (:func:`baselines.reading.slides.load_slide`: ``tissue``, ``logits``, tumour polygons, µm/px); with a
   scenario and glimpse level (the budget curve) the cells are the env's glimpse cells
   (:meth:`histojax.reading.modes.glimpse.Glimpse.host_tables`: ``instances (V, D)`` of the finest tissue views).
2. :func:`check_two_classes` refuses, in one line naming ``dataset.json``, a scored split that holds one class:
   its AUC is undefined.
3. :func:`read_all` is the run loop: every reader's cell orders read at every budget by the glimpse env's rule
   (:func:`baselines.reading.orders.read_cells`) and scored by a callback (the head on what was read).
4. :func:`policy_reads` rolls a trained ``glimpse`` / ``zoom_select`` policy at every budget (:func:`run_seeds`: its
   seeds).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

from baselines.reading.orders import random_order, read_cells
from baselines.reading.slides import HeadDataError, load_slide, load_slides, read_bundle, read_spec, split_bundles
from baselines.run_config import read_run_config
from data_tools.bundle_files.reading import read_metadata
from data_tools.bundle_files.seals import verify_metadata
from histojax.reading.head_reward import pools_views

BUDGETS = (0.05, 0.1, 0.2, 0.5)
"""Fractions of a slide's finest-level tissue views a reader may read (5, 10, 20, 50 %): the default budgets of
``python -m baselines.reading.readers`` and ``python -m baselines.reading.budget_curve``."""


@dataclasses.dataclass
class Split:
    """A split's slides ready for reading. ``labels (B,)`` int 0/1; ``slides``: per slide a dict — the readers'
    finest grid (:func:`baselines.reading.slides.load_slide`) or the budget curve's glimpse cell table
    (:meth:`~histojax.reading.modes.glimpse.Glimpse.host_tables`); ``head``: the head loaded (readers), ``None``
    otherwise; ``cell_level``: the bundle level (readers) or scenario level (budget curve) of the cells;
    ``dataset``, ``split``, ``fold``: where the slides came from."""

    dataset: Path
    split: str
    labels: np.ndarray
    slides: list
    cell_level: int
    head: object = None
    fold: int | None = None

    @property
    def tables(self) -> list:
        """The slides' cell tables (the budget curve's name for :attr:`slides`)."""
        return self.slides


def load_split(
    dataset,
    split: str,
    *,
    fold: int | None = None,
    head=None,
    cell_level: int | None = None,
    env_id: str | None = None,
    level: int | None = None,
    verify: bool = True,
    progress: bool = False,
) -> Split:
    """The one loader of a split's slides, through the checked bundle loader (``ValueError`` /
    ``HistojaxDataError`` naming the file on anything malformed).

    * ``env_id`` and ``level`` (the budget curve): ``histojax.make(env_id, dataset=..., split=..., fold=...)`` and the
      glimpse cell tables of scenario level ``level`` per slide, labels from the env (``verify``: checksums).
    * ``head`` (a head folder or a loaded head; the readers): ``dataset.json`` read with its seal checked, each
      bundle read by :func:`baselines.reading.slides.load_slide` with the finest level and the cells of bundle
      level ``cell_level`` (default :func:`cell_level_for`: downsample nearest 4); a head that reads every feature
      entry gets its per-view scores and cached terms (:func:`with_head_scores`), a logit head its entry."""
    dataset = Path(dataset)
    if env_id is not None:
        tables, labels = _glimpse_tables(dataset, split, env_id, int(level), verify, fold)
        return Split(dataset, split, labels, tables, int(level), None, fold)
    if head is None:
        raise ValueError("load_split: give a head (the readers' cells) or env_id and level (the glimpse cells)")
    from histojax.reading import heads

    head = heads.load(head) if isinstance(head, (str, Path)) else head
    spec = read_spec(dataset, fold)  # fold=i: fold i's sides (a dataset built with --folds K)
    if cell_level is None:
        cell_level = cell_level_for(dataset, spec, split)
    if pools_views(head):
        slides = load_feature_slides(dataset, split, spec, head, cell_level, progress=progress)
    else:
        slides = load_slides(dataset, split, spec, head.dim, levels=(0, cell_level), progress=progress)
    labels = np.asarray([s["label"] for s in slides], int)
    return Split(dataset, split, labels, slides, cell_level, head, fold)


def _glimpse_tables(dataset: Path, split: str, env_id: str, level: int, verify: bool, fold: int | None):
    """``(tables, labels)``: :meth:`Glimpse.host_tables` of ``split``'s slides at scenario level ``level`` and their
    0/1 labels ``(B,)``, read by ``histojax.make`` (the checked bundle loader)."""
    import histojax
    from histojax.reading.modes.glimpse import Glimpse

    env, params = histojax.make(
        env_id, dataset=dataset, split=split, obs_mode="features", task="classification", verify=verify, fold=fold
    )  # not the glimpse mode: it would make the
    glimpse = Glimpse(level=level)  # device tables, unused here, a second time
    glimpse.validate(env)
    tables = glimpse.host_tables(env, params, env.bundles)
    for table, bundle in zip(tables, env.bundles):  # the slide's name and encoder: what a head and a warning check
        table.update(name=Path(bundle.path).name, encoder=(bundle.metadata.get("features") or {}).get("encoder"))
    labels = np.atleast_1d(np.asarray(params.slide.slide_label)).astype(int)
    return tables, labels


def one_class_problem(split: str, labels, fold: int | None = None) -> str | None:
    """What is wrong with a scored split whose 0/1 ``labels (B,)`` hold one class (or none): its AUC is undefined,
    never printed as 1.000 or nan. ``None`` when both classes are there."""
    labels = np.asarray(labels)
    if len(labels) and len(set(labels.tolist())) > 1:
        return None
    which = f"split {split!r}" + (f" (fold {fold})" if fold is not None else "")
    if fold is not None and split in ("test", "validation"):
        which = f"fold {fold}'s held-out side"
    held = f"only {'tumour' if labels[0] else 'normal'} slides ({len(labels)})" if len(labels) else "no slides"
    return (
        f"{which} holds {held}: its AUC is undefined: one class; scoring needs tumour and normal slides "
        "(rebuild the dataset or score another split)"
    )


def split_words(dataset, split: str, fold: int | None = None) -> str:
    """How a command names the slides it scores (warnings, titles): ``"fold I's held-out side"`` for a fold's
    held-out side, ``"the validation share of the train split"`` (or ``"of fold I's train side"``) for the
    ``validation-set`` folder :mod:`baselines.reading.train_readers` scores (its ``"test"`` list is the validation
    share), else ``"the SPLIT split"``. ``dataset``: the dataset folder (its ``dataset.json`` read plainly; an
    unreadable one is named by ``split``)."""
    import json

    if fold is not None and split in ("test", "validation", "val"):
        return f"fold {fold}'s held-out side"
    if fold is not None:
        return f"fold {fold}'s {split} side"
    try:
        spec = json.loads((Path(dataset) / "dataset.json").read_text())
    except (OSError, ValueError):
        spec = {}
    if split == "test" and isinstance(spec, dict) and spec.get("note_split") == "test = the validation slides":
        cut = (spec.get("validation_split") or {}).get("fold")
        return "the validation share of " + ("the train split" if cut is None else f"fold {cut}'s train side")
    return f"the {split} split"


def check_two_classes(dataset, split: str, labels, fold: int | None = None) -> None:
    """Refuse a scored split that holds one class: :class:`~baselines.reading.slides.HeadDataError`, one line
    naming ``dataset.json`` (:func:`one_class_problem`)."""
    problem = one_class_problem(split, labels, fold)
    if problem:
        raise HeadDataError(Path(dataset) / "dataset.json", problem)


# ----------------------------------------------------------------------------- the run loop
def reader_auc(scores, labels) -> dict:
    """The one AUC of a reader, for the readers and the budget curve alike: ``scores (seeds, B)`` its per-slide
    scores (logits or probabilities: the AUC depends on their order only) of each seed (random order, policy seed)
    on the ``B`` slides of 0/1 ``labels (B,)``. Returns :func:`data_tools.metrics.auc_over_runs`: ``auc`` (mean over
    seeds), ``auc_std`` (std over seeds), ``auc_low`` / ``auc_high`` (the 95 % interval over the ``B`` slides),
    ``auc_per_run``, ``n_tumour``, ``n_normal``."""
    from data_tools.metrics import auc_over_runs

    return auc_over_runs(scores, labels)


def nothing_reason(table: dict, order, budget: float) -> str:
    """Why a reader picking ``order`` (cell indices) under ``budget`` reads nothing on the slide of cell ``table``
    (:func:`~baselines.reading.orders.read_cells`' rule): its first pick holds more tissue views than the budget
    allows (and whether a smaller cell would have fit), or the slide has no cell to read."""
    total = int(table["total"])
    limit = int(np.floor(budget * total + 1e-4))
    valid, views = np.asarray(table["valid"], bool).reshape(-1), np.asarray(table["cell_views"]).reshape(-1)
    first = next((int(c) for c in np.asarray(order).reshape(-1) if valid[int(c)]), None)
    if first is None:
        return "it has no cell to read"
    return first_pick_words(int(views[first]), limit, total, views, valid)


def first_pick_words(pick: int | None, limit: int, total: int, cell_views, valid) -> str:
    """``"its first pick (N tissue views) is larger than the budget (M of T views)"`` and whether the slide's smallest
    cell fits; ``pick=None``: the size of the pick refused is unknown (a trained reader's roll-out)."""
    views = np.asarray(cell_views)[np.asarray(valid, bool)]
    smallest = int(views.min()) if views.size else None
    said = f"its first pick{f' ({pick} tissue views)' if pick is not None else ''} is larger than the budget "
    said += f"({limit} of {total} views)"
    if smallest is None:
        return "it has no cell to read"
    if smallest > limit:
        return said + f"; so is every cell of it (the smallest holds {smallest})"
    return said + f", though its smallest cell ({smallest} view{'' if smallest == 1 else 's'}) fits"


def nothing_entries(names, fractions, reasons: dict) -> list[dict]:
    """The slides a row (a reader at one budget) read nothing on: ``[{"slide", "reason"[, "seeds"]}]`` for each slide
    whose fraction read is 0 in some seed of ``fractions (seeds, B)``; ``reasons``: ``{slide index: reason}`` (a
    missing one: ``"it read no view"``); ``seeds``: ``"k of n"`` when there are several seeds."""
    f = np.atleast_2d(np.asarray(fractions, np.float64))
    out = []
    for i in np.flatnonzero((f <= 0).any(0)):
        k = int((f[:, i] <= 0).sum())
        entry = {"slide": str(names[i]), "reason": reasons.get(int(i), "it read no view")}
        if len(f) > 1:
            entry["seeds"] = f"{k} of {len(f)}"
        out.append(entry)
    return out


def nothing_line(reader: str, budget: float, entries: list[dict], shown: int = 5) -> str | None:
    """One line naming the slides ``reader`` read nothing on at ``budget`` (:func:`nothing_entries`) and why (five
    named, then a count); ``None`` when it read something on every slide."""
    if not entries:
        return None
    parts = [
        f"{e['slide']}{' (' + e['seeds'] + ' seeds)' if 'seeds' in e else ''}: {e['reason']}" for e in entries[:shown]
    ]
    more = f"; and {len(entries) - shown} more" if len(entries) > shown else ""
    return (
        f"{reader} at budget {budget * 100:.3g} % read nothing on {len(entries)} slide"
        f"{'s' if len(entries) > 1 else ''} (scored there on nothing read): " + "; ".join(parts) + more
    )


def random_orders(tables: list[dict], seeds: int) -> list[list[np.ndarray]]:
    """``seeds`` × slides random cell orders: seed ``k`` of slide ``i`` drawn from ``default_rng(1000 k + i)`` (the
    random reader of both the readers and the budget curve)."""
    return [[random_order(t, np.random.default_rng(1000 * k + i)) for i, t in enumerate(tables)] for k in range(seeds)]


def read_all(
    tables: list[dict], readers: dict, budgets, score, kinds: dict | None = None, progress: bool = False
) -> dict:
    """The run loop over budgets × readers: each reader's orders read as the glimpse env reads
    (:func:`~baselines.reading.orders.read_cells`) and scored.

    ``readers``: ``{name: [orders per slide] per seed}`` (an order: cell indices ``(C',)`` int); ``score``: called
    with the cells read per slide (a list of ``(c,)`` int arrays), returns ``{"scores": (B,), ...}`` (any other
    per-slide arrays are kept too); ``kinds``: ``{name: kind}`` (plot colour family). Returns ``{(name, budget):
    {"kind", "fractions" (seeds, B), "scores" (seeds, B), "nothing", ...}}`` in budget-then-reader order (the rows'
    order); ``nothing``: ``{slide index: why it read nothing}`` (:func:`nothing_reason`) where some seed read nothing."""
    out = {}
    for b in budgets:
        for name, per_seed in readers.items():
            fractions, parts, why = [], [], {}
            for orders in per_seed:
                reads = [read_cells(t, o, b) for t, o in zip(tables, orders)]
                fractions.append(np.asarray([r[1] for r in reads]))
                parts.append(score([r[0] for r in reads]))
                for i, (t, o, r) in enumerate(zip(tables, orders, reads)):
                    if not len(r[0]) and i not in why:  # read nothing: why, from the first seed that did
                        why[i] = nothing_reason(t, o, b)
            entry = {"kind": (kinds or {}).get(name, "scripted"), "fractions": np.stack(fractions), "nothing": why}
            entry.update({k: np.stack([p[k] for p in parts]) for k in parts[0]})
            out[(name, float(b))] = entry
        if progress:
            print(f"  budget {b:.2f} scored", file=sys.stderr, flush=True)
    return out


# ----------------------------------------------------------------------------- the readers' slides
def cell_level_for(dataset: Path, spec: dict, split: str, target: float = 4.0) -> int:
    """The bundle level (≥ 1) whose downsample is nearest ``target`` (geometric distance), read from the split's
    first bundle."""
    entries = spec.get(split) or []
    if not entries:
        raise HeadDataError(Path(dataset) / "dataset.json", f"has no slides in split {split!r}")
    rel = entries[0]
    bundle = Path(rel) if Path(rel).is_absolute() else Path(dataset) / rel
    meta_file = bundle / "metadata.json"
    try:
        meta = read_metadata(bundle)  # the checked loader's: the bundle's own metadata.json, its fields checked
        verify_metadata(bundle, meta)
        ds = meta.downsamples
    except OSError as e:
        raise HeadDataError(meta_file, f"unreadable level list ({type(e).__name__}: {e})") from None
    if len(ds) < 2:
        raise HeadDataError(meta_file, "one level only: no coarser cells to read by")
    return 1 + int(np.argmin([abs(np.log(d / target)) for d in ds[1:]]))


def with_head_scores(slide: dict, head, grids: dict) -> dict:
    """``slide`` (:func:`baselines.reading.slides.load_slide` with ``grid=True``) scored by a head that reads
    every feature entry: ``logits (H, W)`` its per-view scores of the finest views, ``terms (H, W, 2)`` their
    cached attention and instance logits, and per coarse level in ``grids`` (``{level: (h, w, D)}``) ``coarse``
    the per-view scores and ``coarse_terms`` the terms of the cells' own feature vectors. The finest feature
    grid is dropped. ``HeadDataError`` naming the bundle when the features are not the head's length."""
    feats = np.asarray(slide.pop("features"), np.float32)
    d = int(getattr(head, "features_dim", feats.shape[-1]))
    if feats.shape[-1] != d:
        raise HeadDataError(
            slide["bundle"],
            f"{feats.shape[-1]}-d features; the head reads {d}-d features "
            "(fit a head on this dataset: python -m baselines.reading.learned_head_fit)",
        )
    score = jax.jit(head.view_terms)
    terms = np.asarray(score(feats))
    slide.update(terms=terms, logits=np.asarray(head.calibrate(terms[..., 1]), np.float32), coarse={}, coarse_terms={})
    for lv, g in grids.items():
        t = np.asarray(score(np.asarray(g, np.float32)))
        slide["coarse_terms"][lv] = t
        slide["coarse"][lv] = np.asarray(head.calibrate(t[..., 1]), np.float32)
    return slide


def tumour_geometry(bundle):
    """The tumour geometry (shapely, finest px) of a bundle's annotations, or None when it has none or its
    annotation file holds no polygon (a slide labelled in a label table needs none); read through the bundle's
    own file (:func:`data_tools.bundle_files.safe_files.own_file`)."""
    import os

    from data_tools.annotations import AnnotationError, load_annotations
    from data_tools.bundle_files.format import ANNOTATIONS
    from data_tools.bundle_files.safe_files import own_file

    if not os.path.lexists(Path(bundle) / ANNOTATIONS):
        return None
    path = own_file(Path(bundle), ANNOTATIONS, "annotations")
    try:
        return load_annotations(path).tumour
    except AnnotationError as e:
        if "no polygons" in str(e):
            return None
        raise


def load_feature_slides(dataset, split, spec: dict, head, cell_level: int, progress: bool = False) -> list[dict]:
    """:func:`baselines.reading.slides.load_slide` of every bundle of ``split`` for a head that reads every
    feature entry (:func:`with_head_scores`: per-view scores and terms of the finest views and of the cells of
    bundle level ``cell_level``), through the checked bundle loader."""
    out = []
    for bundle, label in split_bundles(dataset, split, spec, progress):
        if label is None:  # the bundle's own label: tumour annotated or not
            s = load_slide(bundle, None, 0, (0,), grid=True)
        else:  # a label table's label; tumour polygons where the bundle has any (slide-level labels need none)
            s = load_slide(bundle, 0, 0, (0,), grid=True)
            s.update(label=int(label), tumour=tumour_geometry(bundle) if label else None)
        meta, grids, _, _ = read_bundle(bundle, (cell_level,))
        s["downsample"] = {cell_level: float(meta["levels"][cell_level]["downsample"])}
        out.append(with_head_scores(s, head, grids))
    return out


# ----------------------------------------------------------------------------- trained readers
def policy_reads(
    run,
    dataset,
    split: str,
    budgets=BUDGETS,
    env_id: str | None = None,
    seed: int = 0,
    fold: int | None = None,
    why: dict | None = None,
) -> dict:
    """Roll a trained policy greedily, once on every slide of ``dataset``'s ``split`` at each of
    ``budgets``, with :func:`baselines.episodes.rollout.run_episodes` (one jitted program for all slides and
    budgets). ``run``: a run folder of ``python -m baselines.ppo`` (feed-forward) or ``python -m
    baselines.ppo_rnn`` (GRU; ``"algo": "ppo_rnn"`` in its ``config.json``: its hidden state is carried
    through each episode) in a ``glimpse`` or ``zoom_select`` mode; its seed ``seed`` (default the first).

    Returns ``{budget: [(read, own_score, fraction_read, fields_of_view) per slide]}``: the finest tissue views it
    read (indices into the slide's ``host_tables`` instances), its own tumour score
    (``p(tumour) / (p(tumour) + p(no tumour))`` of its policy at the step it declared, or at its last
    step; see :func:`baselines.episodes.policies.learned_policy`), the fraction read and the fields of view
    (env steps that looked at the slide) of the episode. ``why`` (a dict): filled with ``{(budget, slide index):
    reason}`` for each episode that read nothing (:func:`first_pick_words`: its first pick larger than the budget,
    or it declared before reading)."""
    from baselines.episodes import policies, rollout
    from baselines.harness.logs import load_checkpoint
    from histojax.core.seen_views import seen_flags  # seen is a bit set

    params, record = load_checkpoint(run)
    config = read_run_config(record, (Path(run) if Path(run).is_dir() else Path(run).parent) / "config.json")
    n_seeds = jax.tree.leaves(params)[0].shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"{run} has {n_seeds} seed(s), not a seed {seed}")
    params = jax.tree.map(lambda a: a[seed], params)
    kw = {k: v for k, v in (config.env_kwargs or {}).items() if k not in ("dataset", "split", "slides", "fold")}
    config = config.replace(
        env_kwargs={**kw, "dataset": str(dataset), "split": split, **({"fold": fold} if fold is not None else {})}
    )  # fold: the slides scored
    if env_id:
        config = config.replace(env_id=env_id)
    config, (env, env_params) = rollout.eval_env(config)
    if not hasattr(env_params.mode_data, "read_budget") or getattr(env.action, "name", "") not in (
        "glimpse",
        "zoom_select",
    ):
        raise ValueError(
            f"{run}: a policy of action mode {config.action_mode!r}; the budget curve takes "
            f"glimpse or zoom_select policies"
        )
    n = env.num_actions
    policy = policies.learned_policy(
        policies.network_for(config, env), params, config.action_mode, greedy=True, declare=(n - 2, n - 1)
    )
    n_slides = len(env.bundles)
    budgets = [float(b) for b in budgets]
    slides = np.tile(np.arange(n_slides), len(budgets))
    per_episode, axes = rollout.per_episode_params(env_params, slides, np.repeat(budgets, n_slides))
    ep = rollout.run_episodes(env, per_episode, policy, jax.random.key(0), len(slides), params_axes=axes, final=True)
    assert (ep["slide"] == slides).all()
    memory, scores = ep["final_state"].memory, ep["final_memory"][1]
    tables = env.action.host_tables(env, env_params, env.bundles) if hasattr(env.action, "host_tables") else None
    seen_tables = env_params.mode_data
    out = {b: [] for b in budgets}
    for e, i in enumerate(slides):
        if tables is not None:  # glimpse: the instances under the revealed cells
            read = np.isin(tables[i]["instance_cell"], np.flatnonzero(np.asarray(memory.revealed[e])))
        else:  # zoom_select: the finest tissue views seen
            f = env.n_levels - 1
            start = int(seen_tables.grid_offset[i, f])
            size = int(seen_tables.grid_width[i, f] * seen_tables.grid_height[i, f])
            seen = seen_flags(memory.seen[e], start, size)
            read = seen[np.asarray(seen_tables.tissue[i])[:size]]
        if why is not None and not read.any():
            why[(budgets[e // n_slides], int(i))] = _nothing_episode(
                ep["final_state"], e, i, tables, budgets[e // n_slides]
            )
        out[budgets[e // n_slides]].append(
            (np.flatnonzero(read), float(scores[e]), float(ep["fraction_read"][e]), float(ep["fields_of_view"][e]))
        )
    return out


def run_seeds(run) -> int:
    """How many seeds a run folder's ``params.msgpack`` holds."""
    from baselines.harness.logs import load_checkpoint

    return int(jax.tree.leaves(load_checkpoint(run)[0])[0].shape[0])


def _nothing_episode(state, e: int, i: int, tables, budget: float) -> str:
    """Why episode ``e`` (on slide ``i``) of a trained reader read nothing: a glimpse pick refused by the budget (the
    cell it picked, where the final view stands, and its size) or a declaration before any read."""
    if tables is None:  # zoom_select: no cells
        return "it read no finest view"
    t = tables[i]
    limit = int(np.floor(np.float32(budget) * np.float32(t["total"]) + np.float32(1e-4)))
    if not bool(np.asarray(state.memory.over_budget[e])):
        return "it declared before reading a cell"
    x, y = int(np.asarray(state.x[e])), int(np.asarray(state.y[e]))
    hit = np.flatnonzero(((t["cell_x"] == x) & (t["cell_y"] == y) & t["valid"]).reshape(-1))
    pick = int(np.asarray(t["cell_views"]).reshape(-1)[hit[0]]) if hit.size else None
    return first_pick_words(pick, limit, int(t["total"]), t["cell_views"], t["valid"])
