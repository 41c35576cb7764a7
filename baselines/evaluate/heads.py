"""Head scoring: readers whose slide head declares (SASHA's reward, ``histojax.reading.head_reward``), the head's
score per episode and its AUC, with and without ITC-only slides (CAMELYON's lesion classes)."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np

from baselines.episodes.rollout import episode_labels
from baselines.evaluate.checks import one_class
from baselines.run_config import read_run_config
from data_tools.errors import HistojaxDataError
from data_tools.metrics import UNDEFINED
from histojax.reading.heads import encoder_family, same_encoder  # noqa: F401  (encoder_family: this module's API)


def check_head_features(head, encoders: list[str], dim: int) -> None:
    """Refuse (``ValueError``, one line) a slide head that cannot read these slides' features: the slides hold
    another encoder's features than the head records (:func:`histojax.reading.heads.same_encoder`: imported features
    by their folder and file layout), or features of the wrong
    length (``dim`` entries) — a head that reads every entry (``features_dim``: the learned attention-MIL head) needs
    exactly its length, a logit head (``dim``: the entry of the view logit) an entry it reads. Any head kind
    :func:`histojax.reading.heads.load` reads."""
    want = getattr(head, "encoder", None)
    if want and any(not same_encoder(want, e) for e in encoders):
        fit = (
            "python -m baselines.reading.learned_head_fit"
            if hasattr(head, "features_dim")
            else "python -m baselines.reading.head_fit, or learned_head_fit for any encoder"
        )
        raise ValueError(
            f"a slide head for {want} features; these slides hold {', '.join(encoders)} features "
            f"(fit a head on them: {fit})"
        )
    length = getattr(head, "features_dim", None)
    if length is not None:
        if int(length) != dim:
            raise ValueError(
                f"the slide head ({head.kind}) reads {length}-d feature vectors; these slides' features "
                f"have {dim} entries: fit a head on them (python -m baselines.reading.learned_head_fit)"
            )
    elif not 0 <= int(head.dim) < dim:
        raise ValueError(
            f"the slide head reads feature entry {head.dim} ({want or 'its encoder'}'s view "
            f"logit); these slides' features have {dim} entries: score slides embedded with "
            f"{want or 'the encoder the head was fitted on'}"
        )


def head_env(env, env_params, head, settings: dict | None = None):
    """``(env wrapped in HeadReward, lesion classes per slide or None)`` for :func:`evaluate` with a head (any kind
    :func:`histojax.reading.heads.load` reads: a pcam-cnn logit head, a pooled-statistics or MIL head, or the learned
    attention-MIL head of any encoder's features). ``settings``: ``gain``, ``final``, ``read_cost`` of a run's
    ``head_reward.json`` (None: no head reward terms, the env's own reward). ``ValueError`` (one line) when the
    slides' features are not the head's (:func:`check_head_features`)."""
    from histojax.reading.head_reward import HeadReward

    encoders = sorted({str((b.metadata.get("features") or {}).get("encoder")) for b in env.bundles} - {"None"})
    features = getattr(env_params.slide, "features", None)
    check_head_features(head, encoders, int(np.shape(features)[-1]) if features is not None else 0)
    if settings:
        gain = settings.get("gain")
        wrapped = HeadReward(
            env,
            head,
            gain=None if gain in (None, "none", False) else gain,
            final=float(settings.get("final") or 0.0),
            read_cost=float(settings.get("read_cost") or 0.0),
            params=env_params,
        )
    else:
        wrapped = HeadReward(env, head, gain=None, final=0.0, env_reward=True, params=env_params)
    return wrapped, lesion_classes(env, env_params)


def dataset_labelled(env, env_params, config, slide=None):
    """``env_params`` with each slide's label from its dataset's ``dataset.json`` ``labels`` (``config``: the run's
    typed config or record, whose ``env_kwargs`` name the dataset scored), for scoring through a head: a cohort
    labelled by a table without tumour annotated (the TCGA case) keeps the labels the table gave it, where the
    bundles alone would make every slide normal. Unchanged for a single ``slide``, a dataset without labels, or a
    slide the labels do not name."""
    from histojax.datasets import dataset_labels, label_of

    kw = read_run_config(config).env_kwargs or {}
    if slide is not None or not kw.get("dataset"):
        return env_params
    labels = dataset_labels(kw["dataset"])
    if not labels:
        return env_params
    try:
        given = [label_of(b, labels) for b in env.bundles]
    except HistojaxDataError:  # a slide the table does not name: the bundles' own labels stand
        return env_params
    old = np.asarray(jax.device_get(env_params.slide.slide_label))
    new = np.asarray(given, old.dtype).reshape(old.shape) if old.ndim else np.asarray(given[0], old.dtype)
    return env_params.replace(slide=env_params.slide.replace(slide_label=jax.numpy.asarray(new)))


def refuse_one_class(config, env_params, slide=None) -> None:
    """Refuse (``HistojaxDataError``, one line naming the dataset's ``dataset.json`` or the slide) to score through a
    head slides that are all of one class: what the head declares is scored by an AUC, and one class leaves it
    undefined (:data:`~data_tools.metrics.UNDEFINED`), not 1.000 or ``nan``."""
    single = one_class(env_params)
    if single is None:
        return
    kw = read_run_config(config).env_kwargs or {}
    n = int(np.size(np.asarray(jax.device_get(env_params.slide.slide_label))))
    where = Path(kw["dataset"]) / "dataset.json" if kw.get("dataset") and slide is None else Path(slide or "slide")
    split = f"its {kw.get('split', 'train')!r} split" if kw.get("dataset") and slide is None else "the slides scored"
    raise HistojaxDataError(
        where,
        f"{split} holds only {'tumour' if single else 'normal'} slides ({n}): the head's "
        f"AUC is {UNDEFINED}; score a split with tumour and normal slides (--split, --dataset)",
    )


def head_scored(ep: dict, env_params, classes) -> dict:
    """:func:`run_episodes` output of a :class:`~histojax.reading.head_reward.HeadReward` env with the head's
    diagnosis in the fields :func:`summarise` scores: ``tumour_score`` (the head's p(tumour) of what was
    read), ``label``, ``success`` (the head right) and, with ``classes``, ``lesion`` per episode."""
    ep["tumour_score"] = 1.0 / (1.0 + np.exp(-np.asarray(ep["head_score"], np.float64)))
    ep["label"] = episode_labels(env_params, ep["slide"])
    ep["success"] = np.asarray(ep["head_correct"], bool)
    if classes is not None:
        ep["lesion"] = np.asarray(classes)[ep["slide"]]
    return ep


def lesion_classes(env, env_params) -> list[str] | None:
    """CAMELYON's lesion class of each slide of ``env`` (``normal``, ``ITC``, ``micro``, ``macro``:
    :func:`baselines.reading.slides.lesion_of` on the bundle's tumour polygons at its µm/px), or None when a tumour
    slide's class cannot be known (no polygons, no µm/px)."""
    from baselines.reading.slides import lesion_of
    from data_tools.annotations import load_annotations

    labels = np.atleast_1d(np.asarray(jax.device_get(env_params.slide.slide_label))).astype(int)
    out = []
    for bundle, label in zip(env.bundles, np.broadcast_to(labels, (len(env.bundles),))):
        if not label:
            out.append("normal")
            continue
        folder = Path(bundle.path)
        try:
            mpp = float(json.loads((folder / "metadata.json").read_text())["source"]["mpp"])
            geom = load_annotations(folder / "annotations.geojson").tumour
        except (OSError, ValueError, KeyError, TypeError, HistojaxDataError):
            return None
        cls, _ = lesion_of(geom, mpp) if np.isfinite(mpp) and mpp > 0 else ("unknown", None)
        if cls == "unknown":
            return None
        out.append(cls)
    return out
