"""A small labelled cohort with TRIDENT-layout features in which no entry is "the logit", for the learned head.

:func:`make_cohort` builds one small slide (pink tissue on glass, 32-px views) into a bundle, copies it once per
slide, and gives each copy its own feature grid imported from a TRIDENT-style ``.h5`` (``features (N, D)``,
``coords (N, 2)`` with ``patch_size`` / ``patch_level`` attributes, :func:`data_tools.features.hdf5.import_features`).
Each patch's feature vector is ``z @ Q``: ``z`` standard normal noise whose entry 0 is raised by ``signal`` on the
slide's tumour views (a rectangle of views, tumour slides only) and whose entry 1 carries a per-slide offset (a
stain-like nuisance), ``Q`` a random orthogonal matrix, so the tumour direction is ``Q[0]``, spread over every
entry. Labels are in ``dataset.json``'s ``labels``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

TILE = 32
SIZE = (512, 640)  # px (height, width): 16 x 20 views of 32 px


def random_rotation(rng, dim: int) -> np.ndarray:
    """A random ``(dim, dim)`` orthogonal matrix."""
    q, r = np.linalg.qr(rng.normal(size=(dim, dim)))
    return q * np.sign(np.diag(r))


def _template(root: Path) -> Path:
    import tifffile

    from data_tools.bundle import build_bundle

    image = np.full(SIZE + (3,), 245, np.uint8)
    image[32:480, 32:608] = [230, 160, 200]  # tissue: views 1..14 x 1..18
    tifffile.imwrite(root / "template.tif", image, photometric="rgb")
    return build_bundle(root / "template.tif", root / "template", level_sets=(3,), tile_size=TILE, progress=False)


def make_cohort(
    root,
    tumour: int = 16,
    normal: int = 16,
    test_tumour: int = 4,
    test_normal: int = 4,
    dim: int = 48,
    signal: float = 2.5,
    seed: int = 0,
) -> dict:
    """Build the cohort under ``root`` (``dataset.json``, ``bundles/``, ``features/*.h5``); returns ``{"root",
    "q" (D, D), "direction" (D,), "tumour" {name: (16, 20) bool tumour views}, "names" {"train": [...], "test":
    [...]}}``."""
    import h5py

    from data_tools.features.hdf5 import import_features

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    q = random_rotation(rng, dim)
    template = _template(root)
    gh, gw = SIZE[0] // TILE, SIZE[1] // TILE
    ys, xs = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
    coords = np.stack([xs.ravel() * TILE, ys.ravel() * TILE], 1)
    (root / "features").mkdir(exist_ok=True)
    plan = [("train", 1)] * tumour + [("train", 0)] * normal + [("test", 1)] * test_tumour + [("test", 0)] * test_normal
    spec = {"kind": "learned-head test cohort", "train": [], "test": [], "labels": {}}
    masks = {}
    for i, (split, label) in enumerate(plan):
        name = f"s{i:02d}_{'tumour' if label else 'normal'}"
        bundle = root / "bundles" / name
        shutil.copytree(template, bundle)
        m = np.zeros((gh, gw), bool)
        if label:
            h, w = rng.integers(2, 5, 2)
            y0, x0 = rng.integers(1, 15 - h), rng.integers(1, 19 - w)
            m[y0 : y0 + h, x0 : x0 + w] = True
        z = rng.normal(size=(gh * gw, dim))
        z[:, 0] += signal * m.ravel()
        z[:, 1] += rng.normal(0, 1.5)
        with h5py.File(root / "features" / f"{name}.h5", "w") as f:
            f.create_dataset("features", data=(z @ q).astype(np.float32))
            c = f.create_dataset("coords", data=coords)
            c.attrs["patch_size"] = TILE
            c.attrs["patch_level"] = 0
        import_features(bundle, root / "features" / f"{name}.h5", dtype="float32")
        spec[split].append(f"bundles/{name}")
        spec["labels"][name] = label
        masks[name] = m
    shutil.rmtree(template)
    (root / "dataset.json").write_text(json.dumps(spec, indent=1))
    return {
        "root": root,
        "q": q,
        "direction": q[0],
        "tumour": masks,
        "names": {s: [Path(e).name for e in spec[s]] for s in ("train", "test")},
    }


def untrained_fit(train_slides, val, structure, seed=0, **kwargs):
    """``baselines.reading.learned_head_fit.train`` without the training, to monkeypatch in its place: the initial
    head (its standardisation from ``train_slides``) and a one-row curve, so a test sees the fit's bookkeeping (what
    the command records and refuses) cheaply."""
    import jax
    import jax.numpy as jnp

    from baselines.reading import learned_head_fit as fit
    from histojax.reading.heads.learned import LearnedHead, init_params

    d = int(train_slides[0]["features"].shape[1])
    mu, sd = fit.standardisation(train_slides)
    params = init_params(
        jax.random.PRNGKey(seed), d, structure["hidden"], structure["attention"], structure["layers"], mu, sd
    )
    head = LearnedHead(
        params=params,
        prior_logit=jnp.float32(0.0),
        features_dim=d,
        hidden=structure["hidden"],
        attention=structure["attention"],
        layers=structure["layers"],
        encoder=train_slides[0].get("encoder"),
    )
    return head, [{"step": 1, "loss": 0.7, "full": 0.5, "read 0.1": 0.5, "validation_loss": 0.7, "smoothed": 0.5}]
