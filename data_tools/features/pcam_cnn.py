"""``pcam-cnn``: histojax's own small pathology encoder, trained on PatchCamelyon patches as they appear
in the true-scale CAMELYON16 mosaic, its weights shipped in the package (``pcam_cnn.msgpack``).

Model card: docs/encoder-pcam-cnn.md. Training command: ``python -m data_tools train-encoder``
(:mod:`data_tools.features.train_pcam_cnn`).

Input: RGB uint8 ``(B, H, W, 3)`` of any size ≥ 16 px **at the benchmark's scale** (1.94 µm/px, the
C16 full set's level 0 / 8: a PCam patch there is 48 px, an env view 128 px); fed at its own size, no
resizing. Preprocessing: ``(x / 255 − 0.5) / 0.25`` per channel, nothing else (deterministic). Images at
another scale (a PCam patch as distributed: 96 px at 0.972 µm/px) go through :func:`to_benchmark_scale`
first.

Architecture: ``LAYERS``: a 4×4 convolution of stride 4 (24 channels), a 3×3 of stride 2 (48), a 3×3 (48) and
a 1×1 (64), each followed by BatchNorm (running statistics at inference) and ReLU: one output cell per 8 × 8
input px, receptive field 28 px; then a 1×1 convolution to ``CHANNELS`` = 31 feature channels ``f`` and a 1×1
linear tumour-logit map ``l`` over ``relu(f)``. Global pooling over
the cells makes it work on a single patch as on a whole view:

- ``logits(images)`` → float32 ``(B,)``: the mean of ``l`` over the cells (the trained output: the
  patch's tumour logit; on a view it grows with the view's tumour fraction);
- ``embed(images)`` → float32 ``(B, 64)``: ``[mean f (31), max f (31), mean l, max l]``. The last two
  are the tumour logit and its most tumour-like cell, so a linear head (or an agent) can read "how
  much" and "is there any" tumour in a view.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp

NAME = "pcam-cnn"
CHANNELS = 31
DIM = 2 * CHANNELS + 2
VIEW_LOGIT = 2 * CHANNELS  # index of ``mean l`` (the view's tumour logit, the trained output) in ``embed``
MAX_CELL_LOGIT = 2 * CHANNELS + 1  # index of ``max l`` (the most tumour-like cell: noisy over a slide)
LAYERS = ((24, 4, 4), (48, 3, 2), (48, 3, 1), (64, 1, 1))  # (channels, kernel, stride) of each ReLU conv
SCALE_MPP = 1.944  # µm per input px the encoder was trained at (CAMELYON16 level 0 / 8)
PATCH_PX = 48  # a PCam patch (96 px at 0.972 µm/px) at that scale
WEIGHTS = Path(__file__).with_name("pcam_cnn.msgpack")


class PcamCNN(nn.Module):
    """The network: uint8 or float RGB in [0, 255] ``(B, H, W, 3)`` → ``(f, l)``, feature map
    ``(B, h, w, CHANNELS)`` and logit map ``(B, h, w)`` with ``h = ceil(H / 8)``. ``train``: BatchNorm uses and
    updates the batch's statistics (``mutable=["batch_stats"]``) instead of the running ones."""

    train: bool = False
    layers: tuple = LAYERS  # (channels, kernel, stride) of each ReLU conv (an :class:`Arch`'s ``layers``)

    @nn.compact
    def __call__(self, images):
        x = (images.astype(jnp.float32) / 255.0 - 0.5) / 0.25
        for i, (c, k, s) in enumerate(self.layers):
            x = nn.Conv(c, (k, k), strides=(s, s), padding="SAME", use_bias=False, name=f"conv{i}")(x)
            x = nn.relu(nn.BatchNorm(use_running_average=not self.train, momentum=0.9, name=f"bn{i}")(x))
        f = nn.Conv(CHANNELS, (1, 1), name="features")(x)
        logit = nn.Conv(1, (1, 1), name="tumour")(nn.relu(f))[..., 0]
        return f, logit


