"""Small networks for the baselines (flax.linen), sized to train on a CPU.

* :class:`Torso` — observation → feature vector. Pixels ``(B, H, W, 3)`` (uint8 or float) are
  average-pooled to ``POOLED_SIZE`` (32) px a side first (4× for the 128-px views), scaled to
  ``[0, 1]`` and go through three small 2×2 stride-2 convolutions; vector observations go through an
  MLP. A dict observation sends ``"pixels"`` through the CNN and concatenates every other entry
  (``"position"``, feature vectors, …) flattened, after the CNN.
* :class:`ActorCritic` — torso + policy head (categorical logits for discrete actions, a
  diagonal Gaussian mean with a state-independent log-std for continuous ones) + value head.
* :class:`RecurrentActorCritic` — torso + a GRU over time (hidden state reset at episode starts)
  + the same heads, for ``baselines.ppo_rnn``.
* :class:`QNetwork` — torso + one Q-value per discrete action.

Every module but the recurrent one takes observations with exactly one leading batch axis. Distributions are tiny
pure functions here (no distrax dependency). The reader networks over a set of cells (``glimpse`` with
``step_obs=True``) are :mod:`baselines.cell_set_networks`; the rollout helpers here (:func:`rollout_apply`,
:func:`rollout_step`, :func:`rollout_sampler`) serve both.
"""

from __future__ import annotations

import functools
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

POOLED_SIZE = 32


def pool_pixels(x: jax.Array, size: int = POOLED_SIZE) -> jax.Array:
    """Average-pool ``(B, H, W, C)`` pixels down to ``size`` px a side (float32, same scale as
    the input). A no-op on pixels already ``size`` px a side; ``H`` must be a multiple of it."""
    x = jnp.asarray(x, jnp.float32)
    h, w = x.shape[-3], x.shape[-2]
    if h == size and w == size:
        return x
    if h % size or w % size:
        raise ValueError(f"pixels {h}x{w} are not a multiple of {size}")
    fh, fw = h // size, w // size
    x = x.reshape(*x.shape[:-3], size, fh, size, fw, x.shape[-1])
    return x.mean(axis=(-4, -2))


def preprocess_obs(obs):
    """What replay buffers store: pixels pooled to ``POOLED_SIZE`` and rounded back to uint8
    (16× smaller for 128-px views; the torso's first step is the same pooling, so the network
    sees the same input up to rounding). Vector entries pass through."""

    def one(x):
        x = jnp.asarray(x)
        if x.ndim >= 4 and x.dtype == jnp.uint8:
            return jnp.round(pool_pixels(x)).astype(jnp.uint8)
        return x

    if isinstance(obs, dict):
        return {k: (one(v) if k == "pixels" else v) for k, v in obs.items()}
    return one(obs)


def _pixels_to_float(x):
    scale = 1.0 / 255.0 if x.dtype == jnp.uint8 else 1.0
    return pool_pixels(x) * scale


