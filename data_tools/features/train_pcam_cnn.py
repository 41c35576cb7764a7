"""Train ``pcam-cnn`` (:mod:`data_tools.features.pcam_cnn`) on the PCam **training pool**, as its patches
appear in the true-scale CAMELYON16 mosaic: ``python -m data_tools train-encoder --patches
pcam_train_patches.tar.gz --out WEIGHTS.msgpack``. Reproducible from ``--seed``; minutes on 2 CPU cores.

Data. The bank is cut by the pool rule (:func:`data_tools.datasets.pcam_bank.split_pools`): the test pool is
never read for training or for choosing anything; the training pool is cut once more (seeded,
``--val-fraction``) into the patches fitted and a validation set on which the epoch is chosen.

Each patch is shown at the benchmark's scale (96 px → 48 px by 2 × 2 box averaging, as the mosaic's
``Image.BOX`` resize does) with the mosaic's own variation (:mod:`data_tools.datasets.c16_mosaic`): a batch is
cut into ``GROUPS`` "slides", each with its own stain (per-channel optical-density factor in
``STAIN_RANGE`` times a density factor in ``DENSITY_RANGE``) and, with probability ``P_MATCH``, the
mosaic's colour matching (tumour patches' mean RGB moved ``COLOUR_MATCH`` of the way to the group's
normal patches); with probability ``P_RAW`` a group keeps PCam's own colours; every patch takes one of
the 8 orientations and a ±5 % per-channel gain. The loss is the binary cross-entropy of the patch
logit against PCam's label (tumour in the central 32 × 32 px of the 96-px patch).

Output: the weights (msgpack, flax serialisation) and ``NAME.json`` beside them (the model card's
figures: data hash, command, epochs, validation and test-pool AUC).
"""
from __future__ import annotations

import hashlib
import sys
import time
from pathlib import Path

import numpy as np

from data_tools.datasets.c16_mosaic import COLOUR_MATCH, DENSITY_RANGE, STAIN_RANGE

GROUPS = 4          # stain groups ("slides") per batch
P_MATCH = 0.6       # a group's chance of the mosaic's tumour colour matching
P_RAW = 0.2         # a group's chance of keeping PCam's own colours (no stain, no matching)
SHIFT = 4           # px of random translation each way


