"""Episodes without auto-reset: one batch of episodes per policy (:func:`run_episodes`), per-episode slides and
read budgets, the per-policy summary (success, return, length, fraction read), and the evaluation env."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from baselines.common.env import make_env
from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError
from data_tools.metrics import accuracy, auc_interval, roc_auc
from histojax.core import seen_views


# ----------------------------------------------------------------------------- rollouts
def run_episodes(env, env_params, policy, key, num_episodes: int, params_axes=None, final: bool = False):
    """``num_episodes`` vmapped episodes (no auto-reset) of ``policy(key, obs_batch) -> actions``,
    or of a recurrent policy (``policy.initial_memory(n)`` defined): ``policy(key, obs_batch,
    memory) -> (actions, memory)``, its memory carried from step to step of each episode and frozen
    once the episode has ended (so it holds what the policy had at the episode's last step).
    Returns numpy ``return, success, length`` and ``slide`` (the slide index of a multi-slide env)
    per episode, ``fraction_read`` and ``fields_of_view`` at its end (NaN / -1 when the env does not
    track reading; see :func:`histojax.core.seen_views.with_tracking`) and the ``(steps+1, E)`` trajectories
    ``z, x, y``: entry 0 the view at reset, entry ``t`` the view after step ``t`` (frozen after the
    episode ended).

    ``params_axes``: ``jax.vmap`` axes of ``env_params`` (default ``None``: one ``env_params`` for
    every episode); e.g. a per-episode slide (``slide.slide_logits (E, S)``) and reading budget
    (``mode_data.read_budget (E,)``), see :func:`per_episode_params`. ``final=True`` also returns
    ``final_state`` (the env states at the episodes' ends) and ``final_memory`` (the policy's
    memory; ``()`` for a feed-forward policy), as pytrees of numpy arrays.

    An env wrapped in :class:`histojax.reading.head_reward.HeadReward` also gives per episode ``head_score``
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
                lambda a, b: jnp.where(done.reshape(-1, *([1] * (a.ndim - 1))), a, b), old, new
            )
            state, obs, memory = keep(state, state2), keep(obs, obs2), keep(memory, memory2)
            read = jnp.where(active, info.get("fraction_read", read), read)
            fields = jnp.where(active, info.get("fields_of_view", fields), fields)
            head = jnp.where(active, info.get("head_score", head), head)
            right = jnp.where(active, info.get("head_correct", right), right)
            done = done | term | trunc
            view = inner(state)
            return ((obs, state, done, ret, length, success, memory), (read, fields, head, right)), (
                view.z,
                view.x,
                view.y,
            )

        memory = policy.initial_memory(num_episodes) if recurrent else ()
        carry = (
            (obs, state, jnp.zeros(num_episodes, bool), zeros, zeros, jnp.zeros(num_episodes, bool), memory),
            (
                jnp.full(num_episodes, jnp.nan, jnp.float32),
                jnp.full(num_episodes, -1, jnp.int32),
                jnp.full(num_episodes, jnp.nan, jnp.float32),
                jnp.zeros(num_episodes, bool),
            ),
        )
        ((_, state, _, ret, length, success, memory), (read, fields, head, right)), (z, x, y) = jax.lax.scan(
            body, carry, jax.random.split(key, max_steps)
        )
        state = inner(state)
        cat = lambda a0, a: jnp.concatenate([a0[None], a])  # noqa: E731
        return (
            ret,
            success,
            length,
            state.slide_index,
            read,
            fields,
            cat(start.z, z),
            cat(start.x, x),
            cat(start.y, y),
            head,
            right,
        ), (state, memory)

    out, (state, memory) = jax.device_get(go(key, env_params))
    names = (
        "return",
        "success",
        "length",
        "slide",
        "fraction_read",
        "fields_of_view",
        "z",
        "x",
        "y",
        "head_score",
        "head_correct",
    )
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


def episode_labels(env_params, slides) -> np.ndarray:
    """The 0/1 slide label of each episode's slide (``slide_label`` of the env's slides)."""
    label = np.asarray(jax.device_get(env_params.slide.slide_label))
    return (np.full(np.shape(slides), int(label)) if label.ndim == 0 else label[np.asarray(slides)]).astype(int)


def slides_interval(auc: float, ep: dict, keep=None) -> tuple[float, float]:
    """The 95 % interval over slides of an AUC over episodes (:func:`data_tools.metrics.auc_interval`): the
    tumour and normal counts are the distinct slides the episodes (where ``keep``) played, not the episodes, since
    an episode again on a slide adds no slide."""
    return auc_interval(auc, *slide_counts(ep, keep))


