"""The policies an evaluation scores and the reading commands roll: the reference policies (scripted coarse-to-fine on pixels or features,
the coarse-map follower) and a checkpoint's learned policy (greedy or sampled, pooled over its seeds), each a
``policy(key, obs)`` (or ``policy(key, obs, memory)`` for a recurrent one) of a batch of observations."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from baselines.cell_set_networks import RecurrentCellSetActorCritic
from baselines.dqn import DQNConfig
from baselines.networks import (
    ActorCritic,
    QNetwork,
    RecurrentActorCritic,
    ScannedGRU,
    policy_mode,
    policy_sample,
    preprocess_obs,
    rollout_apply,
    rollout_step,
)
from baselines.networks import is_discrete as policy_is_discrete
from baselines.ppo import make_network
from baselines.run_config import read_run_config
from data_tools.features import pcam_cnn
from histojax.core import actions


# ----------------------------------------------------------------------------- scripted policy
def stain_offset(pixels, grid: int = 4, sharpen: float = 4.0):
    """Where the darkest stain of one view ``(T, T, 3)`` lies: the score ``1 − (R + G) / 510``
    (H&E: haematoxylin-rich purple epithelium is dark in red and green; white background and pink
    stroma score low), averaged over a ``grid × grid`` of cells, raised to ``sharpen`` and
    turned into a centroid offset ``(ox, oy)`` from the view centre, in view widths (±0.5)."""
    t = pixels.shape[0]
    score = 1.0 - (pixels[..., 0] + pixels[..., 1]) / 510.0
    cells = score.reshape(grid, t // grid, grid, t // grid).mean(axis=(1, 3))
    w = cells**sharpen + 1e-6
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
        move = jnp.where(
            jnp.abs(ox) >= jnp.abs(oy),
            jnp.where(ox > 0, actions.RIGHT, actions.LEFT),
            jnp.where(oy > 0, actions.DOWN, actions.UP),
        )
        rand_move = jax.random.randint(k1, (), 0, 4)
        centred_action = jnp.where(finest, rand_move, actions.ZOOM_IN)
        a = jnp.where(is_centred, centred_action, move)
        return jnp.where(jax.random.uniform(k2) < epsilon, jax.random.randint(k3, (), 0, 7), a).astype(jnp.int32)
    zoom = jnp.where(is_centred & ~jnp.asarray(finest), 1.0, 0.0)
    jitter = jax.random.uniform(k1, (2,), minval=-0.5, maxval=0.5) * is_centred * jnp.asarray(finest)
    return jnp.stack([2 * ox + jitter[0], 2 * oy + jitter[1], zoom])


def scripted_features_policy(
    key, obs, tumour_index: int = pcam_cnn.VIEW_LOGIT, threshold: float = 1.0, epsilon: float = 0.1
):
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
    toward = jnp.where(
        jnp.abs(dx) >= jnp.abs(dy),
        jnp.where(dx > 0, actions.RIGHT, actions.LEFT),
        jnp.where(dy > 0, actions.DOWN, actions.UP),
    )
    k1, k2, k3 = jax.random.split(key, 3)
    wander = jax.random.randint(k1, (), 0, 4)
    at_finest = jnp.where(far, actions.ZOOM_OUT, jnp.where(inside, wander, toward))
    above = jnp.where(far & (level > travel_level + 1e-6), actions.ZOOM_OUT, jnp.where(inside, actions.ZOOM_IN, toward))
    a = jnp.where(finest, at_finest, above)
    return jnp.where(jax.random.uniform(k2) < epsilon, jax.random.randint(k3, (), 0, 4), a).astype(jnp.int32)


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

            a, m = jax.vmap(one)(
                params_seeds, jax.random.split(key, num_seeds), jax.tree.map(split, obs), jax.tree.map(split, memory)
            )
            return merge(a), jax.tree.map(merge, m)

        policy.initial_memory = probe.initial_memory
        return policy

    def policy(key, obs):
        a = jax.vmap(lambda p, k, o: make_policy(p)(k, o))(
            params_seeds, jax.random.split(key, num_seeds), jax.tree.map(split, obs)
        )
        return merge(a)

    return policy


def network_for(config, env):
    """The network of a run's config (typed, or its record: :func:`baselines.run_config.read_run_config`) sized for
    ``env``: a :class:`QNetwork` of ``hidden`` units for a DQN run, else PPO's actor-critic (recurrent for
    ``ppo_rnn``; the cell-set reader on a ``step_obs`` glimpse env, :func:`baselines.ppo.make_network`)."""
    config = read_run_config(config)
    space = env.action_space()
    if isinstance(config, DQNConfig):
        return QNetwork(space.n, hidden=config.hidden)
    return make_network(config, env, RecurrentActorCritic if config.algo == "ppo_rnn" else ActorCritic)
