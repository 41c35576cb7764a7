"""Score a checkpoint and the reference policies on slides: one row per policy (:func:`evaluate`)."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np

from baselines.episodes.policies import (
    diagnosis_actions,
    learned_policy,
    map_follower_policy,
    network_for,
    scripted_features_policy,
    scripted_policy,
    seeds_policy,
)
from baselines.episodes.rollout import check_fits, episode_labels, eval_env, per_episode_params, run_episodes, summarise
from baselines.evaluate.checks import one_class, split_warnings, undefined_figures
from baselines.evaluate.heads import dataset_labelled, head_env, head_scored, refuse_one_class
from baselines.evaluate.pictures import write_pictures
from baselines.networks import QNetwork
from baselines.networks import is_discrete as policy_is_discrete


def small_split_words(env_params, scored: bool) -> str | None:
    """The small-split warning (:func:`data_tools.metrics.small_split_warning`, one line) of the slides an AUC is
    scored on (``scored``: a diagnosis, or a head declaring), when either class has too few slides to rank; None
    otherwise (and for one class, which :func:`~baselines.evaluate.checks.split_warnings` reports)."""
    from data_tools.metrics import small_split_warning

    if not scored or getattr(env_params.slide, "slide_label", None) is None:
        return None
    labels = np.asarray(jax.device_get(env_params.slide.slide_label)).ravel().astype(int)
    if len(set(labels.tolist())) < 2:
        return None
    return small_split_warning(int(labels.sum()), int((1 - labels).sum()), f"the {labels.size} slides scored")


def unreadable_at_budget(env_params, names) -> str | None:
    """The line of :func:`histojax.reading.modes.glimpse.unreadable_warning` for a glimpse env's reading budget
    (``env_params.mode_data``: its cells and ``read_budget``) on the slides ``names``; ``None`` for other modes or
    when a cell can be read on every slide."""
    from histojax.reading.modes.glimpse import unreadable_warning

    tables = getattr(env_params, "mode_data", None)
    if not all(hasattr(tables, k) for k in ("cell_views", "valid", "total_views", "read_budget")):
        return None
    budget = float(np.asarray(tables.read_budget))
    return unreadable_warning(
        names, np.asarray(tables.cell_views), np.asarray(tables.valid), np.asarray(tables.total_views), [budget]
    )


def read_nothing_episodes(ep: dict, env_params, names) -> list[dict]:
    """The slides on which some of a row's episodes ``ep`` (``slide``, ``fraction_read`` per episode) read nothing in a
    glimpse env (``env_params.mode_data``: its cells and ``read_budget``): ``[{"slide", "reason", "episodes": "k of
    n"}]``; the reason from the slide's cells and the budget (:func:`baselines.reading.pipeline.first_pick_words`:
    every cell larger than the budget, or a first pick larger than it or a stop before reading). ``[]`` for other
    modes."""
    from baselines.reading.pipeline import first_pick_words

    tables = getattr(env_params, "mode_data", None)
    if "fraction_read" not in ep or not all(
        hasattr(tables, k) for k in ("cell_views", "valid", "total_views", "read_budget")
    ):
        return []
    fraction, slide = np.asarray(ep["fraction_read"]).reshape(-1), np.asarray(ep["slide"]).reshape(-1)
    budget = np.float32(np.asarray(tables.read_budget))
    views, valid = np.asarray(tables.cell_views), np.asarray(tables.valid, bool)
    total = np.atleast_1d(np.asarray(tables.total_views)).reshape(-1)
    out = []
    for i in np.unique(slide[fraction <= 0]):
        i = int(i)
        limit = int(np.floor(budget * np.float32(total[i]) + np.float32(1e-4)))
        smallest = views[i][valid[i]].min() if valid[i].any() else None
        if smallest is not None and smallest <= limit:  # a cell fits: the policy picked too big or stopped first
            reason = (
                f"its first pick is larger than the budget ({limit} of {int(total[i])} views), or it stopped before "
                f"reading, though its smallest cell ({int(smallest)} view{'' if smallest == 1 else 's'}) fits"
            )
        else:
            reason = first_pick_words(None, limit, int(total[i]), views[i], valid[i])
        on = slide == i
        out.append(
            {
                "slide": str(names[i]),
                "reason": reason,
                "episodes": f"{int((fraction[on] <= 0).sum())} of {int(on.sum())}",
            }
        )
    return out


def evaluate(
    config,
    params,
    slide=None,
    num_episodes: int = 256,
    seed: int = 0,
    out: Path | None = None,
    label: str = "learned",
    augment: bool = False,
    references: bool = True,
    source=None,
    progress: bool = False,
    warnings: list | None = None,
    head=None,
    head_reward: dict | None = None,
) -> dict:
    """Rows (``config``: the run's typed config or its record) for the learned policy (greedy and sampled; seeds
    pooled), the random agent and the
    scripted policy (``references=False``: without these two) on one slide; writes trajectory
    pictures and reading maps to ``out`` when given (:func:`write_pictures`). Training-time view
    augmentation (``env_kwargs["augment"]``) is switched off unless ``augment=True``: a slide is
    evaluated as it is. ``source``: the run folder, named when its parameters do not fit the network
    its config describes; ``progress``: a line on stderr per policy as it runs. A warning when the slides
    cannot be scored (:func:`split_warnings`) is printed with ``progress`` and appended to ``warnings``.

    ``head`` (any slide head :func:`histojax.reading.heads.load` reads: a pcam-cnn logit head or a head learned
    from any encoder's features; its reading maps show its per-view scores beside where the agent read): **the
    head declares** — every row's episodes run in the
    env wrapped in :class:`histojax.reading.head_reward.HeadReward` (``head_reward``: the run's reward settings
    ``gain``, ``final``, ``read_cost`` from its ``head_reward.json``, so the return is the one it trained
    for; without them the env's own reward), the policy only chooses where to read (its declaring
    actions just stop the reading), and at each episode's end the head scores the finest views read:
    ``success`` is the head's diagnosis right, ``diagnosis_auc`` the AUC of its score and
    ``diagnosis_auc_no_itc`` the same without ITC-only slides (when every tumour slide's lesion class is
    known, :func:`lesion_classes`). Episode ``e`` of each policy reads slide ``e mod S``: every slide
    equally often. Slides of one class are refused through a head (``HistojaxDataError``, one line: the head's
    AUC is undefined: one class), before any episode runs."""
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be at least 1, got {num_episodes}")
    config, (env, env_params) = eval_env(config, slide, augment)
    names = [Path(b.path).name for b in env.bundles]
    picture_env, classes = env, None
    if head is not None:  # the head's diagnosis is scored against the dataset's labels (a label table's too)
        env_params = dataset_labelled(env, env_params, config, slide)
        env, classes = head_env(env, env_params, head, head_reward)
        refuse_one_class(config, env_params, slide)
    mode = config.action_mode
    key = jax.random.PRNGKey(seed)
    rows, episodes = {}, {}
    params_seeds = params
    num_seeds = jax.tree.leaves(params)[0].shape[0] if params is not None else 0
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)  # noqa: E731
    base = env
    while not hasattr(base, "task") and hasattr(base, "_env"):
        base = base._env
    task = getattr(base, "task", "detection")
    for w in split_warnings(
        env,
        env_params,
        task,
        f"{len(names)} slide{'s' if len(names) > 1 else ''} ({', '.join(names[:3])}"
        f"{', ...' if len(names) > 3 else ''})",
    ):
        say(f"warning: {w}")
        if warnings is not None:
            warnings.append(w)
    if (
        w := small_split_words(env_params, task == "classification" or head is not None)
    ) is not None:  # too few slides to rank: one line
        say(w)
        if warnings is not None:
            warnings.append(w)
    if (w := unreadable_at_budget(env_params, names)) is not None:  # a budget below every cell: the overview alone
        say(f"warning: {w}")
        if warnings is not None:
            warnings.append(w)

    def episodes_of(policy, k, n):  # n episodes; through a head, episode e reads slide e mod S
        if head is None:
            return run_episodes(env, env_params, policy, k, n, final=declare is not None)
        per, axes = per_episode_params(env_params, np.arange(n) % len(names))
        return head_scored(run_episodes(env, per, policy, k, n, params_axes=axes), env_params, classes)

    declare = None
    if params is not None:
        network = network_for(config, env)
        variants = [("greedy", True)] if isinstance(network, QNetwork) else [("greedy", True), ("sampled", False)]
        declare = diagnosis_actions(env, network, mode) if head is None else None  # through a head: it declares
        for name, greedy in variants:
            # every seed in one program (one compile): episodes [s E, (s + 1) E) run seed s's policy
            policy = seeds_policy(
                lambda p: learned_policy(network, p, mode, greedy, declare=declare), params_seeds, num_seeds
            )
            check_fits(policy, env, env_params, num_seeds, config, source)
            say(f"  {label} ({name}): {num_episodes * num_seeds} episodes ...")
            ep = episodes_of(policy, jax.random.fold_in(key, 100), num_episodes * num_seeds)
            if declare is not None:  # the policy's p(tumour) at its decision, and the slides' labels
                ep["tumour_score"] = np.asarray(ep.pop("final_memory")[1], np.float64)
                ep["label"] = episode_labels(env_params, ep["slide"])
                ep.pop("final_state")
            per_seed = [
                {k: v[..., s * num_episodes : (s + 1) * num_episodes] for k, v in ep.items()} for s in range(num_seeds)
            ]
            pooled = {k: np.concatenate([e[k] for e in per_seed], axis=-1) for k in per_seed[0]}
            row = summarise(pooled, names)
            row["success_rate_per_seed"] = [summarise(e)["success_rate"] for e in per_seed]
            row["per_seed"] = [summarise(e, names) for e in per_seed]
            rows[f"{label} ({name})"] = row
            episodes[f"{label} ({name})"] = pooled

    def said_nothing():  # a row whose episodes read nothing on some slides: which, and why (JSON and a line)
        from baselines.reading.pipeline import nothing_line

        for name, row in rows.items():
            if name in episodes and (nothing := read_nothing_episodes(episodes[name], env_params, names)):
                row["read_nothing"] = nothing
                w = nothing_line(name, float(np.asarray(env_params.mode_data.read_budget)), nothing)
                say(f"warning: {w}")
                if warnings is not None:
                    warnings.append(w)

    if not references:
        said_nothing()
        return undefined_figures(rows, task, one_class(env_params))
    say(f"  random: {num_episodes} episodes ...")
    space = env.action_space()
    rand = lambda k, obs: jax.vmap(space.sample)(jax.random.split(k, jax.tree.leaves(obs)[0].shape[0]))  # noqa: E731
    declare = None
    episodes["random"] = episodes_of(rand, jax.random.fold_in(key, 1), num_episodes)
    rows["random"] = summarise(episodes["random"], names)
    # the scripted reference: one env's observation-only policy, for what the observation holds
    space_keys = getattr(env.observation_space(), "spaces", {})
    one_env, what, may_lack_pixels = None, "scripted", False
    if "coarse_map" in space_keys and policy_is_discrete(mode):
        one_env, what = map_follower_policy, "scripted (map follower)"
    elif isinstance(env.observation_space(), dict) or env.obs_mode in ("pixels", "pixels_float"):
        one_env, may_lack_pixels = (lambda kk, o: scripted_policy(kk, o, mode)), True
    elif env.obs_mode == "features" and policy_is_discrete(mode) and diagnosis_actions(env, None, mode) is None:
        one_env = scripted_features_policy
    if one_env is not None:

        def scripted(k, obs):
            n = jax.tree.leaves(obs)[0].shape[0]
            return jax.vmap(one_env)(jax.random.split(k, n), obs)

        try:
            say(f"  {what}: {num_episodes} episodes ...")
            episodes["scripted"] = episodes_of(scripted, jax.random.fold_in(key, 2), num_episodes)
            rows["scripted"] = summarise(episodes["scripted"], names)
        except (KeyError, TypeError, ValueError) as e:
            if not may_lack_pixels:
                raise
            print(f"scripted policy skipped: {e}")  # observation without pixels
    if out is not None:
        say(f"  pictures to {out} ...")
        write_pictures(picture_env, env_params, episodes, Path(out), config.env_id, head=head)
    said_nothing()
    return undefined_figures(rows, task, one_class(env_params))
