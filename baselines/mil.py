"""Gated-attention multiple-instance learning (Ilse, Tomczak & Welling, ICML 2018) in flax: the
"read everything" slide classifier of the diagnosis benchmark, and the head that scores what a
budgeted reader has read.

A bag is a slide's instances ``(N, D)`` (feature vectors of finest-level tissue views) with a
validity mask ``(N,)`` (bags are padded to one size). ``h = ReLU(W x)``; attention
``a = softmax(w · (tanh(V h) ⊙ sigmoid(U h)))`` over the valid instances; ``z = Σ a h``; the slide's
tumour logit is ``c · z + b``. Trained full-batch with Adam on the binary cross-entropy.
"""
from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax


class GatedAttentionMIL(nn.Module):
    """``(bag (N, D), mask (N,)) → (logit (), attention (N,))``; ``hidden`` units, ``attention`` gate size."""

    hidden: int = 64
    attention: int = 32

    @nn.compact
    def __call__(self, bag, mask):
        h = nn.relu(nn.Dense(self.hidden)(bag))
        gate = jnp.tanh(nn.Dense(self.attention)(h)) * nn.sigmoid(nn.Dense(self.attention)(h))
        scores = nn.Dense(1)(gate)[..., 0]
        scores = jnp.where(mask, scores, -1e9)
        att = jax.nn.softmax(scores, axis=-1) * mask
        att = att / jnp.maximum(att.sum(-1, keepdims=True), 1e-9)
        z = jnp.einsum("...n,...nh->...h", att, h)
        return nn.Dense(1)(z)[..., 0], att


@dataclasses.dataclass
class MILClassifier:
    """A trained :class:`GatedAttentionMIL` with its input standardisation (``mean``, ``std`` of ``(D,)``)."""

    module: GatedAttentionMIL
    params: dict
    mean: np.ndarray
    std: np.ndarray

    def scores(self, bags: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """Tumour probability in ``[0, 1]`` of each bag: ``(B, N, D), (B, N) → (B,)``."""
        logits, _ = self.module.apply(self.params, self._norm(bags), jnp.asarray(masks, bool))
        return np.asarray(jax.nn.sigmoid(logits))

    def attention(self, instances: np.ndarray) -> np.ndarray:
        """The attention weights ``(N,)`` (summing to 1) the classifier gives ``instances (N, D)`` read
        as one bag: what a scripted reader ranks cells by (higher = read first)."""
        x = self._norm(instances)[None]
        _, att = self.module.apply(self.params, x, jnp.ones(x.shape[:2], bool))
        return np.asarray(att[0])

    def _norm(self, x):
        return (jnp.asarray(x, jnp.float32) - self.mean) / self.std


def train_mil(bags: np.ndarray, masks: np.ndarray, labels: np.ndarray, steps: int = 400, lr: float = 3e-3,
              seed: int = 0, hidden: int = 64) -> MILClassifier:
    """Fit a gated-attention MIL classifier on ``bags (B, N, D)``, ``masks (B, N)``, 0/1 ``labels (B,)``
    (full batch, Adam, ``steps`` updates). Inputs are standardised by the valid instances' mean/std."""
    bags = np.asarray(bags, np.float32)
    masks = np.asarray(masks, bool)
    valid = bags[masks]
    mean, std = valid.mean(0), valid.std(0) + 1e-6
    module = GatedAttentionMIL(hidden=hidden)
    x = jnp.asarray((bags - mean) / std)
    m = jnp.asarray(masks)
    y = jnp.asarray(labels, jnp.float32)
    params = module.init(jax.random.key(seed), x[:1], m[:1])
    opt = optax.adam(lr)
    state = opt.init(params)

    def loss_fn(p):
        logits, _ = module.apply(p, x, m)
        return optax.sigmoid_binary_cross_entropy(logits, y).mean()

    @jax.jit
    def update(p, s):
        loss, grads = jax.value_and_grad(loss_fn)(p)
        updates, s = opt.update(grads, s, p)
        return optax.apply_updates(p, updates), s, loss

    for _ in range(steps):
        params, state, _ = update(params, state)
    return MILClassifier(module, params, mean, std)