def space_to_depth(x: jax.Array, block: int = 2) -> jax.Array:
    """``(B, H, W, C) -> (B, H/block, W/block, block*block*C)``: each block×block patch as one vector."""
    b, h, w, c = x.shape
    x = x.reshape(b, h // block, block, w // block, block, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(b, h // block, w // block, block * block * c)


class CNN(nn.Module):
    """Pooled pixels (32 px) → three 2×2 stride-2 convolutions (32 → 16 → 8 → 4 px) → dense.

    Each convolution is written as space-to-depth + a dense layer (the same function as
    ``nn.Conv(c, (2, 2), strides=2)``): on XLA's CPU backend, convolution gradients inside
    ``lax.scan`` / ``while`` loops run ~10-80× slower than outside them, while a matmul does not,
    and the whole PPO run is one loop."""

    channels: Sequence[int] = (32, 64, 64)
    hidden: int = 256

    @nn.compact
    def __call__(self, x):
        x = _pixels_to_float(x)
        x = x - 0.5
        for c in self.channels:
            x = nn.relu(nn.Dense(c, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(space_to_depth(x)))
        x = x.reshape(x.shape[0], -1)
        return nn.relu(nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))


class MLP(nn.Module):
    hidden: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.tanh(nn.Dense(h, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
        return x


def is_discrete(action_mode: str) -> bool:
    """True for the action modes with a ``Discrete`` space: ``"discrete"``, ``"glimpse[:LEVEL]"`` and
    ``"zoom_select[:K]"`` (see :mod:`histojax.core.modes.factory`); the others are continuous."""
    return action_mode.partition(":")[0] in ("discrete", "glimpse", "zoom_select")


def _flat(x):
    x = jnp.asarray(x, jnp.float32)
    return x.reshape(x.shape[0], -1)


def normalise_features(obs, obs_norm):
    """``obs`` with its feature vector (the ``"features"`` entry of a dict observation, or a flat
    ``(B, D)`` array) standardised by a fixed ``obs_norm = (mean (D,), std (D,))`` (tuples, see
    :func:`baselines.ppo.dataset_normaliser`); ``obs`` unchanged when ``obs_norm`` is None."""
    if obs_norm is None:
        return obs
    mean, std = (jnp.asarray(v, jnp.float32) for v in obs_norm)

    def norm(x):
        return (jnp.asarray(x, jnp.float32) - mean) / std

    if isinstance(obs, dict):
        return {k: (norm(v) if k == "features" else v) for k, v in obs.items()}
    obs = jnp.asarray(obs)
    return norm(obs) if obs.ndim == 2 and obs.shape[-1] == mean.shape[0] else obs


class Torso(nn.Module):
    """Observation (array or dict, one leading batch axis) → features. See the module doc.
    ``obs_norm``: a fixed normaliser of feature observations (:func:`normalise_features`)."""

    hidden: int = 256
    obs_norm: tuple | None = None

    @nn.compact
    def __call__(self, obs):
        obs = normalise_features(obs, self.obs_norm)
        if isinstance(obs, dict):
            parts, vectors = [], []
            for k in sorted(obs):
                if k == "pixels":
                    parts.append(CNN(hidden=self.hidden)(obs[k]))
                else:
                    vectors.append(_flat(obs[k]))
            if vectors:
                v = jnp.concatenate(vectors, axis=-1)
                if parts:  # pixels + small vectors: join after the CNN, one more dense layer
                    x = jnp.concatenate(parts + [v], axis=-1)
                    return nn.relu(nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
                return MLP((self.hidden, self.hidden))(v)
            return parts[0]
        obs = jnp.asarray(obs)
        if obs.ndim == 4:
            return CNN(hidden=self.hidden)(obs)
        return MLP((self.hidden, self.hidden))(_flat(obs))


class ActorCritic(nn.Module):
    """Shared torso; ``__call__(obs) -> (policy parameters, value)``: logits ``(B, A)`` for
    ``action_mode="discrete"``, ``(mean (B, A), log_std (A,))`` for ``"continuous"``."""

    action_dim: int
    action_mode: str = "discrete"
    hidden: int = 256
    obs_norm: tuple | None = None

    @nn.compact
    def __call__(self, obs):
        return policy_value_heads(self, Torso(self.hidden, self.obs_norm)(obs))


def policy_value_heads(module: nn.Module, h: jax.Array):
    """The actor and critic heads of ``module`` (an :class:`ActorCritic`-like module with
    ``action_dim``, ``action_mode``, ``hidden``), called from inside its compact ``__call__`` on
    features ``h (..., F)``: ``(policy parameters, value (...))`` as :class:`ActorCritic` returns.
    Shared by the feed-forward and the recurrent actor-critic (same parameter names)."""
    a = nn.tanh(nn.Dense(module.hidden // 2, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(h))
    c = nn.tanh(nn.Dense(module.hidden // 2, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(h))
    value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0))(c)[..., 0]
    out = nn.Dense(module.action_dim, kernel_init=nn.initializers.orthogonal(0.01), bias_init=nn.initializers.zeros)(a)
    if is_discrete(module.action_mode):
        return out, value
    log_std = module.param("log_std", nn.initializers.constant(-0.5), (module.action_dim,))
    return (out, log_std), value


class ScannedGRU(nn.Module):
    """A GRU over a time-major sequence (``nn.scan`` of ``nn.GRUCell``, PureJaxRL ``ppo_rnn``
    style): ``(h (B, H), (x (T, B, F), resets (T, B) bool)) -> (h_T, outputs (T, B, H))``. Where
    ``resets[t, b]`` is true the hidden state of env ``b`` is set to zeros *before* step ``t``
    reads ``x[t, b]`` (``x[t]`` is the first observation of a new episode)."""

    hidden: int

    @functools.partial(nn.scan, variable_broadcast="params", split_rngs={"params": False}, in_axes=0, out_axes=0)
    @nn.compact
    def __call__(self, h, inputs):
        x, resets = inputs
        h = jnp.where(resets[:, None], jnp.zeros_like(h), h)
        h, y = nn.GRUCell(features=self.hidden)(h, x)
        return h, y

    @staticmethod
    def initial_state(batch: int, hidden: int) -> jax.Array:
        """The hidden state of a fresh episode: zeros ``(batch, hidden)`` float32."""
        return jnp.zeros((batch, hidden), jnp.float32)


class RecurrentActorCritic(nn.Module):
    """:class:`Torso` → dense embedding → :class:`ScannedGRU` → the heads of :class:`ActorCritic`.

    ``__call__(h (B, H), obs (T, B, ...), resets (T, B)) -> (h_T, policy parameters (T, B, ...),
    value (T, B))``; ``obs`` is time-major with one batch axis after time (an array or dict, as
    :class:`Torso` takes). One env step is ``T = 1``."""

    action_dim: int
    action_mode: str = "discrete"
    hidden: int = 256
    obs_norm: tuple | None = None

    @nn.compact
    def __call__(self, h, obs, resets):
        t, b = resets.shape
        flat = jax.tree.map(lambda a: jnp.reshape(a, (t * b, *jnp.shape(a)[2:])), obs)
        x = Torso(self.hidden, self.obs_norm)(flat).reshape(t, b, -1)
        x = nn.relu(nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
        h, y = ScannedGRU(self.hidden)(h, (x, resets.astype(bool)))
        return (h, *policy_value_heads(self, y))


def network_step(network: RecurrentActorCritic, params, h, obs, first, cell_keys=None):
    """One env step of the recurrent policy for a batch: ``h (B, H)``, ``obs`` (batch-major, one
    leading axis ``B``), ``first (B,)`` bool → ``(h', policy parameters (B, ...), value (B,))``.
    ``cell_keys``: a recurrent cell-set reader's per-slide keys computed once (:func:`rollout_step`)."""
    extra = {} if cell_keys is None else {"cell_keys": cell_keys}
    h, pi, value = network.apply(params, h, jax.tree.map(lambda a: a[None], obs), first[None], **extra)
    return h, jax.tree.map(lambda a: a[0], pi), value[0]


def rollout_step(network: nn.Module, params):
    """``(h, obs, first) -> network_step(network, params, h, obs, first)`` for the many steps of a rollout
    with the same ``params``; a recurrent cell-set reader's per-cell tables
    (:class:`baselines.cell_set_networks.RecurrentCellSetActorCritic`, whose ``KEYS_ONLY`` is ``(None, None, None)``)
    are computed here once (as :func:`rollout_apply` does for the feed-forward reader)."""
    recurrent_reader = getattr(network, "KEYS_ONLY", None) == (None, None, None)
    keys = network.apply(params, None, None, None) if recurrent_reader else None
    return lambda h, obs, first: network_step(network, params, h, obs, first, cell_keys=keys)


class QNetwork(nn.Module):
    """``__call__(obs) -> Q (B, num_actions)``."""

    num_actions: int
    hidden: int = 256

    @nn.compact
    def __call__(self, obs):
        h = Torso(self.hidden)(obs)
        return nn.Dense(self.num_actions, kernel_init=nn.initializers.orthogonal(1.0))(h)


def rollout_apply(network: nn.Module, params):
    """``obs -> network.apply(params, obs)`` for the many calls of a rollout with the same ``params``. For a
    feed-forward cell-set reader (:class:`baselines.cell_set_networks.CellSetActorCritic`, whose ``KEYS_ONLY`` is
    ``(None,)``) the per-cell tables (every valid cell's key and slot row, the reader's largest cost) are computed here
    once instead of at every step; the outputs are those of ``network.apply(params, obs)``."""
    if getattr(network, "KEYS_ONLY", None) == (None,):
        keys = network.apply(params, None)
        return lambda obs: network.apply(params, obs, cell_keys=keys)
    return lambda obs: network.apply(params, obs)


# ----------------------------------------------------------------------------- distributions
def categorical_sample(key, logits):
    return jax.random.categorical(key, logits)


def inverse_cdf_sample(key, logits, block: int = 32):
    """One draw per row of ``logits (..., n)`` from ``softmax(logits)`` by inverse CDF, with **one** uniform per
    row (``jax.random.categorical`` draws ``n`` Gumbel numbers a row: most of a set reader's rollout step over
    ``C + 2`` actions on the CPU). The probabilities are summed in blocks of ``block``: a block is picked by its
    cumulative mass, then an entry inside it, O(n). An entry of probability 0 (a masked cell) is never drawn.
    Returns int32 ``(...)``. The same distribution as :func:`categorical_sample`, not the same draws."""
    n = logits.shape[-1]
    nb = -(-n // block)
    p = jax.nn.softmax(jnp.asarray(logits, jnp.float32), -1)
    p = jnp.pad(p, [(0, 0)] * (p.ndim - 1) + [(0, nb * block - n)]).reshape(*p.shape[:-1], nb, block)
    mass = p.sum(-1)  # (..., nb)
    cum = jnp.cumsum(mass, -1)
    u = jax.random.uniform(key, logits.shape[:-1], jnp.float32) * cum[..., -1]

    def last_positive(a):  # the last index holding mass (rounding may carry a draw past it)
        return a.shape[-1] - 1 - jnp.argmax(jnp.flip(a > 0, -1), -1)

    b = jnp.minimum((cum <= u[..., None]).sum(-1), last_positive(mass))
    rest = u - jnp.take_along_axis(cum - mass, b[..., None], -1)[..., 0]
    inside = jnp.take_along_axis(p, b[..., None, None], -2)[..., 0, :]  # (..., block)
    j = jnp.minimum((jnp.cumsum(inside, -1) <= rest[..., None]).sum(-1), last_positive(inside))
    return (b * block + j).astype(jnp.int32)


def categorical_log_prob(logits, action):
    logp = jax.nn.log_softmax(logits)
    return jnp.take_along_axis(logp, action[..., None].astype(jnp.int32), axis=-1)[..., 0]


def categorical_entropy(logits):
    logp = jax.nn.log_softmax(logits)
    return -(jnp.exp(logp) * logp).sum(-1)


def gaussian_sample(key, mean, log_std):
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)


def gaussian_log_prob(mean, log_std, action):
    z = (action - mean) * jnp.exp(-log_std)
    return (-0.5 * z**2 - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)


def gaussian_entropy(mean, log_std):
    return jnp.broadcast_to(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e), mean.shape).sum(-1)


def policy_sample(key, pi, action_mode: str):
    """A stochastic action. Continuous actions are sampled unclipped (the env clips to [-1, 1];
    the log-probability is that of the unclipped Gaussian sample — a clipped Gaussian)."""
    if is_discrete(action_mode):
        return categorical_sample(key, pi)
    return gaussian_sample(key, *pi)


def rollout_sampler(network: nn.Module, action_mode: str):
    """``(key, pi) -> action``: how a trainer's rollout samples ``network``'s actions. A cell-set reader
    (:mod:`baselines.cell_set_networks`, a network with ``KEYS_ONLY``: ``C + 2`` actions, a thousand or more on a
    true-scale slide) draws by inverse CDF (:func:`inverse_cdf_sample`, one uniform per env); every other policy
    as :func:`policy_sample`. Evaluation samples with :func:`policy_sample` throughout."""
    if getattr(network, "KEYS_ONLY", None) is not None:
        return inverse_cdf_sample
    return lambda key, pi: policy_sample(key, pi, action_mode)


def policy_mode(pi, action_mode: str):
    """The greedy action: argmax of the logits, or the clipped Gaussian mean."""
    if is_discrete(action_mode):
        return jnp.argmax(pi, axis=-1)
    return jnp.clip(pi[0], -1.0, 1.0)


def policy_log_prob(pi, action, action_mode: str):
    if is_discrete(action_mode):
        return categorical_log_prob(pi, action)
    return gaussian_log_prob(*pi, action)


def policy_entropy(pi, action_mode: str):
    if is_discrete(action_mode):
        return categorical_entropy(pi)
    return gaussian_entropy(*pi)
