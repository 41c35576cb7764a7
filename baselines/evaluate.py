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
"""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from baselines import common, outputs
from data_tools.metrics import accuracy, roc_auc
from baselines.ppo import make_network
from baselines.networks import (ActorCritic, QNetwork, RecurrentActorCritic, RecurrentCellSetActorCritic, ScannedGRU,
                                policy_mode, policy_sample, preprocess_obs, rollout_apply, rollout_step)
from baselines.networks import is_discrete as policy_is_discrete
from baselines.published_agents import PUBLISHED
from data_tools.cli_output import positive_int
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn
from histojax import actions
from histojax.reading import tables as reading_tables
from histojax.render import animate, render_reading_map, render_trajectory


# ----------------------------------------------------------------------------- scripted policy
def stain_offset(pixels, grid: int = 4, sharpen: float = 4.0):
    """Where the darkest stain of one view ``(T, T, 3)`` lies: the score ``1 − (R + G) / 510``
    (H&E: haematoxylin-rich purple epithelium is dark in red and green; white background and pink
    stroma score low), averaged over a ``grid × grid`` of cells, raised to ``sharpen`` and
    turned into a centroid offset ``(ox, oy)`` from the view centre, in view widths (±0.5)."""
    t = pixels.shape[0]
    score = 1.0 - (pixels[..., 0] + pixels[..., 1]) / 510.0
    cells = score.reshape(grid, t // grid, grid, t // grid).mean(axis=(1, 3))
    w = cells ** sharpen + 1e-6
    centres = (jnp.arange(grid) + 0.5) / grid - 0.5
    ox = (w.sum(0) * centres).sum() / w.sum()
    oy = (w.sum(1) * centres).sum() / w.sum()
    return ox, oy


def scripted_policy(key, obs, action_mode: str = "discrete", centred: float = 0.12, epsilon: float = 0.1):
    """Coarse-to-fine from the observation and position only (never the mask), for one env.

    Look where the darkest stain of the view lies (:func:`stain_offset`); if it is within
    ``centred`` view widths of the centre, zoom in (at the finest level: step randomly, since the
    target was not reached there); otherwise move toward it — one view width along the larger
    offset for discrete actions, the offset itself for continuous ones. With probability
    ``epsilon`` a random discrete action breaks loops."""
    px = obs["pixels"] if isinstance(obs, dict) else obs
    pxf = jnp.asarray(px, jnp.float32)
    if not jnp.issubdtype(jnp.asarray(px).dtype, jnp.integer):
        pxf = pxf * 255.0
    ox, oy = stain_offset(pxf)
    finest = obs["position"][2] >= 1.0 - 1e-6 if isinstance(obs, dict) and "position" in obs else False
    k1, k2, k3 = jax.random.split(key, 3)
    is_centred = jnp.maximum(jnp.abs(ox), jnp.abs(oy)) < centred
    if action_mode.partition(":")[0] == "discrete":  # "discrete" or "discrete:memory"
        move = jnp.where(jnp.abs(ox) >= jnp.abs(oy),
                         jnp.where(ox > 0, actions.RIGHT, actions.LEFT),
                         jnp.where(oy > 0, actions.DOWN, actions.UP))
        rand_move = jax.random.randint(k1, (), 0, 4)
        centred_action = jnp.where(finest, rand_move, actions.ZOOM_IN)
        a = jnp.where(is_centred, centred_action, move)
        return jnp.where(jax.random.uniform(k2) < epsilon, jax.random.randint(k3, (), 0, 7), a).astype(jnp.int32)
    zoom = jnp.where(is_centred & ~jnp.asarray(finest), 1.0, 0.0)
    jitter = jax.random.uniform(k1, (2,), minval=-0.5, maxval=0.5) * is_centred * jnp.asarray(finest)
    return jnp.stack([2 * ox + jitter[0], 2 * oy + jitter[1], zoom])


def scripted_features_policy(key, obs, tumour_index: int = pcam_cnn.VIEW_LOGIT, threshold: float = 1.0,
                             epsilon: float = 0.1):
    """Coarse-to-fine on feature observations (discrete actions; one env), from the observation only:
    the view's tumour logit is ``features[tumour_index]`` (pcam-cnn: entry 62, ``mean l``, the view's
    tumour logit; entry 63, ``max l``, its most tumour-like cell, is noisier). Above ``threshold``
    zoom in (at the finest level: stay, since the view is already there); below it, move one view
    width in a random direction, and at the finest level zoom out half the time to look around from
    higher up. With probability ``epsilon`` a random action breaks loops. Meaningful for encoders
    with a tumour logit (pcam-cnn); on others it is a baseline of the same shape. The defaults
    (entry 62, threshold 1.0) were chosen on the validation slides of the v1 full set, Hard: 14.1 %
    of episodes found tumour, against 10.2 % with entry 63 at 0.0 (the earlier default)."""
    feats = obs["features"] if isinstance(obs, dict) else obs
    logit = jnp.asarray(feats, jnp.float32)[tumour_index]
    finest = obs["position"][2] >= 1.0 - 1e-6 if isinstance(obs, dict) and "position" in obs else False
    k1, k2, k3, k4 = jax.random.split(key, 4)
    move = jax.random.randint(k1, (), 0, 4)
    away = jnp.where(finest & (jax.random.uniform(k4) < 0.5), actions.ZOOM_OUT, move)
    hot = jnp.where(finest, actions.STAY, actions.ZOOM_IN)
    a = jnp.where(logit > threshold, hot, away)
    return jnp.where(jax.random.uniform(k2) < epsilon, jax.random.randint(k3, (), 0, 7), a).astype(jnp.int32)


def map_follower_policy(key, obs, travel_level: float = 0.5, read_enough: float = 0.5, epsilon: float = 0.05):
    """A navigator that walks to where the coarse map is high (``discrete:map`` observations; one env), from
    the observation only: its target is the block of ``coarse_map (16, 16)`` with the highest value among
    blocks whose ``visited`` fraction is below ``read_enough``. Far from it (more than 2 blocks) it travels at
    normalised level ``travel_level`` (``position[2]``: 0 coarsest, 1 finest; zooming out from the finest);
    over the target's block it zooms in; at the finest level inside the block it moves at random (reading
    the block's views), outside it steps towards the block's centre along the longer axis. With probability
    ``epsilon`` a random action breaks loops. The map's reference: what a navigator given the map could read."""
    m = obs["coarse_map"].shape[-1]
    score = jnp.where(obs["visited"] >= read_enough, -jnp.inf, obs["coarse_map"]).reshape(-1)
    target = jnp.argmax(score)
    ty, tx = jnp.divmod(target, m)
    dx = (tx + 0.5) / m - obs["position"][0]
    dy = (ty + 0.5) / m - obs["position"][1]
    level = obs["position"][2]
    finest = level >= 1.0 - 1e-6
    inside = (jnp.abs(dx) < 0.5 / m) & (jnp.abs(dy) < 0.5 / m)
    far = jnp.maximum(jnp.abs(dx), jnp.abs(dy)) > 2.0 / m
    toward = jnp.where(jnp.abs(dx) >= jnp.abs(dy), jnp.where(dx > 0, actions.RIGHT, actions.LEFT),
                       jnp.where(dy > 0, actions.DOWN, actions.UP))
    k1, k2, k3 = jax.random.split(key, 3)
    wander = jax.random.randint(k1, (), 0, 4)
    at_finest = jnp.where(far, actions.ZOOM_OUT, jnp.where(inside, wander, toward))
    above = jnp.where(far & (level > travel_level + 1e-6), actions.ZOOM_OUT,
                      jnp.where(inside, actions.ZOOM_IN, toward))
    a = jnp.where(finest, at_finest, above)
    return jnp.where(jax.random.uniform(k2) < epsilon, jax.random.randint(k3, (), 0, 4), a).astype(jnp.int32)


