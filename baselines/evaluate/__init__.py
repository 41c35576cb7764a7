"""Evaluate a trained checkpoint against reference policies.

    python -m baselines.evaluate runs/ppo-easy [--env HistoJAX-Easy-v0] [--slides BUNDLE ... | held-out] [--episodes 256]

For every slide (default: the one the checkpoint was trained on) prints and writes
(``eval.json``, ``eval.csv`` in ``--out``, default ``<run>/eval``, or ``runs/eval-<name>`` for a run inside
the package such as ``baselines/published/NAME``) one row per policy:

* the checkpoint's policy, greedy (argmax / Gaussian mean) and sampled, pooled over its seeds;
* ``random`` — uniform random actions;
* ``scripted`` — coarse-to-fine using only the observation (see :func:`scripted_policy`); for a
  ``discrete:map`` navigator, the map follower (:func:`map_follower_policy`).

Columns: success rate (target reached at the finest level), mean return, mean episode length,
mean steps to success (over the successful episodes), mean fraction of the slide read and fields of
view, and for a diagnosis the AUC of the policy's tumour score.

**Readers trained with SASHA's reward** (``python -m baselines.reading.train_readers``; their run folder holds a
``head_reward.json`` naming the slide head; ``--head DIR`` names another, or scores any checkpoint's reading
through a head): the policy only chooses where to read, until it stops or its budget is spent, and the
**head declares** — it scores the finest views each episode read (:func:`head_env`), every row through
the same head; columns ``AUC`` over all slides and ``AUC w/o ITC`` without ITC-only tumour slides
(CAMELYON's lesion classes from the bundles' tumour polygons, when every tumour slide has them), success
= the head's diagnosis right, each slide read equally often. A cell-set reader (the ``-v2`` ids) runs on
slides of any size; a flat glimpse policy (``-v1``) on a slide wider or taller than its cell grid, a
retired published folder and a slide head folder are refused in one line saying what to use instead. Episodes run without auto-reset until
success or the step limit. Also writes, on each episode's own slide, ``trajectory_<policy>.png``
(histojax.render.render_trajectory), ``reading_<policy>_tumour.png`` / ``_normal.png`` (where it read,
histojax.render.render_reading_map) and ``trajectory.gif`` (histojax.render.animate) of one episode of
the first policy. Warns when the slides cannot be scored (no tumour slide; one class only for an AUC), when
the checkpoint is scored on its own training split or at another scale, and on config.json keys no
trainer writes.


Modules: ``policies``, ``rollout``, ``heads``, ``pictures``, ``checks``, ``scoring``, ``cli``."""

from __future__ import annotations

from baselines.evaluate.checks import (
    RETIRED,
    SET_READER,
    check_config,
    check_params_tree,
    grid_refusal,
    head_reward_settings,
    known_config_keys,
    provenance_warnings,
    published_path,
    refuse_not_an_agent,
    resolve_head,
    split_warnings,
)
from baselines.evaluate.cli import add_arguments, default_out, main, print_table, resolve_slides, run, with_dataset
from baselines.evaluate.heads import head_env, head_scored, lesion_classes
from baselines.evaluate.pictures import write_pictures
from baselines.evaluate.policies import (
    diagnosis_actions,
    learned_policy,
    map_follower_policy,
    network_for,
    scripted_features_policy,
    scripted_policy,
    seeds_policy,
    stain_offset,
)
from baselines.evaluate.rollout import (
    check_fits,
    episode_labels,
    eval_env,
    per_episode_params,
    run_episodes,
    summarise,
    trajectory,
)
from baselines.evaluate.scoring import evaluate

__all__ = [
    "RETIRED",
    "SET_READER",
    "add_arguments",
    "check_config",
    "check_fits",
    "check_params_tree",
    "default_out",
    "diagnosis_actions",
    "episode_labels",
    "eval_env",
    "evaluate",
    "grid_refusal",
    "head_env",
    "head_reward_settings",
    "head_scored",
    "known_config_keys",
    "learned_policy",
    "lesion_classes",
    "main",
    "map_follower_policy",
    "network_for",
    "per_episode_params",
    "print_table",
    "provenance_warnings",
    "published_path",
    "refuse_not_an_agent",
    "resolve_head",
    "resolve_slides",
    "run",
    "run_episodes",
    "scripted_features_policy",
    "scripted_policy",
    "seeds_policy",
    "split_warnings",
    "stain_offset",
    "summarise",
    "trajectory",
    "with_dataset",
    "write_pictures",
]