def box_half(patches: np.ndarray) -> np.ndarray:
    """uint8 ``(N, 96, 96, 3)`` → uint8 ``(N, 48, 48, 3)``: 2 × 2 box average, rounded (the mosaic's
    resize to 1.94 µm/px; PIL's BOX filter at an exact factor of 2)."""
    q = patches.astype(np.uint16)
    return ((q[:, 0::2, 0::2] + q[:, 1::2, 0::2] + q[:, 0::2, 1::2] + q[:, 1::2, 1::2] + 2) // 4).astype(np.uint8)


def bank_digest(bank) -> str:
    """sha256 over the bank's patches (label, name and JPEG bytes, in the bank's order)."""
    h = hashlib.sha256()
    for i in range(len(bank)):
        h.update(f"{int(bank.labels[i])}/{bank.names[i]}\n".encode())
        h.update(bank.blob[bank.offsets[i]:bank.offsets[i + 1]].tobytes())
    return h.hexdigest()


def mosaic_augment(key, images, labels):
    """float32 ``(B, H, W, 3)`` in [0, 255] and 0/1 ``labels (B,)`` → augmented float32 images (see the module
    doc); ``B`` must be a multiple of ``GROUPS``. Pure JAX (jitted inside the train step)."""
    import jax
    import jax.numpy as jnp

    b = images.shape[0]
    g = b // GROUPS
    ks = jax.random.split(key, 8)
    group = jnp.repeat(jnp.arange(GROUPS), g)
    gains = (jax.random.uniform(ks[0], (GROUPS, 3), minval=STAIN_RANGE[0], maxval=STAIN_RANGE[1])
             * jax.random.uniform(ks[1], (GROUPS, 1), minval=DENSITY_RANGE[0], maxval=DENSITY_RANGE[1]))
    raw = jax.random.uniform(ks[2], (GROUPS,)) < P_RAW
    gains = jnp.where(raw[:, None], 1.0, gains)
    od = -jnp.log((images + 1.0) / 256.0)
    x = jnp.clip(256.0 * jnp.exp(-od * gains[group][:, None, None, :]) - 1.0, 0.0, 255.0)
    # the mosaic's colour matching, per group: tumour patches × (mean normal / mean tumour) ** COLOUR_MATCH
    mean_rgb = x.mean(axis=(1, 2))
    y = labels.astype(jnp.float32)
    def group_mean(w):
        s = jax.ops.segment_sum(mean_rgb * w[:, None], group, GROUPS)
        return s / jnp.maximum(jax.ops.segment_sum(w, group, GROUPS), 1.0)[:, None]
    gain = (group_mean(1.0 - y) / jnp.maximum(group_mean(y), 1.0)) ** COLOUR_MATCH
    n_tumour = jax.ops.segment_sum(y, group, GROUPS)
    both = (n_tumour > 0) & (n_tumour < g)   # matching needs both classes in the group
    match = (jax.random.uniform(ks[3], (GROUPS,)) < P_MATCH) & ~raw & both
    gain = jnp.where(match[:, None], gain, 1.0)[group]
    x = jnp.where(y[:, None, None, None] > 0, x * gain[:, None, None, :], x)
    x = x * jax.random.uniform(ks[4], (b, 1, 1, 3), minval=0.95, maxval=1.05)
    # 8 orientations: transpose with probability 1/2, then flips of each axis
    t = jax.random.bernoulli(ks[5], 0.5, (b,))
    x = jnp.where(t[:, None, None, None], jnp.swapaxes(x, 1, 2), x)
    flips = jax.random.bernoulli(ks[6], 0.5, (b, 2))
    x = jnp.where(flips[:, 0, None, None, None], x[:, ::-1], x)
    x = jnp.where(flips[:, 1, None, None, None], x[:, :, ::-1], x)
    # a shift of up to SHIFT px each way (mirror padding), as patches sit anywhere under a view's cells
    h, w = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (SHIFT, SHIFT), (SHIFT, SHIFT), (0, 0)), mode="reflect")
    offsets = jax.random.randint(ks[7], (b, 2), 0, 2 * SHIFT + 1)
    x = jax.vmap(lambda img, o: jax.lax.dynamic_slice(img, (o[0], o[1], 0), (h, w, 3)))(padded, offsets)
    return jnp.clip(x, 0.0, 255.0)


def stained_copy(images: np.ndarray, labels: np.ndarray, seed: int) -> np.ndarray:
    """A fixed mosaic-like augmentation of uint8 ``images`` (for validation/test figures), uint8."""
    import jax
    import jax.numpy as jnp

    n = len(images) // GROUPS * GROUPS
    perm = np.random.default_rng([seed, 5]).permutation(len(images))[:n]   # groups mix both classes
    out = np.asarray(jax.jit(mosaic_augment)(jax.random.PRNGKey(seed), jnp.asarray(images[perm], jnp.float32),
                                            jnp.asarray(labels[perm])))
    result = images.copy()
    result[perm] = np.rint(out).astype(np.uint8)
    return result


def predict(variables, images: np.ndarray, batch: int = 1024) -> np.ndarray:
    """Tumour logits ``(N,)`` of uint8 images at the benchmark scale."""
    import jax

    from data_tools.features import pcam_cnn

    f = jax.jit(lambda v, x: pcam_cnn.apply(v, x)[1])
    return np.concatenate([np.asarray(f(variables, images[i:i + batch])) for i in range(0, len(images), batch)]
                          or [np.zeros(0, np.float32)])