# ----------------------------------------------------------------------------- rollouts
def run_episodes(env, env_params, policy, key, num_episodes: int, params_axes=None, final: bool = False):
    """``num_episodes`` vmapped episodes (no auto-reset) of ``policy(key, obs_batch) -> actions``,
    or of a recurrent policy (``policy.initial_memory(n)`` defined): ``policy(key, obs_batch,
    memory) -> (actions, memory)``, its memory carried from step to step of each episode and frozen
    once the episode has ended (so it holds what the policy had at the episode's last step).
    Returns numpy ``return, success, length`` and ``slide`` (the slide index of a multi-slide env)
    per episode, ``fraction_read`` and ``fields_of_view`` at its end (NaN / -1 when the env does not
    track reading; see :func:`histojax.reading.tables.with_tracking`) and the ``(steps+1, E)`` trajectories
    ``z, x, y``: entry 0 the view at reset, entry ``t`` the view after step ``t`` (frozen after the
    episode ended).

    ``params_axes``: ``jax.vmap`` axes of ``env_params`` (default ``None``: one ``env_params`` for
    every episode); e.g. a per-episode slide (``slide.slide_logits (E, S)``) and reading budget
    (``mode_data.read_budget (E,)``), see :func:`per_episode_params`. ``final=True`` also returns
    ``final_state`` (the env states at the episodes' ends) and ``final_memory`` (the policy's
    memory; ``()`` for a feed-forward policy), as pytrees of numpy arrays.

    An env wrapped in :class:`histojax.adapters.head_reward.HeadReward` also gives per episode ``head_score``
    (the slide head's tumour logit of what the episode read, at its last step) and ``head_correct``
    (the head's diagnosis right); ``NaN`` / False for other envs. Trajectories and ``final_state`` are
    the wrapped env's own states."""
    from histojax.registry import check_params

    check_params(env, env_params, where="evaluate: env params")  # changed after make: named, not run
    max_steps = int(np.max(np.asarray(env_params.max_steps_in_episode)))
    step = jax.vmap(env.step, in_axes=(0, 0, 0, params_axes))
    reset = jax.vmap(env.reset, in_axes=(0, params_axes))
    recurrent = hasattr(policy, "initial_memory")
    inner = lambda s: getattr(s, "env_state", s)  # noqa: E731  (a HeadReward state holds the env's)

    @jax.jit
    def go(key, env_params):
        key, k_reset = jax.random.split(key)
        obs, state = reset(jax.random.split(k_reset, num_episodes), env_params)
        start = inner(state)  # the views at reset: entry 0 of the trajectories
        zeros = jnp.zeros(num_episodes)

        def body(carry, k):
            (obs, state, done, ret, length, success, memory), (read, fields, head, right) = carry
            k_act, k_step = jax.random.split(k)
            if recurrent:
                action, memory2 = policy(k_act, obs, memory)
            else:
                action, memory2 = policy(k_act, obs), memory
            obs2, state2, r, term, trunc, info = step(jax.random.split(k_step, num_episodes), state, action, env_params)
            active = ~done
            ret = ret + r * active
            length = length + active
            success = success | (info["success"] & active)
            keep = lambda old, new: jax.tree.map(  # noqa: E731
                lambda a, b: jnp.where(done.reshape(-1, *([1] * (a.ndim - 1))), a, b), old, new)
            state, obs, memory = keep(state, state2), keep(obs, obs2), keep(memory, memory2)
            read = jnp.where(active, info.get("fraction_read", read), read)
            fields = jnp.where(active, info.get("fields_of_view", fields), fields)
            head = jnp.where(active, info.get("head_score", head), head)
            right = jnp.where(active, info.get("head_correct", right), right)
            done = done | term | trunc
            view = inner(state)
            return ((obs, state, done, ret, length, success, memory), (read, fields, head, right)), (view.z, view.x,
                                                                                                     view.y)

        memory = policy.initial_memory(num_episodes) if recurrent else ()
        carry = ((obs, state, jnp.zeros(num_episodes, bool), zeros, zeros, jnp.zeros(num_episodes, bool), memory),
                 (jnp.full(num_episodes, jnp.nan, jnp.float32), jnp.full(num_episodes, -1, jnp.int32),
                  jnp.full(num_episodes, jnp.nan, jnp.float32), jnp.zeros(num_episodes, bool)))
        ((_, state, _, ret, length, success, memory), (read, fields, head, right)), (z, x, y) = jax.lax.scan(
            body, carry, jax.random.split(key, max_steps))
        state = inner(state)
        cat = lambda a0, a: jnp.concatenate([a0[None], a])  # noqa: E731
        return (ret, success, length, state.slide_index, read, fields, cat(start.z, z), cat(start.x, x),
                cat(start.y, y), head, right), (state, memory)

    out, (state, memory) = jax.device_get(go(key, env_params))
    names = ("return", "success", "length", "slide", "fraction_read", "fields_of_view", "z", "x", "y", "head_score",
             "head_correct")
    episodes = dict(zip(names, (np.asarray(a) for a in out)))
    if final:
        episodes["final_state"], episodes["final_memory"] = state, memory
    return episodes