def slide_counts(ep: dict, keep=None) -> tuple[int, int]:
    """``(tumour, normal)``: the distinct slides of each class the episodes (where ``keep``) played."""
    keep = np.ones(len(ep["label"]), bool) if keep is None else np.asarray(keep, bool)
    slide = np.asarray(ep["slide"] if "slide" in ep else np.arange(len(ep["label"])))[keep]
    label = np.asarray(ep["label"])[keep].astype(bool)
    return len(set(slide[label].tolist())), len(set(slide[~label].tolist()))


def summarise(ep: dict, slide_names=None) -> dict:
    """Episodes, success rate, mean return, mean length and mean steps to success (over the
    successful episodes) of :func:`run_episodes`' output; with ``slide_names`` (one per slide of a
    multi-slide env) also ``by_slide``: ``{name: {"episodes", "successes"}}`` for the slides drawn."""
    s = ep["success"].astype(bool)
    row = {
        "episodes": int(s.size),
        "success_rate": float(s.mean()),
        "mean_return": float(ep["return"].mean()),
        "mean_length": float(ep["length"].mean()),
        "mean_steps_to_success": float(ep["length"][s].mean()) if s.any() else float("nan"),
        "mean_fraction_read": float(np.mean(ep["fraction_read"])) if "fraction_read" in ep else float("nan"),
        "mean_fields_of_view": float(np.mean(ep["fields_of_view"])) if "fields_of_view" in ep else float("nan"),
    }
    if "tumour_score" in ep:  # diagnosis: AUC of the policy's p(tumour), accuracy of thresholding it at 0.5
        row["diagnosis_auc"] = roc_auc(ep["tumour_score"], ep["label"])
        row["diagnosis_auc_low"], row["diagnosis_auc_high"] = slides_interval(row["diagnosis_auc"], ep)
        row["diagnosis_tumour_slides"], row["diagnosis_normal_slides"] = slide_counts(ep)
        row["score_accuracy"] = accuracy(ep["tumour_score"], ep["label"])
    if "lesion" in ep:  # ITC-only slides left out (CAMELYON's isolated tumour cells)
        keep = ep["lesion"] != "ITC"
        row["diagnosis_auc_no_itc"] = roc_auc(ep["tumour_score"][keep], ep["label"][keep])
        row["diagnosis_auc_no_itc_low"], row["diagnosis_auc_no_itc_high"] = slides_interval(
            row["diagnosis_auc_no_itc"], ep, keep
        )
    if slide_names is not None and len(slide_names) > 1:
        row["by_slide"] = {
            name: {
                "episodes": int((ep["slide"] == i).sum()),
                "successes": int(s[ep["slide"] == i].sum()),
                "steps_to_success_sum": float(ep["length"][s & (ep["slide"] == i)].sum()),
            }
            for i, name in enumerate(slide_names)
            if (ep["slide"] == i).any()
        }
    return row


def trajectory(ep: dict, i: int):
    """``(z, x, y)`` of episode ``i`` from its start to its last step."""
    n = int(ep["length"][i])
    return ep["z"][: n + 1, i], ep["x"][: n + 1, i], ep["y"][: n + 1, i]


def eval_env(config, slide=None, augment: bool = False):
    """``(config, (env, env_params))``: the checkpoint's env as :func:`evaluate` runs it — on
    ``slide`` when given (it replaces a training dataset), without auto-reset, without training-time
    view augmentation unless ``augment``, and with reading tracked
    (:func:`histojax.core.seen_views.with_tracking`) for the efficiency metrics. ``config``: the run's typed config
    or its record (:func:`baselines.run_config.read_run_config`); the typed config of that env comes back."""
    config = read_run_config(config)
    config = config.replace(slide=slide if slide is not None else config.slide)
    if config.env_kwargs:
        drop = {"augment"} if not augment else set()
        if slide is not None:  # a given slide replaces a training dataset
            drop |= {"dataset", "split", "fold", "slides", "slide_weights"}
        config = config.replace(env_kwargs={k: v for k, v in config.env_kwargs.items() if k not in drop})
    return config, seen_views.with_tracking(*make_env(config, auto_reset=False))


def check_fits(policy, env, env_params, num_seeds: int, config, source=None) -> None:
    """Trace (no compute) ``policy`` on one observation per seed: parameters that do not fit the network
    the config describes (``hidden``, ``action_mode``, the env's spaces changed since training) raise
    ``HistojaxDataError`` naming the checkpoint, not a flax traceback."""
    config = read_run_config(config)
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
        raise HistojaxDataError(
            where,
            f"its parameters do not fit the network its config.json describes "
            f"(algo {config.algo}, hidden={getattr(config, 'hidden', None)}, action_mode="
            f"{config.action_mode!r}, on {config.env_id}): {first[:300]}",
        ) from e
