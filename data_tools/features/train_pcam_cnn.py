"""Train ``pcam-cnn`` (:mod:`data_tools.features.pcam_cnn`) on the PCam **training pool**, as its patches
appear in the true-scale CAMELYON16 mosaic: ``python -m data_tools train-encoder --patches
pcam_train_patches.tar.gz --out WEIGHTS.msgpack``. Reproducible from ``--seed``; minutes on 2 CPU cores.

Data. The bank is cut by the pool rule (:func:`data_tools.datasets.pcam_bank.split_pools`): the test pool is
never read for training or for choosing anything; the training pool is cut once more (seeded,
``--val-fraction``) into the patches fitted and a validation set on which the epoch is chosen.

Each patch is shown at the benchmark's scale (96 px → 48 px by 2 × 2 box averaging, as the mosaic's
``Image.BOX`` resize does) with the mosaic's own variation (:mod:`data_tools.datasets.c16.mosaic`): a batch is
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

from data_tools.datasets.c16.mosaic import COLOUR_MATCH, DENSITY_RANGE, STAIN_RANGE

GROUPS = 4  # stain groups ("slides") per batch
P_MATCH = 0.6  # a group's chance of the mosaic's tumour colour matching
P_RAW = 0.2  # a group's chance of keeping PCam's own colours (no stain, no matching)
SHIFT = 4  # px of random translation each way


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
        h.update(bank.blob[bank.offsets[i] : bank.offsets[i + 1]].tobytes())
    return h.hexdigest()


def mosaic_augment(key, images, labels, shift: int = SHIFT, brightness: float = 0.0):
    """float32 ``(B, H, W, 3)`` in [0, 255] and 0/1 ``labels (B,)`` → augmented float32 images (see the module
    doc); ``B`` must be a multiple of ``GROUPS``. ``shift``: px of random translation each way; ``brightness``:
    when > 0, each patch's three channels are also scaled by one factor in ``1 ± brightness`` (drawn from a key
    of its own, so ``brightness=0`` gives the same images as before it existed). Pure JAX (jitted inside the
    train step)."""
    import jax
    import jax.numpy as jnp

    b = images.shape[0]
    g = b // GROUPS
    ks = jax.random.split(key, 8)
    group = jnp.repeat(jnp.arange(GROUPS), g)
    gains = jax.random.uniform(ks[0], (GROUPS, 3), minval=STAIN_RANGE[0], maxval=STAIN_RANGE[1]) * jax.random.uniform(
        ks[1], (GROUPS, 1), minval=DENSITY_RANGE[0], maxval=DENSITY_RANGE[1]
    )
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
    both = (n_tumour > 0) & (n_tumour < g)  # matching needs both classes in the group
    match = (jax.random.uniform(ks[3], (GROUPS,)) < P_MATCH) & ~raw & both
    gain = jnp.where(match[:, None], gain, 1.0)[group]
    x = jnp.where(y[:, None, None, None] > 0, x * gain[:, None, None, :], x)
    x = x * jax.random.uniform(ks[4], (b, 1, 1, 3), minval=0.95, maxval=1.05)
    if brightness > 0:
        x = x * jax.random.uniform(
            jax.random.fold_in(key, 9), (b, 1, 1, 1), minval=1.0 - brightness, maxval=1.0 + brightness
        )
    # 8 orientations: transpose with probability 1/2, then flips of each axis
    t = jax.random.bernoulli(ks[5], 0.5, (b,))
    x = jnp.where(t[:, None, None, None], jnp.swapaxes(x, 1, 2), x)
    flips = jax.random.bernoulli(ks[6], 0.5, (b, 2))
    x = jnp.where(flips[:, 0, None, None, None], x[:, ::-1], x)
    x = jnp.where(flips[:, 1, None, None, None], x[:, :, ::-1], x)
    # a shift of up to SHIFT px each way (mirror padding), as patches sit anywhere under a view's cells
    h, w = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (shift, shift), (shift, shift), (0, 0)), mode="reflect")
    offsets = jax.random.randint(ks[7], (b, 2), 0, 2 * shift + 1)
    x = jax.vmap(lambda img, o: jax.lax.dynamic_slice(img, (o[0], o[1], 0), (h, w, 3)))(padded, offsets)
    return jnp.clip(x, 0.0, 255.0)


def stained_copy(images: np.ndarray, labels: np.ndarray, seed: int, shift: int = SHIFT) -> np.ndarray:
    """A fixed mosaic-like augmentation of uint8 ``images`` (for validation/test figures), uint8."""
    import functools

    import jax
    import jax.numpy as jnp

    n = len(images) // GROUPS * GROUPS
    perm = np.random.default_rng([seed, 5]).permutation(len(images))[:n]  # groups mix both classes
    augment = jax.jit(functools.partial(mosaic_augment, shift=shift))
    out = np.asarray(
        augment(jax.random.PRNGKey(seed), jnp.asarray(images[perm], jnp.float32), jnp.asarray(labels[perm]))
    )
    result = images.copy()
    result[perm] = np.rint(out).astype(np.uint8)
    return result


def predict(variables, images: np.ndarray, batch: int = 1024, arch=None, embed: bool = False) -> np.ndarray:
    """Tumour logits ``(N,)`` (``embed``: embeddings ``(N, 64)``) of uint8 images at ``arch``'s scale (an
    :class:`data_tools.features.pcam_cnn.Arch`; default ``pcam-cnn``)."""
    import jax

    from data_tools.features import pcam_cnn

    arch = arch or pcam_cnn.PCAM_CNN
    f = jax.jit(lambda v, x: pcam_cnn.apply(v, x, arch)[0 if embed else 1])
    return np.concatenate(
        [np.asarray(f(variables, images[i : i + batch])) for i in range(0, len(images), batch)]
        or [np.zeros((0, pcam_cnn.DIM) if embed else 0, np.float32)]
    )


def get_arch(name: str | None):
    """The :class:`data_tools.features.pcam_cnn.Arch` called ``name`` (None: ``pcam-cnn``)."""
    from data_tools.features import pcam_cnn, pcam_cnn96  # noqa: F401  (registers pcam-cnn96)

    return pcam_cnn.ARCHS[name or pcam_cnn.NAME]


def at_scale(patches96: np.ndarray, arch) -> np.ndarray:
    """PCam patches as distributed (uint8 ``(N, 96, 96, 3)``) at ``arch``'s scale: 48 px (:func:`box_half`) for
    ``pcam-cnn``, unchanged for ``pcam-cnn96``."""
    return patches96 if arch.patch_px == 96 else box_half(patches96)


def train(
    patches=None,
    seed: int = 0,
    epochs: int = 30,
    batch: int = 256,
    lr: float = 2e-3,
    weight_decay: float = 1e-4,
    val_fraction: float = 0.1,
    max_patches: int | None = None,
    progress: bool = True,
    arch: str | None = None,
    brightness: float = 0.0,
    checkpoint=None,
    log=None,
) -> tuple[dict, dict]:
    """Train from ``patches`` (a PCam folder / ``.tar.gz`` / bank ``.npz``; default the shipped 1,000-patch
    bank). Returns ``(variables of the epoch with the best validation AUC, report dict)``.
    ``max_patches``: use at most that many training-pool patches (tests). ``arch``: the network (``pcam-cnn``, the
    default, at 48 px; ``pcam-cnn96`` at 96 px). ``brightness``: per-patch brightness jitter (``1 ± brightness``).
    ``checkpoint``: a file written after every epoch; a run started with the same file and settings resumes
    after its last finished epoch. ``log``: a text file that gets one line per epoch (progress of a background
    run)."""
    import functools
    import pickle

    import jax
    import jax.numpy as jnp
    import optax
    from tqdm.auto import tqdm

    from data_tools.bundle_files.writes import atomic_file
    from data_tools.datasets.pcam_bank import load_bank, pool_rule, split_pools
    from data_tools.features import pcam_cnn
    from data_tools.metrics import roc_auc

    t0 = time.perf_counter()
    arch_ = get_arch(arch)
    shift = SHIFT * arch_.patch_px // 48
    bank = load_bank(patches)
    train_pool, test_pool = split_pools(bank)
    rng = np.random.default_rng([seed, 2024])
    order = rng.permutation(len(train_pool))
    if max_patches is not None:
        order = order[:max_patches]
    n_val = max(GROUPS, int(round(val_fraction * len(order))))
    val_idx, fit_idx = np.sort(order[:n_val]), np.sort(order[n_val:])
    batch = max(GROUPS, batch // GROUPS * GROUPS)
    settings = {
        "arch": arch_.name,
        "seed": seed,
        "epochs": epochs,
        "batch": batch,
        "lr": lr,
        "weight_decay": weight_decay,
        "brightness": brightness,
        "fit": len(fit_idx),
    }
    ck = None
    if checkpoint is not None and Path(checkpoint).exists():  # checked before the slow part (decoding)
        from data_tools.errors import HistojaxDataError

        try:
            with open(checkpoint, "rb") as fh:
                ck = pickle.load(fh)  # a file this command wrote (trusted, like the run folder it sits in)
        except Exception as e:  # truncated or foreign file
            raise HistojaxDataError(
                checkpoint, f"not a train-encoder checkpoint ({type(e).__name__}); remove it to start afresh"
            ) from None
        if not isinstance(ck, dict) or ck.get("settings") != settings:
            got = ck.get("settings") if isinstance(ck, dict) else None
            raise HistojaxDataError(
                checkpoint,
                f"a checkpoint of other settings ({got}, not {settings}); remove it or give another --checkpoint",
            )
    images = at_scale(train_pool.decode(np.arange(len(train_pool))), arch_)
    labels = train_pool.labels.astype(np.int32)
    x_fit, y_fit = images[fit_idx], labels[fit_idx]
    x_val, y_val = images[val_idx], labels[val_idx]
    x_val_stained = stained_copy(x_val, y_val, seed + 1, shift=shift)
    steps_per_epoch = max(1, len(x_fit) // batch)
    total = steps_per_epoch * epochs
    warmup = min(100, steps_per_epoch) if total > min(100, steps_per_epoch) else 0  # a one-step run: no warm-up
    schedule = optax.warmup_cosine_decay_schedule(0.0 if warmup else lr, lr, warmup, total)
    tx = optax.adamw(schedule, weight_decay=weight_decay)
    variables = pcam_cnn.init_variables(seed, arch_)
    opt_state = tx.init(variables["params"])
    net = arch_.module(train=True)
    augment = functools.partial(mosaic_augment, shift=shift, brightness=brightness)

    def loss_fn(params, stats, x, y):
        (f, lg), new = net.apply({"params": params, "batch_stats": stats}, x, mutable=["batch_stats"])
        logit = pcam_cnn.pool(f, lg)[1]
        return optax.sigmoid_binary_cross_entropy(logit, y.astype(jnp.float32)).mean(), new["batch_stats"]

    @jax.jit
    def step(v, opt_state, key, x, y):
        x = augment(key, x.astype(jnp.float32), y)
        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(v["params"], v["batch_stats"], x, y)
        updates, opt_state = tx.update(grads, opt_state, v["params"])
        return {"params": optax.apply_updates(v["params"], updates), "batch_stats": stats}, opt_state, loss

    key = jax.random.PRNGKey(seed)
    best, history, start, spent = None, [], 0, 0.0
    if ck is not None:
        variables, opt_state = ck["variables"], ck["opt_state"]
        key, best, history, start, spent = ck["key"], ck["best"], ck["history"], ck["epoch"], ck["seconds"]
        rng.bit_generator.state = ck["rng"]

    def note(line):
        if log is not None:
            with open(log, "a") as fh:
                fh.write(time.strftime("%H:%M:%S ") + line + "\n")

    note(f"{arch_.name}: {len(fit_idx)} fitted patches, {steps_per_epoch} steps/epoch, epochs {start + 1}..{epochs}")
    bar = tqdm(
        total=epochs * steps_per_epoch,
        initial=start * steps_per_epoch,
        desc=f"train {arch_.name}",
        unit="step",
        disable=not progress,
    )
    for epoch in range(start, epochs):
        perm = rng.permutation(len(x_fit))
        losses = []
        for s in range(steps_per_epoch):
            idx = perm[s * batch : (s + 1) * batch]
            key, sub = jax.random.split(key)
            variables, opt_state, loss = step(
                variables, opt_state, sub, jnp.asarray(x_fit[idx]), jnp.asarray(y_fit[idx])
            )
            losses.append(float(loss))
            bar.update(1)
            if log is not None and s % 10 == 9:
                note(f"epoch {epoch + 1} step {s + 1}/{steps_per_epoch} loss {np.mean(losses):.4f}")
        auc_raw = roc_auc(predict(variables, x_val, arch=arch_), y_val)
        auc_stained = roc_auc(predict(variables, x_val_stained, arch=arch_), y_val)
        history.append(
            {
                "epoch": epoch + 1,
                "loss": round(float(np.mean(losses)), 5),
                "val_auc_raw": round(auc_raw, 4),
                "val_auc_mosaic": round(auc_stained, 4),
            }
        )
        score = (auc_raw + auc_stained) / 2
        if best is None or score > best[0]:
            best = (score, epoch + 1, variables)
        bar.set_postfix(val_auc=f"{auc_raw:.3f}/{auc_stained:.3f}")
        note(f"epoch {epoch + 1}/{epochs}: {history[-1]}")
        if checkpoint is not None:
            with atomic_file(Path(checkpoint)) as tmp:
                Path(tmp).write_bytes(
                    pickle.dumps(
                        {
                            "settings": settings,
                            "variables": jax.tree_util.tree_map(np.asarray, variables),
                            "opt_state": jax.tree_util.tree_map(np.asarray, opt_state),
                            "key": np.asarray(key),
                            "best": (best[0], best[1], jax.tree_util.tree_map(np.asarray, best[2])),
                            "history": history,
                            "epoch": epoch + 1,
                            "seconds": spent + time.perf_counter() - t0,
                            "rng": rng.bit_generator.state,
                        }
                    )
                )
    bar.close()
    report = {
        "encoder": arch_.name,
        "seed": int(seed),
        "epochs": int(epochs),
        "batch": int(batch),
        "lr": lr,
        "weight_decay": weight_decay,
        "val_fraction": val_fraction,
        "patch_px": arch_.patch_px,
        "mpp": arch_.mpp,
        "layers": [list(c) for c in arch_.layers],
        "augmentations": {
            "stain": f"per-channel optical density x STAIN_RANGE x DENSITY_RANGE per group of {batch // GROUPS}",
            "p_colour_match": P_MATCH,
            "p_raw": P_RAW,
            "channel_gain": 0.05,
            "brightness": brightness,
            "dihedral": 8,
            "shift_px": shift,
        },
        "best_epoch": best[1],
        "val_auc_mean_of_raw_and_mosaic": round(best[0], 4),
        "patches": bank.source,
        "patches_sha256": bank_digest(bank),
        "bank_patches": len(bank),
        "pool_rule": pool_rule(),
        "training_pool_patches": len(train_pool),
        "fitted_patches": len(fit_idx),
        "validation_patches": len(val_idx),
        "test_pool_patches": len(test_pool),
        "training_pool_sha256": bank_digest(train_pool),
        "history": history,
        "train_seconds": round(spent + time.perf_counter() - t0, 1),
        "jax": jax.__version__,
    }
    return best[2], report


def fit_linear_probe(emb: np.ndarray, labels: np.ndarray, l2: float = 1e-3, iters: int = 30):
    """L2-regularised logistic regression by Newton's method on standardised embeddings ``emb (N, D)``;
    returns a function ``(M, D) → scores (M,)``."""
    mu, sd = emb.mean(0), emb.std(0) + 1e-6
    x = np.concatenate([(emb - mu) / sd, np.ones((len(emb), 1))], axis=1).astype(np.float64)
    y = np.asarray(labels, np.float64)
    w = np.zeros(x.shape[1])
    reg = l2 * len(x) * np.eye(x.shape[1])
    reg[-1, -1] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-np.clip(x @ w, -30, 30)))
        grad = x.T @ (p - y) + reg @ w
        hess = (x * (p * (1 - p))[:, None]).T @ x + reg
        step = np.linalg.solve(hess + 1e-9 * np.eye(len(w)), grad)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return lambda e: np.concatenate([(np.asarray(e) - mu) / sd, np.ones((len(e), 1))], axis=1) @ w


def test_pool_auc(
    variables, patches=None, limit: int | None = None, seed: int = 0, arch=None, probe: bool = False
) -> dict:
    """Patch AUC of ``variables`` on the **test pool** of ``patches`` (never trained on), on PCam's own
    colours and on a fixed mosaic-like stain: ``{"raw": auc, "mosaic": auc, "patches": n, "intervals": {...}}``
    (``intervals``: :func:`data_tools.metrics.roc_auc_with_interval` of each). ``arch``: the network's name (default
    ``pcam-cnn``). ``probe``: also a linear probe (:func:`fit_linear_probe`) on the 64 embedding numbers, fitted on
    the whole **training pool** (PCam colours, and a mosaic-stained copy for the mosaic figure) and scored on the
    same test-pool patches: ``probe_raw``, ``probe_mosaic``."""
    from data_tools.datasets.pcam_bank import load_bank, split_pools
    from data_tools.metrics import roc_auc_with_interval

    arch_ = get_arch(arch)
    shift = SHIFT * arch_.patch_px // 48
    train_pool, test_pool = split_pools(load_bank(patches))
    idx = np.arange(len(test_pool))
    if limit is not None and limit < len(idx):
        idx = np.sort(np.random.default_rng([seed, 7]).choice(idx, limit, replace=False))
    x = at_scale(test_pool.decode(idx), arch_)
    y = test_pool.labels[idx]
    x_mosaic = stained_copy(x, y, 99, shift=shift)
    scores = {"raw": predict(variables, x, arch=arch_), "mosaic": predict(variables, x_mosaic, arch=arch_)}
    if probe:
        x_fit = at_scale(train_pool.decode(np.arange(len(train_pool))), arch_)
        y_fit = train_pool.labels
        for name, fit_images, test_images in (
            ("probe_raw", x_fit, x),
            ("probe_mosaic", stained_copy(x_fit, y_fit, 98, shift=shift), x_mosaic),
        ):
            f = fit_linear_probe(predict(variables, fit_images, arch=arch_, embed=True), y_fit)
            scores[name] = f(predict(variables, test_images, arch=arch_, embed=True))
    intervals = {
        k: {m: round(float(v), 4) if isinstance(v, float) else v for m, v in roc_auc_with_interval(sc, y).items()}
        for k, sc in scores.items()
    }
    out = {k: intervals[k]["auc"] for k in scores}
    out.update(patches=int(len(idx)), intervals=intervals)
    return out


def views_per_second(arch=None, variables=None, batch: int = 256, size: int = 128, seconds: float = 5.0) -> float:
    """``embed`` throughput of ``arch`` on uint8 ``(batch, size, size, 3)`` views on this machine's default JAX
    device, compile excluded (views/s)."""
    import jax

    from data_tools.features import pcam_cnn

    arch_ = get_arch(arch)
    variables = variables if variables is not None else pcam_cnn.init_variables(0, arch_)
    f = jax.jit(lambda v, x: pcam_cnn.apply(v, x, arch_)[0])
    x = jax.numpy.asarray(np.random.default_rng(0).integers(0, 256, (batch, size, size, 3), dtype=np.uint8))
    f(variables, x).block_until_ready()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        f(variables, x).block_until_ready()
        n += batch
    return n / (time.perf_counter() - t0)


def save_weights(variables, out, report: dict) -> Path:
    """Write ``out`` (msgpack) and ``out.json`` (the report) atomically."""
    from flax import serialization

    from data_tools.bundle_files.writes import atomic_file, write_json

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        Path(tmp).write_bytes(
            serialization.msgpack_serialize(
                serialization.to_state_dict(__import__("jax").tree_util.tree_map(np.asarray, variables))
            )
        )
    write_json(out.with_suffix(".json"), report)
    return out


def add_arguments(p) -> None:
    """The options of ``python -m data_tools train-encoder``."""
    p.add_argument(
        "--patches",
        default=None,
        help="PCam patches: folder with 0/ and 1/, its .tar.gz, or a bank .npz "
        "(default: the shipped 1,000-patch bank; the shipped weights were trained on "
        "pcam_train_patches.tar.gz, 20,000 patches)",
    )
    p.add_argument("--out", required=True, help="weights file to write (.msgpack; a .json report beside it)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--max-patches", type=int, default=None, help="use at most N training-pool patches (quick runs)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--arch",
        default=None,
        choices=["pcam-cnn", "pcam-cnn96"],
        help="the network: pcam-cnn (48-px patches at 1.94 µm/px, default) or pcam-cnn96 (96 px at 0.97 µm/px)",
    )
    p.add_argument("--brightness", type=float, default=0.0, help="per-patch brightness jitter, 1 ± this (default 0)")
    p.add_argument("--checkpoint", default=None, help="file written after every epoch; rerun with it to resume")
    p.add_argument("--log", default=None, help="text file that gets one line per epoch (background runs)")
    p.add_argument("--probe", action="store_true", help="also score a linear probe on the embedding (test pool)")


def run(args, parser=None) -> int:
    """Train, score the test pool once, write the weights and report."""
    variables, report = train(
        args.patches,
        seed=args.seed,
        epochs=args.epochs,
        batch=args.batch,
        lr=args.lr,
        max_patches=args.max_patches,
        progress=not args.quiet,
        arch=args.arch,
        brightness=args.brightness,
        checkpoint=args.checkpoint,
        log=args.log,
    )
    report["test_pool_auc"] = test_pool_auc(variables, args.patches, arch=args.arch, probe=args.probe)
    report["command"] = "python -m data_tools train-encoder " + " ".join(sys.argv[2:] if len(sys.argv) > 2 else [])
    out = save_weights(variables, args.out, report)
    print(
        f"wrote {out}: best epoch {report['best_epoch']}/{report['epochs']}, validation AUC "
        f"{report['val_auc_mean_of_raw_and_mosaic']:.3f}; test-pool patch AUC {report['test_pool_auc']['raw']:.3f} "
        f"(PCam colours), {report['test_pool_auc']['mosaic']:.3f} (mosaic stain) on "
        f"{report['test_pool_auc']['patches']} patches; {report['train_seconds']:.0f} s"
    )
    return 0


__all__ = [
    "add_arguments",
    "at_scale",
    "box_half",
    "fit_linear_probe",
    "get_arch",
    "mosaic_augment",
    "run",
    "save_weights",
    "test_pool_auc",
    "train",
    "views_per_second",
]