def per_episode_params(env_params, slides, read_budgets=None):
    """``(params, axes)`` for :func:`run_episodes`' ``params_axes``: episode ``e`` runs on slide
    ``slides[e]`` (its ``slide_logits`` put all the weight there) and, with ``read_budgets``, with
    reading budget ``read_budgets[e]`` (``mode_data.read_budget`` of ``glimpse``, ``zoom_select`` or
    tracking); every other entry of ``env_params`` is shared by the episodes."""
    slides = np.asarray(slides)
    params, axes = env_params, jax.tree.map(lambda _: None, env_params)
    if env_params.slide.slide_logits is None:  # one slide
        if slides.any():
            raise ValueError(f"one slide, but episodes asked for slides {sorted(set(slides.tolist()))}")
    else:
        n_slides = int(np.asarray(env_params.slide.slide_logits).shape[-1])
        logits = np.where(np.arange(n_slides)[None] == slides[:, None], 0.0, -np.inf).astype(np.float32)
        params = params.replace(slide=params.slide.replace(slide_logits=jnp.asarray(logits)))
        axes = axes.replace(slide=axes.slide.replace(slide_logits=0))
    if read_budgets is not None:
        budgets = jnp.asarray(np.broadcast_to(np.asarray(read_budgets, np.float32), slides.shape))
        params = params.replace(mode_data=params.mode_data.replace(read_budget=budgets))
        axes = axes.replace(mode_data=axes.mode_data.replace(read_budget=0))
    return params, axes


def diagnosis_actions(env, network, action_mode: str):
    """``(DECLARE_NO_TUMOUR, DECLARE_TUMOUR)`` action indices when ``env`` is a diagnosis env
    (``task="classification"``) and ``network`` a discrete actor-critic, so the evaluation can score
    the policy's probability of declaring tumour (:func:`learned_policy`'s ``declare``); else None."""
    base = env
    while not hasattr(base, "task") and hasattr(base, "_env"):
        base = base._env
    if getattr(base, "task", None) != "classification" or isinstance(network, QNetwork):
        return None
    if not policy_is_discrete(action_mode):
        return None
    n = int(getattr(env, "num_actions", getattr(base, "num_actions", 0)))
    return (n - 2, n - 1) if n >= 2 else None


def episode_labels(env_params, slides) -> np.ndarray:
    """The 0/1 slide label of each episode's slide (``slide_label`` of the env's slides)."""
    label = np.asarray(jax.device_get(env_params.slide.slide_label))
    return (np.full(np.shape(slides), int(label)) if label.ndim == 0 else label[np.asarray(slides)]).astype(int)


def summarise(ep: dict, slide_names=None) -> dict:
    """Episodes, success rate, mean return, mean length and mean steps to success (over the
    successful episodes) of :func:`run_episodes`' output; with ``slide_names`` (one per slide of a
    multi-slide env) also ``by_slide``: ``{name: {"episodes", "successes"}}`` for the slides drawn."""
    s = ep["success"].astype(bool)
    row = {"episodes": int(s.size), "success_rate": float(s.mean()), "mean_return": float(ep["return"].mean()),
           "mean_length": float(ep["length"].mean()),
           "mean_steps_to_success": float(ep["length"][s].mean()) if s.any() else float("nan"),
           "mean_fraction_read": float(np.mean(ep["fraction_read"])) if "fraction_read" in ep else float("nan"),
           "mean_fields_of_view": float(np.mean(ep["fields_of_view"])) if "fields_of_view" in ep else float("nan")}
    if "tumour_score" in ep:  # diagnosis: AUC of the policy's p(tumour), accuracy of thresholding it at 0.5
        row["diagnosis_auc"] = roc_auc(ep["tumour_score"], ep["label"])
        row["score_accuracy"] = accuracy(ep["tumour_score"], ep["label"])
    if "lesion" in ep:  # ITC-only slides left out (CAMELYON's isolated tumour cells)
        keep = ep["lesion"] != "ITC"
        row["diagnosis_auc_no_itc"] = roc_auc(ep["tumour_score"][keep], ep["label"][keep])
    if slide_names is not None and len(slide_names) > 1:
        row["by_slide"] = {name: {"episodes": int((ep["slide"] == i).sum()),
                                  "successes": int(s[ep["slide"] == i].sum()),
                                  "steps_to_success_sum": float(ep["length"][s & (ep["slide"] == i)].sum())}
                           for i, name in enumerate(slide_names) if (ep["slide"] == i).any()}
    return row


def trajectory(ep: dict, i: int):
    """``(z, x, y)`` of episode ``i`` from its start to its last step."""
    n = int(ep["length"][i])
    return ep["z"][: n + 1, i], ep["x"][: n + 1, i], ep["y"][: n + 1, i]


def learned_policy(network, params, action_mode: str, greedy: bool, declare: tuple[int, int] | None = None):
    """The checkpoint's policy for :func:`run_episodes`: greedy or sampled; a
    :class:`RecurrentActorCritic` or :class:`RecurrentCellSetActorCritic` gives a recurrent policy whose
    memory is the GRU state (zeros at the episode's start, as in training). A cell-set reader's per-slide
    cell keys are computed once here (:func:`~baselines.networks.rollout_apply`), not at every step.

    ``declare = (no tumour, tumour)`` action indices (a discrete actor-critic of
    ``task="classification"``): the policy is recurrent (its memory ``(GRU state or (), score)``)
    and keeps its own **tumour score** of each step, ``p(tumour) / (p(tumour) + p(no tumour))`` of
    its action distribution; at an episode's end (memory frozen) that is the score at the step it
    declared, or at its last step."""
    recurrent = isinstance(network, (RecurrentActorCritic, RecurrentCellSetActorCritic))
    # the params are fixed: a cell-set reader's per-slide cell keys are computed once, not at every step
    step_recurrent = rollout_step(network, params) if recurrent else None
    forward = rollout_apply(network, params) if not recurrent and not isinstance(network, QNetwork) else None

    def act(key, obs, h):
        obs = preprocess_obs(obs)
        if isinstance(network, QNetwork):
            return network.apply(params, obs).argmax(-1), h, None
        if recurrent:
            first = jnp.zeros(jax.tree.leaves(obs)[0].shape[0], bool)  # h starts at zeros already
            h, pi, _ = step_recurrent(h, obs, first)
        else:
            pi, _ = forward(obs)
        return (policy_mode(pi, action_mode) if greedy else policy_sample(key, pi, action_mode)), h, pi

    initial_h = (lambda n: ScannedGRU.initial_state(n, network.hidden)) if recurrent else (lambda n: ())
    if declare is not None:
        if isinstance(network, QNetwork) or not policy_is_discrete(action_mode):
            raise ValueError("declare= needs a discrete actor-critic")
        no, yes = declare

        def scoring_policy(key, obs, memory):
            action, h, pi = act(key, obs, memory[0])
            return action, (h, jax.nn.sigmoid(pi[:, yes] - pi[:, no]))
        scoring_policy.initial_memory = lambda n: (initial_h(n), jnp.full(n, 0.5, jnp.float32))
        return scoring_policy
    if recurrent:
        def recurrent_policy(key, obs, h):
            action, h, _ = act(key, obs, h)
            return action, h
        recurrent_policy.initial_memory = initial_h
        return recurrent_policy
    return lambda key, obs: act(key, obs, ())[0]