def train(patches=None, seed: int = 0, epochs: int = 30, batch: int = 256, lr: float = 2e-3,
          weight_decay: float = 1e-4, val_fraction: float = 0.1, max_patches: int | None = None,
          progress: bool = True) -> tuple[dict, dict]:
    """Train from ``patches`` (a PCam folder / ``.tar.gz`` / bank ``.npz``; default the shipped 1,000-patch
    bank). Returns ``(variables of the epoch with the best validation AUC, report dict)``.
    ``max_patches``: use at most that many training-pool patches (tests)."""
    import jax
    import jax.numpy as jnp
    import optax
    from tqdm.auto import tqdm

    from data_tools.metrics import roc_auc
    from data_tools.features import pcam_cnn
    from data_tools.datasets.pcam_bank import load_bank, pool_rule, split_pools

    t0 = time.perf_counter()
    bank = load_bank(patches)
    train_pool, test_pool = split_pools(bank)
    rng = np.random.default_rng([seed, 2024])
    order = rng.permutation(len(train_pool))
    if max_patches is not None:
        order = order[:max_patches]
    n_val = max(GROUPS, int(round(val_fraction * len(order))))
    val_idx, fit_idx = np.sort(order[:n_val]), np.sort(order[n_val:])
    images = box_half(train_pool.decode(np.arange(len(train_pool))))
    labels = train_pool.labels.astype(np.int32)
    x_fit, y_fit = images[fit_idx], labels[fit_idx]
    x_val, y_val = images[val_idx], labels[val_idx]
    x_val_stained = stained_copy(x_val, y_val, seed + 1)
    batch = max(GROUPS, batch // GROUPS * GROUPS)
    steps_per_epoch = max(1, len(x_fit) // batch)
    total = steps_per_epoch * epochs
    warmup = min(100, steps_per_epoch) if total > min(100, steps_per_epoch) else 0  # a one-step run: no warm-up
    schedule = optax.warmup_cosine_decay_schedule(0.0 if warmup else lr, lr, warmup, total)
    tx = optax.adamw(schedule, weight_decay=weight_decay)
    variables = pcam_cnn.init_variables(seed)
    opt_state = tx.init(variables["params"])
    net = pcam_cnn.PcamCNN(train=True)

    def loss_fn(params, stats, x, y):
        (f, lg), new = net.apply({"params": params, "batch_stats": stats}, x, mutable=["batch_stats"])
        logit = pcam_cnn.pool(f, lg)[1]
        return optax.sigmoid_binary_cross_entropy(logit, y.astype(jnp.float32)).mean(), new["batch_stats"]

    @jax.jit
    def step(v, opt_state, key, x, y):
        x = mosaic_augment(key, x.astype(jnp.float32), y)
        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(v["params"], v["batch_stats"], x, y)
        updates, opt_state = tx.update(grads, opt_state, v["params"])
        return {"params": optax.apply_updates(v["params"], updates), "batch_stats": stats}, opt_state, loss

    key = jax.random.PRNGKey(seed)
    best, history = None, []
    bar = tqdm(total=epochs * steps_per_epoch, desc="train pcam-cnn", unit="step", disable=not progress)
    for epoch in range(epochs):
        perm = rng.permutation(len(x_fit))
        losses = []
        for s in range(steps_per_epoch):
            idx = perm[s * batch:(s + 1) * batch]
            key, sub = jax.random.split(key)
            variables, opt_state, loss = step(variables, opt_state, sub, jnp.asarray(x_fit[idx]),
                                              jnp.asarray(y_fit[idx]))
            losses.append(float(loss))
            bar.update(1)
        auc_raw = roc_auc(predict(variables, x_val), y_val)
        auc_stained = roc_auc(predict(variables, x_val_stained), y_val)
        history.append({"epoch": epoch + 1, "loss": round(float(np.mean(losses)), 5),
                        "val_auc_raw": round(auc_raw, 4), "val_auc_mosaic": round(auc_stained, 4)})
        score = (auc_raw + auc_stained) / 2
        if best is None or score > best[0]:
            best = (score, epoch + 1, variables)
        bar.set_postfix(val_auc=f"{auc_raw:.3f}/{auc_stained:.3f}")
    bar.close()
    report = {
        "encoder": pcam_cnn.NAME, "seed": int(seed), "epochs": int(epochs), "batch": int(batch), "lr": lr,
        "weight_decay": weight_decay, "val_fraction": val_fraction,
        "best_epoch": best[1], "val_auc_mean_of_raw_and_mosaic": round(best[0], 4),
        "patches": bank.source, "patches_sha256": bank_digest(bank), "bank_patches": len(bank),
        "pool_rule": pool_rule(), "training_pool_patches": len(train_pool), "fitted_patches": len(fit_idx),
        "validation_patches": len(val_idx), "test_pool_patches": len(test_pool),
        "training_pool_sha256": bank_digest(train_pool), "history": history,
        "train_seconds": round(time.perf_counter() - t0, 1), "jax": jax.__version__,
    }
    return best[2], report


def test_pool_auc(variables, patches=None, limit: int | None = None, seed: int = 0) -> dict:
    """Patch AUC of ``variables`` on the **test pool** of ``patches`` (never trained on), on PCam's own
    colours and on a fixed mosaic-like stain: ``{"raw": auc, "mosaic": auc, "patches": n}``."""
    from data_tools.metrics import roc_auc
    from data_tools.datasets.pcam_bank import load_bank, split_pools

    _, test_pool = split_pools(load_bank(patches))
    idx = np.arange(len(test_pool))
    if limit is not None and limit < len(idx):
        idx = np.sort(np.random.default_rng([seed, 7]).choice(idx, limit, replace=False))
    x = box_half(test_pool.decode(idx))
    y = test_pool.labels[idx]
    return {"raw": round(roc_auc(predict(variables, x), y), 4),
            "mosaic": round(roc_auc(predict(variables, stained_copy(x, y, 99)), y), 4), "patches": int(len(idx))}


def save_weights(variables, out, report: dict) -> Path:
    """Write ``out`` (msgpack) and ``out.json`` (the report) atomically."""
    from flax import serialization

    from data_tools.bundle_format import atomic_file, write_json

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        Path(tmp).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(
            __import__("jax").tree_util.tree_map(np.asarray, variables))))
    write_json(out.with_suffix(".json"), report)
    return out