def pool(f: jax.Array, logit: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Global pooling of the maps: ``(embedding (B, DIM), patch logit (B,))``."""
    emb = jnp.concatenate(
        [f.mean(axis=(1, 2)), f.max(axis=(1, 2)), logit.mean(axis=(1, 2))[:, None], logit.max(axis=(1, 2))[:, None]],
        axis=1,
    )
    return emb, logit.mean(axis=(1, 2))


@dataclasses.dataclass(frozen=True)
class Arch:
    """One trained network of this family: its registered ``name``, conv ``layers`` ((channels, kernel, stride)
    of each ReLU conv), the scale it reads (``mpp``, µm per input px), a PCam patch's size there (``patch_px``)
    and its shipped ``weights``. The output (``DIM`` = 64 numbers, :func:`pool`) is the same for every one."""

    name: str
    layers: tuple
    mpp: float
    patch_px: int
    weights: Path

    def module(self, train: bool = False) -> PcamCNN:
        """The flax module of this architecture."""
        return PcamCNN(train=train, layers=self.layers)


PCAM_CNN = Arch(NAME, LAYERS, SCALE_MPP, PATCH_PX, WEIGHTS)
ARCHS = {NAME: PCAM_CNN}  # more are added by their modules (data_tools.features.pcam_cnn96)


def init_variables(seed: int = 0, arch: Arch = PCAM_CNN) -> dict:
    """Fresh (untrained) variables of ``arch``, He-initialised by flax's defaults."""
    return arch.module().init(jax.random.PRNGKey(seed), jnp.zeros((1, arch.patch_px, arch.patch_px, 3), jnp.uint8))


def apply(variables, images, arch: Arch = PCAM_CNN) -> tuple[jax.Array, jax.Array]:
    """``(embedding (B, DIM), tumour logit (B,))`` of uint8 images ``(B, H, W, 3)`` at ``arch``'s scale."""
    return pool(*arch.module().apply(variables, images))


def to_benchmark_scale(images, mpp: float) -> jax.Array:
    """uint8 RGB ``(B, H, W, 3)`` at ``mpp`` µm/px → uint8 at the encoder's ``SCALE_MPP`` (1.94 µm/px): a PCam
    patch (96 px at 0.972 µm/px) becomes 48 px by 2 × 2 box averaging, as the C16 mosaic resizes it; other
    scales are resized with antialiasing. Unchanged when ``mpp`` is already the encoder's scale."""
    images = jnp.asarray(images)
    factor = mpp / SCALE_MPP
    if abs(factor - 1.0) < 0.02:
        return images
    b, h, w, c = images.shape
    if abs(factor - 0.5) < 0.01 and h % 2 == 0 and w % 2 == 0:
        q = images.astype(jnp.uint32).reshape(b, h // 2, 2, w // 2, 2, c).sum(axis=(2, 4))
        return ((q + 2) // 4).astype(jnp.uint8)
    size = (b, max(1, round(h * factor)), max(1, round(w * factor)), c)
    out = jax.image.resize(images.astype(jnp.float32), size, method="linear", antialias=True)
    return jnp.clip(jnp.round(out), 0, 255).astype(jnp.uint8)


def read_weights(path=None, arch: Arch = PCAM_CNN) -> dict:
    """The shipped (or given) msgpack weights of ``arch``, checked against the architecture; ``WeightsError``
    naming the file when missing, unreadable or of another shape."""
    from flax import serialization

    from data_tools.features.torch_weights import WeightsError

    path = Path(path) if path is not None else arch.weights
    template = init_variables(arch=arch)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise WeightsError(
            path,
            f"cannot read the {arch.name} weights ({e.strerror or e}); "
            "retrain them with `python -m data_tools train-encoder`",
        ) from None
    try:
        state = serialization.msgpack_restore(raw)
        variables = serialization.from_state_dict(template, state)
    except Exception as e:  # msgpack/flax raise assorted types on a corrupt or foreign file
        raise WeightsError(path, f"not {arch.name} weights ({type(e).__name__}: {e})") from None
    for a, b in zip(jax.tree_util.tree_leaves(template), jax.tree_util.tree_leaves(variables)):
        if a.shape != b.shape:
            raise WeightsError(path, f"weights of shape {b.shape} where the architecture has {a.shape}")
    return jax.tree_util.tree_map(jnp.asarray, variables)


@functools.lru_cache(maxsize=4)
def load_pcam_encoder(encoder_class, weights=None, name: str = NAME):
    """The encoder ``name`` of this family (``pcam-cnn``, ``pcam-cnn96``) as an ``efficientnet.Encoder`` (views fed
    at their own size)."""
    arch = ARCHS[name]
    variables = read_weights(weights, arch)
    return encoder_class(
        name=arch.name,
        dim=DIM,
        image_size=None,
        variables=variables,
        _embed=jax.jit(lambda v, x: apply(v, x, arch)[0]),
        _logits=jax.jit(lambda v, x: apply(v, x, arch)[1]),
    )


__all__ = [
    "ARCHS",
    "Arch",
    "CHANNELS",
    "DIM",
    "NAME",
    "PATCH_PX",
    "PCAM_CNN",
    "PcamCNN",
    "SCALE_MPP",
    "WEIGHTS",
    "apply",
    "init_variables",
    "load_pcam_encoder",
    "read_weights",
    "to_benchmark_scale",
]