def seeds_policy(make_policy, params_seeds, num_seeds: int):
    """One policy for :func:`run_episodes` over ``num_seeds × E`` episodes from ``make_policy(params)``
    (:func:`learned_policy` of one seed's parameters): episode block ``s`` (episodes ``s E`` to
    ``(s + 1) E − 1``) acts with seed ``s``'s parameters (``params_seeds`` stacked on axis 0), all
    seeds vmapped in one program. Recurrent policies keep their memory per episode as before."""
    split = lambda a: a.reshape(num_seeds, a.shape[0] // num_seeds, *a.shape[1:])  # noqa: E731
    merge = lambda a: a.reshape(a.shape[0] * a.shape[1], *a.shape[2:])  # noqa: E731
    probe = make_policy(jax.tree.map(lambda a: a[0], params_seeds))
    if hasattr(probe, "initial_memory"):
        def policy(key, obs, memory):
            def one(p, k, o, m):
                return make_policy(p)(k, o, m)
            a, m = jax.vmap(one)(params_seeds, jax.random.split(key, num_seeds), jax.tree.map(split, obs),
                                 jax.tree.map(split, memory))
            return merge(a), jax.tree.map(merge, m)
        policy.initial_memory = probe.initial_memory
        return policy

    def policy(key, obs):
        a = jax.vmap(lambda p, k, o: make_policy(p)(k, o))(params_seeds, jax.random.split(key, num_seeds),
                                                         jax.tree.map(split, obs))
        return merge(a)
    return policy


def network_for(config: dict, env):
    space = env.action_space()
    if config.get("algo") == "dqn" or "buffer_size" in config:
        return QNetwork(space.n, hidden=config["hidden"])
    return make_network(config, env, RecurrentActorCritic if config.get("algo") == "ppo_rnn" else ActorCritic)


def eval_env(config: dict, slide=None, augment: bool = False):
    """``(config, (env, env_params))``: the checkpoint's env as :func:`evaluate` runs it — on
    ``slide`` when given (it replaces a training dataset), without auto-reset, without training-time
    view augmentation unless ``augment``, and with reading tracked
    (:func:`histojax.reading.tables.with_tracking`) for the efficiency metrics."""
    config = {**config, "slide": slide if slide is not None else config.get("slide")}
    if config.get("env_kwargs"):
        drop = {"augment"} if not augment else set()
        if slide is not None:  # a given slide replaces a training dataset
            drop |= {"dataset", "split", "fold", "slides", "slide_weights"}
        config["env_kwargs"] = {k: v for k, v in config["env_kwargs"].items() if k not in drop}
    return config, reading_tables.with_tracking(*common.make_env(config, auto_reset=False))


def evaluate(config: dict, params, slide=None, num_episodes: int = 256, seed: int = 0, out: Path | None = None,
             label: str = "learned", augment: bool = False, references: bool = True, source=None,
             progress: bool = False, warnings: list | None = None, head=None, head_reward: dict | None = None) -> dict:
    """Rows for the learned policy (greedy and sampled; seeds pooled), the random agent and the
    scripted policy (``references=False``: without these two) on one slide; writes trajectory
    pictures and reading maps to ``out`` when given (:func:`write_pictures`). Training-time view
    augmentation (``env_kwargs["augment"]``) is switched off unless ``augment=True``: a slide is
    evaluated as it is. ``source``: the run folder, named when its parameters do not fit the network
    its config describes; ``progress``: a line on stderr per policy as it runs. A warning when the slides
    cannot be scored (:func:`split_warnings`) is printed with ``progress`` and appended to ``warnings``.

    ``head`` (a :class:`histojax.reading.heads.logit.SlideHead`): **the head declares** — every row's episodes run in the
    env wrapped in :class:`histojax.adapters.head_reward.HeadReward` (``head_reward``: the run's reward settings
    ``gain``, ``final``, ``read_cost`` from its ``head_reward.json``, so the return is the one it trained
    for; without them the env's own reward), the policy only chooses where to read (its declaring
    actions just stop the reading), and at each episode's end the head scores the finest views read:
    ``success`` is the head's diagnosis right, ``diagnosis_auc`` the AUC of its score and
    ``diagnosis_auc_no_itc`` the same without ITC-only slides (when every tumour slide's lesion class is
    known, :func:`lesion_classes`). Episode ``e`` of each policy reads slide ``e mod S``: every slide
    equally often."""
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be at least 1, got {num_episodes}")
    config, (env, env_params) = eval_env(config, slide, augment)
    names = [Path(b.path).name for b in env.bundles]
    picture_env, classes = env, None
    if head is not None:
        env, classes = head_env(env, env_params, head, head_reward)
    mode = config["action_mode"]
    key = jax.random.PRNGKey(seed)
    rows, episodes = {}, {}
    params_seeds = params
    num_seeds = jax.tree.leaves(params)[0].shape[0] if params is not None else 0
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)  # noqa: E731
    base = env
    while not hasattr(base, "task") and hasattr(base, "_env"):
        base = base._env
    for w in split_warnings(env, env_params, getattr(base, "task", "detection"),
                            f"{len(names)} slide{'s' if len(names) > 1 else ''} ({', '.join(names[:3])}"
                            f"{', ...' if len(names) > 3 else ''})"):
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
            policy = seeds_policy(lambda p: learned_policy(network, p, mode, greedy, declare=declare),
                                  params_seeds, num_seeds)
            check_fits(policy, env, env_params, num_seeds, config, source)
            say(f"  {label} ({name}): {num_episodes * num_seeds} episodes ...")
            ep = episodes_of(policy, jax.random.fold_in(key, 100), num_episodes * num_seeds)
            if declare is not None:  # the policy's p(tumour) at its decision, and the slides' labels
                ep["tumour_score"] = np.asarray(ep.pop("final_memory")[1], np.float64)
                ep["label"] = episode_labels(env_params, ep["slide"])
                ep.pop("final_state")
            per_seed = [{k: v[..., s * num_episodes:(s + 1) * num_episodes] for k, v in ep.items()}
                        for s in range(num_seeds)]
            pooled = {k: np.concatenate([e[k] for e in per_seed], axis=-1) for k in per_seed[0]}
            row = summarise(pooled, names)
            row["success_rate_per_seed"] = [summarise(e)["success_rate"] for e in per_seed]
            row["per_seed"] = [summarise(e, names) for e in per_seed]
            rows[f"{label} ({name})"] = row
            episodes[f"{label} ({name})"] = pooled
    if not references:
        return rows
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
        write_pictures(picture_env, env_params, episodes, Path(out), config["env_id"])
    return rows