def add_arguments(p) -> None:
    """The options of ``python -m data_tools train-encoder``."""
    p.add_argument("--patches", default=None, help="PCam patches: folder with 0/ and 1/, its .tar.gz, or a bank .npz "
                   "(default: the shipped 1,000-patch bank; the shipped weights were trained on "
                   "pcam_train_patches.tar.gz, 20,000 patches)")
    p.add_argument("--out", required=True, help="weights file to write (.msgpack; a .json report beside it)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--max-patches", type=int, default=None, help="use at most N training-pool patches (quick runs)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args, parser=None) -> int:
    """Train, score the test pool once, write the weights and report."""
    variables, report = train(args.patches, seed=args.seed, epochs=args.epochs, batch=args.batch, lr=args.lr,
                              max_patches=args.max_patches, progress=not args.quiet)
    report["test_pool_auc"] = test_pool_auc(variables, args.patches)
    report["command"] = "python -m data_tools train-encoder " + " ".join(sys.argv[2:] if len(sys.argv) > 2 else [])
    out = save_weights(variables, args.out, report)
    print(f"wrote {out}: best epoch {report['best_epoch']}/{report['epochs']}, validation AUC "
          f"{report['val_auc_mean_of_raw_and_mosaic']:.3f}; test-pool patch AUC {report['test_pool_auc']['raw']:.3f} "
          f"(PCam colours), {report['test_pool_auc']['mosaic']:.3f} (mosaic stain) on "
          f"{report['test_pool_auc']['patches']} patches; {report['train_seconds']:.0f} s")
    return 0


__all__ = ["add_arguments", "box_half", "mosaic_augment", "run", "save_weights", "test_pool_auc", "train"]
