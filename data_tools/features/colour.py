"""``colour-stats``: a cheap hand-made encoder of a view's colour (no weights, no training).

Eight numbers per view, from its RGB in ``[0, 1]``: the mean and the standard deviation of R, G
and B; the fraction of *tissue* pixels (not near-white glass: mean of RGB < 0.85); the fraction of
*haematoxylin-dense* pixels (dark and blue-purple: mean < 0.6 and B > R). It describes what an H&E
view looks like at the coarsest grain only; on histojax's semi-synthetic slides (purple, crowded
tumour on pink tissue) that is enough to tell tumour from normal tissue, which makes it the fast
encoder of the diagnosis benchmarks and tests (``python -m data_tools features BUNDLE --encoder
colour-stats``). For real slides use a learned encoder (``efficientnet-lite0``, or imported
CLAM/TRIDENT features).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

NAME = "colour-stats"
DIM = 8


def colour_stats(images: jax.Array) -> jax.Array:
    """``uint8 (B, H, W, 3)`` → ``float32 (B, 8)`` (see the module doc)."""
    x = images.astype(jnp.float32) / 255.0
    mean = x.mean(axis=(1, 2))
    std = x.std(axis=(1, 2))
    grey = x.mean(axis=-1)
    tissue = (grey < 0.85).mean(axis=(1, 2))
    dense = ((grey < 0.6) & (x[..., 2] > x[..., 0])).mean(axis=(1, 2))
    return jnp.concatenate([mean, std, tissue[:, None], dense[:, None]], axis=1)


def load_colour_encoder(encoder_class):
    """The ``colour-stats`` encoder as an ``efficientnet.Encoder`` (views fed at their own size)."""
    embed = jax.jit(lambda v, x: colour_stats(x))
    return encoder_class(name=NAME, dim=DIM, image_size=None, variables=None, _embed=embed, _logits=embed)