def head_env(env, env_params, head, settings: dict | None = None):
    """``(env wrapped in HeadReward, lesion classes per slide or None)`` for :func:`evaluate` with a head.
    ``settings``: ``gain``, ``final``, ``read_cost`` of a run's ``head_reward.json`` (None: no head reward
    terms, the env's own reward). ``ValueError`` (one line) when the slides' features do not carry the
    head's view logit."""
    from histojax.adapters.head_reward import HeadReward

    encoders = sorted({str((b.metadata.get("features") or {}).get("encoder")) for b in env.bundles} - {"None"})
    if head.encoder and any(e != head.encoder for e in encoders):
        raise ValueError(f"a slide head for {head.encoder} features; these slides hold {', '.join(encoders)} features "
                         "(fit a head on them: python -m baselines.reading.head_fit)")
    features = getattr(env_params.slide, "features", None)
    dim = int(np.shape(features)[-1]) if features is not None else 0
    if head.dim >= dim:
        raise ValueError(f"the slide head reads feature entry {head.dim} ({head.encoder or 'its encoder'}'s view "
                         f"logit); these slides' features have {dim} entries: score slides embedded with "
                         f"{head.encoder or 'the encoder the head was fitted on'}")
    if settings:
        gain = settings.get("gain")
        wrapped = HeadReward(env, head, gain=None if gain in (None, "none", False) else gain,
                             final=float(settings.get("final") or 0.0), read_cost=float(settings.get("read_cost") or 0.0),
                             params=env_params)
    else:
        wrapped = HeadReward(env, head, gain=None, final=0.0, env_reward=True, params=env_params)
    return wrapped, lesion_classes(env, env_params)


def head_scored(ep: dict, env_params, classes) -> dict:
    """:func:`run_episodes` output of a :class:`~histojax.adapters.head_reward.HeadReward` env with the head's
    diagnosis in the fields :func:`summarise` scores: ``tumour_score`` (the head's p(tumour) of what was
    read), ``label``, ``success`` (the head right) and, with ``classes``, ``lesion`` per episode."""
    ep["tumour_score"] = 1.0 / (1.0 + np.exp(-np.asarray(ep["head_score"], np.float64)))
    ep["label"] = episode_labels(env_params, ep["slide"])
    ep["success"] = np.asarray(ep["head_correct"], bool)
    if classes is not None:
        ep["lesion"] = np.asarray(classes)[ep["slide"]]
    return ep


def lesion_classes(env, env_params) -> list[str] | None:
    """CAMELYON's lesion class of each slide of ``env`` (``normal``, ``ITC``, ``micro``, ``macro``:
    :func:`baselines.reading.lesions.lesion_of` on the bundle's tumour polygons at its µm/px), or None when a tumour
    slide's class cannot be known (no polygons, no µm/px)."""
    from data_tools.annotations import load_annotations
    from baselines.reading.lesions import lesion_of

    labels = np.atleast_1d(np.asarray(jax.device_get(env_params.slide.slide_label))).astype(int)
    out = []
    for bundle, label in zip(env.bundles, np.broadcast_to(labels, (len(env.bundles),))):
        if not label:
            out.append("normal")
            continue
        folder = Path(bundle.path)
        try:
            mpp = float(json.loads((folder / "metadata.json").read_text())["source"]["mpp"])
            geom = load_annotations(folder / "annotations.geojson").tumour
        except (OSError, ValueError, KeyError, TypeError, HistojaxDataError):
            return None
        cls, _ = lesion_of(geom, mpp) if np.isfinite(mpp) and mpp > 0 else ("unknown", None)
        if cls == "unknown":
            return None
        out.append(cls)
    return out


def check_fits(policy, env, env_params, num_seeds: int, config: dict, source=None) -> None:
    """Trace (no compute) ``policy`` on one observation per seed: parameters that do not fit the network
    the config describes (``hidden``, ``action_mode``, the env's spaces changed since training) raise
    ``HistojaxDataError`` naming the checkpoint, not a flax traceback."""
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    try:
        def probe():
            obs, _ = jax.vmap(env.reset, in_axes=(0, None))(keys, env_params)
            if hasattr(policy, "initial_memory"):
                return policy(keys[0], obs, policy.initial_memory(num_seeds))
            return policy(keys[0], obs)
        jax.eval_shape(probe)
    except Exception as e:  # flax's ScopeParamShapeError, KeyError of a missing layer, ...: no common base
        where = Path(source) / "params.msgpack" if source is not None else "the checkpoint"
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise HistojaxDataError(where, f"its parameters do not fit the network its config.json describes "
                                f"(algo {config.get('algo', 'ppo')}, hidden={config.get('hidden')}, action_mode="
                                f"{config.get('action_mode')!r}, on {config.get('env_id')}): {first[:300]}") from e


def _tag(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "")


def _shown_episode(ep: dict, among=None) -> int:
    """The episode a picture shows: the first successful one (of ``among``, default all), else the first."""
    among = np.arange(ep["success"].size) if among is None else np.asarray(among)
    hit = among[ep["success"][among].astype(bool)]
    return int(hit[0] if hit.size else among[0])


