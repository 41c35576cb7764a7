"""Tiny encoders for tests/data_pipeline/test_own_encoder.py (``--encoder encoder_helpers:NAME``): one that keeps the
rules (``uint8 (N, H, W, 3) → float32 (N, D)``) and one for each rule broken."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


@jax.jit
def _tiny(images):
    x = images.astype(jnp.float32) / 255.0
    return jnp.concatenate([x.mean(axis=(1, 2)), x.std(axis=(1, 2))], axis=1)  # (N, 6): mean and std of R, G, B


def tiny_colour(images):
    """A small JAX model: mean and standard deviation of each colour, 6 numbers a view."""
    return _tiny(jnp.asarray(images))


tiny_colour.name = "tiny-colour"
tiny_colour.version = "1"


def unnamed(images):
    return np.asarray(images, np.float32).mean(axis=(1, 2))  # (N, 3), no name or version attribute


def wrong_shape(images):
    return np.zeros(len(images), np.float32)  # (N,), not (N, D)


def wrong_dtype(images):
    return np.zeros((len(images), 4), np.float64)


def not_finite(images):
    out = np.zeros((len(images), 4), np.float32)
    out[-1, 0] = np.nan
    return out


def raises(images):
    raise RuntimeError("weights not found")


def steals_a_name(images):
    return np.zeros((len(images), 4), np.float32)


steals_a_name.name = "pcam-cnn"