def write_pictures(env, env_params, episodes: dict, out: Path, env_id: str) -> list[Path]:
    """For every policy of ``episodes`` (:func:`run_episodes` output by name): ``trajectory_<policy>.png`` of
    one episode on its own slide (the first that reached its target, else the first), ``trajectory.gif`` of
    the first policy's, and reading maps ``reading_<policy>_tumour.png`` / ``_normal.png`` (where it read on
    the first episode of a tumour and of a normal slide, with its tumour score when it has one). Returns
    the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, ep in episodes.items():
        i = _shown_episode(ep)
        z, x, y = trajectory(ep, i)
        s = int(ep["slide"][i])
        path = out / f"trajectory_{_tag(name)}.png"
        render_trajectory(env, z, x, y, path=path, slide_index=s,
                          title=f"{env_id}, {name}, {len(z) - 1} steps, "
                                f"target {'reached' if ep['success'][i] else 'not reached'}")
        written.append(path)
        known = getattr(env_params.slide, "slide_label", None) is not None
        labels = episode_labels(env_params, ep["slide"]) if known else np.full(ep["slide"].shape, -1)
        for label, kind in ((1, "tumour"), (0, "normal"), (-1, "slide")):  # -1: slides without a label
            on = np.flatnonzero(labels == label)
            if not on.size:
                continue
            j = int(on[0])
            score = float(ep["tumour_score"][j]) if "tumour_score" in ep else \
                ("target reached" if ep["success"][j] else "target not reached")
            path = out / f"reading_{_tag(name)}_{kind}.png"
            render_reading_map(env, env_params, {"z": ep["z"][:, j], "x": ep["x"][:, j], "y": ep["y"][:, j],
                                                 "length": ep["length"][j]},
                               slide_index=int(ep["slide"][j]), score=score, path=path, title=f"{env_id}, {name}")
            written.append(path)
    first = next(iter(episodes))
    ep = episodes[first]
    i = _shown_episode(ep)
    written.append(animate(env, *trajectory(ep, i), out / "trajectory.gif", slide_index=int(ep["slide"][i]),
                           params=env_params))
    return written


def _usage_exit(message: str) -> SystemExit:
    """A ``SystemExit`` with status 2 (a user error) whose text is ``message``, printed as one ``error:`` line."""
    print(f"error: {message}", file=sys.stderr)
    exit_ = SystemExit(message)
    exit_.code = 2
    return exit_


def resolve_slides(slides: list[str], config: dict) -> list[str]:
    """Bundle paths to evaluate: ``slides`` as given, or for ``["held-out"]`` the ``"test"`` list of
    the ``dataset.json`` the checkpoint was trained on (``config["env_kwargs"]["dataset"]``)."""
    if list(slides) != ["held-out"]:
        return list(slides)
    dataset = (config.get("env_kwargs") or {}).get("dataset")
    if not dataset:
        raise _usage_exit("--slides held-out: this checkpoint was not trained on a dataset (env_kwargs has no "
                          "'dataset'); give bundle folders instead")
    spec_path = Path(dataset) / "dataset.json"
    try:
        test = json.loads(spec_path.read_text())["test"]
    except (OSError, ValueError, KeyError) as e:
        raise _usage_exit(f"--slides held-out: cannot read the test split from {spec_path}: {e}") from None
    if not test:
        raise _usage_exit(f"--slides held-out: {spec_path} has an empty test split")
    return [str(Path(dataset) / rel) for rel in test]


def with_dataset(config: dict, dataset=None, split: str | None = None) -> dict:
    """``config`` scoring ``split`` of ``dataset`` (default split ``"test"``) in place of the slides it
    trained on; only ``split`` given: the same dataset, another split. Unchanged when neither is given."""
    if dataset is None and split is None:
        return config
    kw = {k: v for k, v in (config.get("env_kwargs") or {}).items() if k not in ("slides", "slide_weights")}
    if dataset is not None:
        if not (Path(dataset) / "dataset.json").is_file():
            raise _usage_exit(f"--dataset {dataset}: no dataset.json there")
        kw["dataset"] = str(dataset)
    elif "dataset" not in kw:
        raise _usage_exit("--split: this checkpoint was not trained on a dataset; give --dataset DIR too")
    kw["split"] = split or "test"
    return {**config, "env_kwargs": kw, "slide": None}


def print_table(title: str, rows: dict, head: str | None = None) -> None:
    """The printed table: per policy episodes, success, mean return / length, steps to success, mean fraction
    of the slide read and fields of view; with a diagnosis score (``diagnosis_auc``), its AUC too, and
    without ITC-only slides (``diagnosis_auc_no_itc``) when known. ``head``: the slide head that declared
    (its name and folder), said under the table."""
    auc = any("diagnosis_auc" in r for r in rows.values())
    no_itc = any("diagnosis_auc_no_itc" in r for r in rows.values())
    print(f"\n{title}")
    print(f"{'policy':<22} {'episodes':>8} {'success':>8} {'mean return':>11} {'mean length':>11} {'steps to success':>16}"
          f" {'read':>6} {'fields':>6}" + (f" {'AUC':>6}" if auc else "") + (f" {'AUC w/o ITC':>11}" if no_itc else ""))
    for name, r in rows.items():
        cell = f" {r['diagnosis_auc']:>6.3f}" if "diagnosis_auc" in r else f" {'-':>6}"
        cell2 = f" {r['diagnosis_auc_no_itc']:>11.3f}" if "diagnosis_auc_no_itc" in r else f" {'-':>11}"
        print(f"{name:<22} {r['episodes']:>8} {r['success_rate']:>8.1%} {r['mean_return']:>11.3f} "
              f"{r['mean_length']:>11.1f} {r['mean_steps_to_success']:>16.1f} {r['mean_fraction_read']:>6.1%} "
              f"{r['mean_fields_of_view']:>6.1f}" + (cell if auc else "") + (cell2 if no_itc else ""))
    if head:
        print(f"the head declares: the policy chooses where to read, then the slide head {head} scores the finest "
              "views read; success: the head's diagnosis was right; AUC: of the head's score over the episodes "
              "(each slide equally often)" + ("; AUC w/o ITC: ITC-only tumour slides left out" if no_itc else "")
              + " (read: mean fraction of the slide's tissue views read)")
    elif auc:
        print("success: the diagnosis declared was right; AUC: of the policy's tumour score over the slides "
              "(read: mean fraction of the slide's tissue views read)")


def add_arguments(p) -> None:
    """The options of ``python -m baselines.evaluate`` and ``histojax evaluate``."""
    p.add_argument("checkpoint", nargs="?", default=None,
                   help="run folder or params.msgpack (omit with --env for reference rows only)")
    p.add_argument("--env", default=None, help="env id (default: the checkpoint's)")
    p.add_argument("--slide", "--slides", nargs="*", default=None,
                   help="bundle folder(s) (default: the checkpoint's slide), or 'held-out': the test split of "
                        "the dataset the checkpoint trained on")
    p.add_argument("--dataset", default=None,
                   help="score on this dataset folder (dataset.json) instead of the one the checkpoint trained on, "
                        "e.g. a published agent on any C16-style dataset")
    p.add_argument("--split", default=None, choices=("train", "test", "all"),
                   help="split of the dataset to score (default: test with --dataset, else the checkpoint's)")
    p.add_argument("--episodes", type=positive_int, default=256,
                   help="episodes per policy (per seed for the learned one), at least 1")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-position", action="store_true", help="(reference rows only) observation with position")
    p.add_argument("--action-mode", default="discrete", help="(reference rows only)")
    p.add_argument("--out", default=None,
                   help="output folder (default <run>/eval, or runs/eval-<run name> for a run inside the installed "
                        "package such as baselines/published/NAME, or runs/eval-<env> without a checkpoint)")
    p.add_argument("--augment", action="store_true",
                   help="keep the checkpoint's training-time view augmentation (default: slides as they are)")
    p.add_argument("--head", default=None,
                   help="slide head folder (histojax.reading.heads) that declares: the policy only chooses where to read, "
                        "the head scores what was read (default: the head a reader trained with SASHA's reward "
                        "names in its head_reward.json; none for other checkpoints)")


def default_out(run: Path | None, env_id: str) -> Path:
    """Where ``evaluate`` writes when ``--out`` is not given: ``<run>/eval`` for a run of the user's;
    ``runs/eval-<run name>`` (under the working folder) for a run inside the package (the published agents)
    or a run folder that is not writable; ``runs/eval-<env id>`` without a checkpoint."""
    import os

    if run is None:
        return Path("runs") / f"eval-{env_id}"
    package = [Path(__file__).resolve().parent, Path(common.__file__).resolve().parents[1] / "histojax"]
    inside = any(run.resolve().is_relative_to(p) for p in package)
    if inside or not os.access(run, os.W_OK):
        return Path("runs") / f"eval-{run.resolve().name}"
    return run / "eval"


# every key a trainer writes into config.json (the trainers' defaults) and the older spellings
def known_config_keys() -> set[str]:
    """The ``config.json`` keys some trainer writes (its defaults), ``seed``, and older spellings."""
    from baselines import dqn, ppo, ppo_rnn

    return {*ppo.DEFAULTS, *dqn.DEFAULTS, *ppo_rnn.DEFAULTS, "seed", *common.OLDER_SPELLINGS}


def check_config(config, path) -> list[str]:
    """Refuse a ``config.json`` that is not an object or whose ``hidden`` is not a positive whole number
    (``HistojaxDataError`` naming ``path``); return one warning per key no trainer writes (a misspelling is
    otherwise ignored without a word), naming the closest known key."""
    import difflib

    if not isinstance(config, dict):
        raise HistojaxDataError(path, f"holds a JSON {type(config).__name__}, not an object of settings "
                                "(the config.json a trainer writes); train again or restore it")
    hidden = config.get("hidden", 256)
    if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 1:
        raise HistojaxDataError(path, f"hidden={hidden!r}: the network width must be a whole number of at least 1")
    mode = config.get("action_mode", "discrete")
    if not isinstance(mode, str):
        raise HistojaxDataError(path, f"action_mode={mode!r}: must be a string such as 'discrete' or 'glimpse:1'")
    if not isinstance(config.get("env_kwargs") or {}, dict):
        raise HistojaxDataError(path, f"env_kwargs={config['env_kwargs']!r}: must be an object of make() settings")
    known = known_config_keys()
    warnings = []
    for key in sorted(set(config) - known):
        close = difflib.get_close_matches(key, sorted(known), n=1)
        warnings.append(f"{path}: unknown key {key!r} ignored" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return warnings


def split_warnings(env, env_params, task: str, where: str) -> list[str]:
    """Why a set of slides cannot be scored: a diagnosis needs tumour and normal slides for an AUC; detection
    needs a slide with tumour (no target can be reached on the others)."""
    if getattr(env_params.slide, "slide_label", None) is None:
        return []
    labels = np.asarray(jax.device_get(env_params.slide.slide_label)).ravel()
    n = labels.size
    if task == "classification" and len(set(labels.tolist())) < 2:
        kind = "tumour" if labels.size and labels[0] else "normal"
        return [f"{where}: all {n} slide{'s' if n > 1 else ''} {'are' if n > 1 else 'is'} {kind}: the diagnosis AUC "
                "is undefined (it needs tumour and normal slides); only the accuracy of the declared diagnosis "
                "means something"]
    if task != "classification" and not labels.any():
        return [f"{where}: no slide here has tumour annotated: no policy can reach a target, so every success "
                "rate is 0 % by construction; score a split with tumour slides"]
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
    t_kw, s_kw = trained.get("env_kwargs") or {}, scored.get("env_kwargs") or {}
    t_ds, s_ds = t_kw.get("dataset"), s_kw.get("dataset")
    if not t_ds or not s_ds:
        return []
    t_split, s_split = t_kw.get("split", "train"), s_kw.get("split", "train")
    overlap = s_split == "all" or t_split == "all" or s_split == t_split
    t_rec, s_rec = _dataset_record(t_ds), _dataset_record(s_ds)
    same = Path(t_ds).resolve() == Path(s_ds).resolve()
    c16 = lambda rec, env_id="": "CAMELYON16" in str(rec.get("kind", "")) or "-C16-" in env_id  # noqa: E731
    out = []
    if overlap and (same or (c16(s_rec) and c16(t_rec, str(trained.get("env_id", ""))))):
        why = "the same dataset" if same else ("a CAMELYON16 set: its split is fixed by slide, so its "
                                               f"{s_split} split holds slides this agent trained on")
        out.append(f"{config_path}: trained on the {t_split} split of {t_ds}; scored on the {s_split} split of "
                   f"{s_ds} ({why}): these figures are not held-out; score --split test")
    t_mpp, s_mpp = (t_rec.get("scale") or {}).get("mpp"), (s_rec.get("scale") or {}).get("mpp")
    if t_mpp and s_mpp and abs(float(t_mpp) - float(s_mpp)) > 1e-6 * float(t_mpp):
        out.append(f"{config_path}: trained at {float(t_mpp):.3g} µm/px ({t_ds}); scored at {float(s_mpp):.3g} µm/px "
                   f"({s_ds}): another scale than it trained at")
    elif s_mpp and not t_rec and c16(s_rec):
        out.append(f"{config_path}: its training dataset {t_ds} is not here and config.json records no scale, so the "
                   f"scale cannot be checked: {s_ds} is at {float(s_mpp):.3g} µm/px ({s_rec.get('variant', '?')} "
                   "variant); the published c16-v1 agents trained on the full set (1.94 µm/px)")
    return out


def run(args, parser) -> int:
    """Evaluate on parsed ``args``: tables, eval.json, eval.csv, trajectory pictures and reading maps."""
    if args.checkpoint is None and args.env is None:
        parser.error("give a CHECKPOINT or --env")
    warnings = []
    settings, where = None, None
    if args.checkpoint is not None:
        refuse_not_an_agent(Path(args.checkpoint))
        run = Path(args.checkpoint)
        run = run if run.is_dir() else run.parent
        try:  # a config.json that is not an object is named before loading (which would fail on it in its own words)
            raw = json.loads((run / "config.json").read_text())
        except (OSError, ValueError):
            raw = {}  # unreadable: load_checkpoint names the file and why
        check_config(raw, run / "config.json")
        params, config = common.load_checkpoint(args.checkpoint)
        warnings += check_config(config, run / "config.json")
        check_params_tree(params, run / "params.msgpack")
        label = config.get("algo") or ("dqn" if "buffer_size" in config else "ppo")
        settings, where = head_reward_settings(run, config)
    else:
        params, config, run, label = None, {"action_mode": args.action_mode, "with_position": args.with_position,
                                            "obs_mode": "pixels", "hidden": 256}, None, "none"
    trained = dict(config)
    if args.env:
        config["env_id"] = args.env
    config = with_dataset(config, getattr(args, "dataset", None), getattr(args, "split", None))
    if run is not None:
        warnings += provenance_warnings(trained, config, run / "config.json")
    head, head_dir = None, None
    if getattr(args, "head", None) or settings:
        from histojax.reading import heads

        head_dir = Path(args.head) if getattr(args, "head", None) else resolve_head(settings["head"], run, where)
        head = heads.load(head_dir)  # ValueError naming the file: one line
        recorded = (settings or {}).get("head_name")
        if recorded and not getattr(args, "head", None) and recorded != head.name:
            warnings.append(f"{where}: the reader trained with the head {recorded!r}; the head found at {head_dir} "
                            f"is {head.name!r}")
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    out = Path(args.out) if args.out else default_out(run, config["env_id"])
    slides = resolve_slides(args.slide, config) if args.slide else [config.get("slide")]
    results = {}
    for i, slide in enumerate(slides):
        sub = out if len(slides) == 1 else out / f"slide{i}"
        dataset = (config.get("env_kwargs") or {}).get("dataset")
        name = slide or (f"dataset {dataset} ({(config.get('env_kwargs') or {}).get('split', 'train')} split)"
                         if dataset else "embedded sample slide")
        print(f"evaluating {config['env_id']} on {name} ({i + 1} of {len(slides)}), {args.episodes} episodes per "
              "policy ...", file=sys.stderr, flush=True)
        try:
            rows = evaluate(config, params, slide=slide, num_episodes=args.episodes, seed=args.seed, out=sub,
                            label=label, augment=args.augment, source=run, progress=True, warnings=warnings,
                            head=head, head_reward=settings if not getattr(args, "head", None) else None)
        except ValueError as e:
            raise grid_refusal(e, run) from None
        print_table(f"{config['env_id']} on {name} ({args.episodes} episodes per policy"
                    f"{' per seed' if params is not None else ''})", rows,
                    head=f"{head.name!r} ({head_dir})" if head is not None else None)
        results[name] = rows
    out.mkdir(parents=True, exist_ok=True)
    record = {"env_id": config["env_id"], "results": results, "warnings": warnings}
    if head is not None:
        record["head"] = {"folder": str(head_dir), "name": head.name, "reward": settings}
    outputs.write_text(out / "eval.json", json.dumps(record, indent=2))
    with outputs.open_text(out / "eval.csv") as f:
        w = csv.writer(f)
        w.writerow(["slide", "policy", "episodes", "success_rate", "mean_return", "mean_length", "mean_steps_to_success",
                    "mean_fraction_read", "mean_fields_of_view", "diagnosis_auc", "diagnosis_auc_no_itc"])
        for slide, rows in results.items():
            for name, r in rows.items():
                w.writerow([slide, name, r["episodes"], r["success_rate"], r["mean_return"], r["mean_length"],
                            r["mean_steps_to_success"], r["mean_fraction_read"], r["mean_fields_of_view"],
                            r.get("diagnosis_auc", ""), r.get("diagnosis_auc_no_itc", "")])
    print(f"\nwrote {out}/eval.json, eval.csv, trajectory_*.png, reading_*.png, trajectory.gif")
    return 0


# ----------------------------------------------------------------------------- published readers
SET_READER = "c16-v2-set-reader"  # the published cell-set reader: reads slides of any size
# published folders retired, with what replaced them: `histojax evaluate` on the old path names the new one
RETIRED = {"c16-v1-glimpse-reader": (SET_READER, "a flat glimpse policy over a padded 16 × 14 cell grid, it could "
                                                 "not read a slide wider or taller than that grid")}


def published_path(name: str) -> Path:
    """``baselines/published/NAME``, relative to the working folder when it lies under it."""
    path = PUBLISHED / name
    try:
        return path.relative_to(Path.cwd())
    except ValueError:
        return path


def refuse_not_an_agent(path: Path) -> None:
    """Refuse, in one line saying why and what to use instead, a published folder that was retired
    (:data:`RETIRED`; the folder is gone) and a slide head folder (``histojax.reading.heads``: it scores what a
    reader read, it does not act)."""
    from histojax.reading.heads import HEADS

    name = path.parent.name if path.name == "params.msgpack" else path.name
    if not path.exists() and name in RETIRED:
        new, why = RETIRED[name]
        raise HistojaxDataError(path, f"the published agent {name} was retired ({why}); its results stay in "
                                f"docs/results/c16.md; use {published_path(new)}, which reads slides of any "
                                f"size: histojax evaluate {published_path(new)} --dataset DIR")
    try:
        kind = json.loads((path / "config.json").read_text()).get("kind") if path.is_dir() else None
    except (OSError, ValueError, AttributeError):
        kind = None
    if kind in HEADS:
        raise HistojaxDataError(path, "a slide head, not an agent: it scores what a reader read, it does not act; "
                                f"score a reader through it: histojax evaluate READER --head {path} --dataset DIR "
                                f"(or python -m baselines.reading.readers --head {path} --dataset DIR)")


def grid_refusal(error: ValueError, run) -> ValueError:
    """``error`` of a flat glimpse policy (the ``-v1`` observation, a padded cell grid pinned at training) on
    a slide whose cells do not fit that grid, as one line saying that this policy cannot read it by
    construction and which reader to use instead; any other error unchanged."""
    text = str(error)
    if run is None or "do not fit glimpse_grid" not in text:
        return error
    where = text.split(" (the grid a policy was trained with)")[0]
    set_reader = published_path(SET_READER)
    use = (f"use the cell-set reader, which reads slides of any size: histojax evaluate {set_reader} --dataset DIR"
           if set_reader.is_dir() else
           "use a cell-set reader, which reads slides of any size (the -v2 ids; python -m baselines.reading.train_readers "
           "trains one)")
    return ValueError(f"{where}: {run} is a flat glimpse policy over the padded cell grid it trained on, so it cannot "
                      f"read a slide wider or taller than that grid; {use}")


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
            raise HistojaxDataError(f, "names no slide head (a 'head' folder, as baselines.reading.train_readers writes it); "
                                    "give --head DIR")
        return record, f
    record = config.get("head_reward")
    if isinstance(record, dict) and isinstance(record.get("head"), str) and record["head"]:
        return record, run / "config.json"
    return None, None


def resolve_head(recorded: str, run: Path, where) -> Path:
    """The slide head folder a run names (``recorded``): as given when absolute; else beside the run, in the
    working folder, in the repository, or a published head of that name. ``HistojaxDataError`` naming
    ``where`` (the file that names it) when none holds a ``config.json``."""
    p = Path(recorded)
    tries = [p] if p.is_absolute() else [run / p, p, Path(__file__).resolve().parents[1] / p]
    tries.append(PUBLISHED / p.name)
    for c in tries:
        if (c / "config.json").is_file():
            return c
    raise HistojaxDataError(where, f"names the slide head {recorded!r}, which is not here (looked beside the run, in "
                            "the working folder and in baselines/published); give --head DIR, e.g. --head "
                            f"{published_path('c16-v2-head')}")


def check_params_tree(params, path) -> None:
    """Refuse a checkpoint that holds no parameter arrays stacked over seeds (a foreign msgpack)."""
    leaves = jax.tree.leaves(params) if isinstance(params, dict) else []
    if not leaves or any(np.ndim(a) < 1 for a in leaves) or len({np.shape(a)[0] for a in leaves}) != 1:
        raise HistojaxDataError(path, "not a histojax checkpoint (no network parameters stacked over seeds, as the "
                                "trainers write them); give the params.msgpack of a histojax training run")


def main(argv=None) -> int:
    """``python -m baselines.evaluate``: the same command as ``histojax evaluate`` (errors one line, exit 2)."""
    from histojax.cli import main as histojax_main

    return histojax_main(["evaluate", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
