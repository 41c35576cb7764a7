"""Environment ids → scenarios, and ``make``.

Scenarios (all on the same magnification range of the slide; more levels = smaller zoom steps):

==================  ========  ======================  ===================
id                  levels    max_steps_in_episode    zoom per level (R=16)
==================  ========  ======================  ===================
HistoJAX-Easy-v0    3         100                     4×
HistoJAX-Medium-v0  5         200                     2×
HistoJAX-Hard-v0    7         300                     1.59×
==================  ========  ======================  ===================

The true-scale CAMELYON16 benchmark (``docs/c16-benchmark.md``; geometry real CAMELYON16, pixels real
PCam patches arranged by us, not scanned slides) needs a dataset made by ``python -m data_tools c16``:
``make("HistoJAX-C16-Hard-v0", dataset=DIR, split="train" | "test")`` (or ``$HISTOJAX_C16_DATASET``).

=========================  ========  =====  ==============================================
id                         levels    steps  task
=========================  ========  =====  ==============================================
HistoJAX-C16-Easy-v0       3         100    detection (find a view ≥ 50 % tumour; tumour slides)
HistoJAX-C16-Medium-v0     5         200    detection
HistoJAX-C16-Hard-v0       7         300    detection
HistoJAX-C16-Diagnosis-v0  5         200    classification: declare tumour / no tumour
=========================  ========  =====  ==============================================

``-v1``: pcam-cnn features observed by default, datasets of format 2. ``-v2``: as ``-v1``, and the reading
modes' observations carry only what a step changes (``step_obs=True``; :meth:`HistoEnv.episode_tables`).

Which slides an id loads (dataset folders, splits, folds, labels, the C16 ids' default dataset) is
:mod:`histojax.datasets`; this module keeps the registration of ids and ``make``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from histojax.core.env import EnvParams, HistoEnv
from histojax.core.modes import factory
from histojax.core.modes.base import Navigation
from histojax.core.slide import start_cdf
from histojax.datasets import c16_dataset, dataset_labels, label_of, resolve_slides, tumour_slide_weights
from histojax.loading import DEFAULT_MAX_DEVICE_BYTES, check_alike, load_slide, stack_slides
from histojax.make_options import DATASET, MODE, PARAMS, STATIC, MakeOptions

# the names of make's options by where they go, derived from the one typed set (histojax.make_options.MakeOptions):
# static HistoEnv settings, EnvParams fields, the action mode's prepare settings (histojax.core.modes.base),
# and how make draws a dataset's slides (``tumour_slides_only``: reset draws only slides with tumour annotated;
# ``dataset_format`` / ``dataset_encoder``: the least ``dataset.json`` "format" and the feature encoder a dataset
# must have for this id, an older dataset refused naming the command that rebuilds it)
STATIC_FIELDS = MakeOptions.names(STATIC)
PARAM_FIELDS = MakeOptions.names(PARAMS)
MODE_SETTINGS = MakeOptions.names(MODE)
DATASET_FIELDS = MakeOptions.names(DATASET)
if set(PARAM_FIELDS) != {f.name for f in dataclasses.fields(EnvParams)} - {"slide", "mode_data"}:
    raise AssertionError("MakeOptions' params options must be the EnvParams fields")


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """The one registration record of an environment id, for built-in ids and scenario files alike.

    ``settings`` holds static settings (``STATIC_FIELDS``: ``n_levels``, ``obs_mode``, ``reward``, …),
    ``EnvParams`` defaults (``PARAM_FIELDS``: ``max_steps_in_episode``, …) and dataset settings
    (``DATASET_FIELDS``), spelled as the env spells them. ``slide`` is the id's default slide when ``make`` gets none: a bundle path, a list of
    them (a dataset), or a recipe ``f(settings) -> path(s)`` (e.g. builds into the cache on first use);
    ``None`` means the embedded sample slide. ``scenario`` is the :class:`histojax.scenarios.Scenario`
    it was registered from, if any."""

    id: str
    settings: dict
    slide: object = None
    scenario: object = None

    def __post_init__(self):
        unknown = set(self.settings) - set(MakeOptions.names(STATIC, PARAMS, DATASET))
        if unknown:
            raise TypeError(f"unknown scenario settings {sorted(unknown)}")

    @property
    def options(self) -> MakeOptions:
        """``settings`` as the typed :class:`~histojax.make_options.MakeOptions`."""
        return MakeOptions(**self.settings)


_REGISTRY: dict[str, EnvSpec] = {}


def register(env_id: str, slide=None, **settings) -> EnvSpec:
    """Register an id: ``settings`` are :class:`EnvSpec` settings (static ones such as ``n_levels``,
    ``reward``, and ``EnvParams`` defaults such as ``max_steps_in_episode``); ``slide`` as in
    :class:`EnvSpec`. Returns the record. (:func:`histojax.scenarios.register_scenario` registers a
    scenario file through :func:`register_spec` with the same record.)"""
    return register_spec(EnvSpec(id=env_id, settings=dict(settings), slide=slide))


def register_spec(spec: EnvSpec) -> EnvSpec:
    """Register (or replace) the record ``spec`` under ``spec.id``; returns it."""
    _REGISTRY[spec.id] = spec
    return spec


def spec_of(env_id: str) -> EnvSpec:
    """The registration record of ``env_id`` (ValueError naming the registered ids when unknown)."""
    if env_id not in _REGISTRY:
        raise ValueError(f"unknown environment id {env_id!r}; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY[env_id]


def registered_envs() -> tuple[str, ...]:
    """All registered environment ids."""
    return tuple(_REGISTRY)


register("HistoJAX-Easy-v0", n_levels=3, max_steps_in_episode=100)
register("HistoJAX-Medium-v0", n_levels=5, max_steps_in_episode=200)
register("HistoJAX-Hard-v0", n_levels=7, max_steps_in_episode=300)


# v0: any C16 dataset (the observation is whatever the caller picks; pixels by default).
# v1: datasets of format 2 (train and test slides textured from disjoint PCam patch pools) embedded with the
# PCam-trained encoder ``pcam-cnn``, observed through it by default (obs_mode="features"); an older dataset is
# refused with the command that rebuilds it (it keeps loading under v0).
C16_V1 = dict(dataset_format=2, dataset_encoder="pcam-cnn", obs_mode="features")
for _name, _levels, _steps in (("Easy", 3, 100), ("Medium", 5, 200), ("Hard", 7, 300)):
    register(
        f"HistoJAX-C16-{_name}-v0",
        slide=c16_dataset,
        n_levels=_levels,
        max_steps_in_episode=_steps,
        tumour_slides_only=True,
    )
    register(
        f"HistoJAX-C16-{_name}-v1",
        slide=c16_dataset,
        n_levels=_levels,
        max_steps_in_episode=_steps,
        tumour_slides_only=True,
        **C16_V1,
    )
register("HistoJAX-C16-Diagnosis-v0", slide=c16_dataset, n_levels=5, max_steps_in_episode=200, task="classification")
register(
    "HistoJAX-C16-Diagnosis-v1",
    slide=c16_dataset,
    n_levels=5,
    max_steps_in_episode=200,
    task="classification",
    **C16_V1,
)
# v2: v1's datasets and defaults; the reading modes observe per step only what changed (step_obs=True: for
# glimpse the cells read, their summaries in K slots, the read bits, the budget left and the slide index; the
# slides' cell tables come once from env.episode_tables). Navigation observes the same as under v1. The v1 ids
# keep v1's observation, so policies trained on them (the c16-v1 published readers) still load and run.
for _name, _levels, _steps in (("Easy", 3, 100), ("Medium", 5, 200), ("Hard", 7, 300)):
    register(
        f"HistoJAX-C16-{_name}-v2",
        slide=c16_dataset,
        n_levels=_levels,
        max_steps_in_episode=_steps,
        tumour_slides_only=True,
        step_obs=True,
        **C16_V1,
    )
register(
    "HistoJAX-C16-Diagnosis-v2",
    slide=c16_dataset,
    n_levels=5,
    max_steps_in_episode=200,
    task="classification",
    step_obs=True,
    **C16_V1,
)


def _reading_dataset(spec: dict):
    """The reading ids have no default slides: one clear error asking for ``dataset=``."""
    raise ValueError(
        "HistoJAX-Reading-v0 reads a dataset of your own: make('HistoJAX-Reading-v0', dataset=DIR) with "
        "DIR from `histojax dataset`, `histojax c16` or imported .h5 features (any encoder)"
    )


# Reading on any dataset (any encoder's feature grids, imported .h5 included): the cell-set reader's -v2
# observation (step_obs) on a classification task, five zoom levels (n_levels= for bundles built with fewer)
READING_ID = "HistoJAX-Reading-v0"
register(
    READING_ID,
    slide=_reading_dataset,
    n_levels=5,
    max_steps_in_episode=200,
    task="classification",
    step_obs=True,
    obs_mode="features",
)


def make(
    env_id: str,
    slide=None,
    verify: bool = True,
    max_device_bytes: int = DEFAULT_MAX_DEVICE_BYTES,
    slides=None,
    slide_weights=None,
    dataset=None,
    split: str = "train",
    labels=None,
    fold: int | None = None,
    **overrides,
):
    """Make ``(env, params)`` for a registered id.

    ``slide``: a bundle folder (``python -m data_tools build``) or ``None`` for the id's registered
    slide (``register(..., slide=...)``, e.g. a scenario's recipe) or else the embedded sample slide
    (bundles are built on first use). ``overrides``: the options of :class:`histojax.make_options.MakeOptions`,
    any static setting (``action_mode``, ``obs_mode``, ``with_position``, ``reward``, ``auto_reset``,
    ``augment``; ``tile_size`` only for the sample slide, where it selects another cached bundle) or ``EnvParams`` field
    (``max_steps_in_episode``, ``stride``, ``success_threshold``, ``step_cost``,
    ``success_bonus``, ``histogym_scale``, ``dense_weight``, ``random_start``, ``start_level``), or the reading
    settings of :mod:`histojax.core.seen_views`: ``read_budget`` (fraction of finest-level tissue views, for
    ``action_mode="glimpse"`` / ``"zoom_select"``, or with tracking) and ``track_reading=True`` (the
    pan/zoom modes then report ``fraction_read`` and ``fields_of_view`` in ``info``), and for ``glimpse``,
    ``glimpse_grid=(H, W)``, the padded cell grid (default: the largest of the slides loaded; the
    trainers record it so that a glimpse policy runs on other slides).
    The slide's arrays are put on the device once and returned inside ``params``; a slide
    needing more than ``max_device_bytes`` (default 4 GiB) is refused with a clear error. It bounds the
    arrays put on the device, not the process's host memory (on the CPU backend, where they are host
    memory, ``make`` peaks at about 1.6× them; see :func:`histojax.loading.load_slide`).
    ``verify`` checks every array's SHA-256 against the bundle metadata.

    Datasets: ``slides=[bundle, ...]`` (any sizes, same tile size) or ``dataset=FOLDER`` holding a
    ``dataset.json`` with ``"train"`` / ``"test"`` lists of bundle paths (``split`` picks one; e.g.
    ``python -m data_tools synth``) give one env over all of them (``fold=i`` on a dataset built with
    ``--folds K``: fold ``i``'s sides, see :func:`histojax.datasets.dataset_slides`): ``reset`` draws a slide
    (uniformly, or by ``slide_weights``). ``max_device_bytes`` then bounds the whole dataset.
    ``labels`` (a dict bundle-name → 0/1 or a CSV file with columns ``slide,label``) overrides the
    slide labels of ``task="classification"`` (default: the ``"labels"`` of the dataset's ``dataset.json``
    when it has them, e.g. ``data_tools dataset --labels`` or CAMELYON16's ``reference.csv``, else 1 when
    the bundle has tumour annotated).
    """
    given = MakeOptions.of(overrides, where=f"make({env_id!r})")  # TypeError naming an unknown setting
    options = given.over(spec_of(env_id).options)
    mode_settings = given.given(MODE)  # only as given: a registered id holds no mode settings
    spec = options.given(STATIC, PARAMS, DATASET)
    _check_start_level(
        factory.action_mode(spec.get("action_mode", "discrete")), spec.get("start_level", 0), f"make({env_id!r})"
    )
    slides = resolve_slides(env_id, spec_of(env_id).slide, spec, slide, slides, dataset, split, fold)
    if labels is None and dataset is not None and spec.get("task", "detection") == "classification":
        labels = dataset_labels(dataset)  # a label table's or CAMELYON16's labels, not just "annotated"
    feature_obs = factory.obs_mode(spec.get("obs_mode", "pixels")).needs_features
    features = True if feature_obs or factory.action_mode(spec.get("action_mode", "discrete")).needs_features else None
    check_alike(slides, features=features)  # bundles that cannot make one dataset, named before any array is read
    loaded, budget = [], max_device_bytes
    for path in slides:  # obs_mode="features": the feature-only layout, no pixels on the device
        arrays, bundle = load_slide(
            path, spec["n_levels"], verify=verify, max_device_bytes=budget, features=features, pixels=not feature_obs
        )
        budget -= sum(int(a.nbytes) for a in jax.tree.leaves(arrays))
        loaded.append((arrays, bundle))
    tile_sizes = {b.tile_size for _, b in loaded}
    if len(tile_sizes) != 1:
        raise ValueError(f"the slides were built with different tile sizes {sorted(tile_sizes)}; rebuild them alike")
    tile_size = tile_sizes.pop()
    if spec.get("tile_size", tile_size) != tile_size:
        raise ValueError(
            f"bundle {slides[0]} was built with tile size {tile_size}; rebuild it with "
            f"--tile-size {spec['tile_size']} or drop the override"
        )
    if labels is not None:
        loaded = [(a.replace(slide_label=jnp.int32(label_of(b, labels))), b) for a, b in loaded]
    if spec.get("tumour_slides_only") and spec.get("task", "detection") == "detection":
        slide_weights = tumour_slide_weights([a for a, _ in loaded], slides, slide_weights)
    if len(loaded) == 1 and slide_weights is None:
        arrays = loaded[0][0]
    else:
        arrays = stack_slides([a for a, _ in loaded], weights=slide_weights, consume=True)  # per-slide copies freed
    arrays = arrays.replace(start_cdf=jnp.asarray(start_cdf(arrays.start_logits)))  # once, not at every reset
    static = {**options.given(STATIC), "tile_size": tile_size}
    validate_params(options.given(PARAMS), tile_size, where=f"make({env_id!r})")
    params = EnvParams(slide=arrays, **options.given(PARAMS))
    bundles = tuple(b for _, b in loaded)
    env = HistoEnv(name=env_id, _default_params=params, _bundle=bundles[0], _bundles=bundles, **static)
    mode_data = env.action.prepare(env, params, bundles, **mode_settings)  # per-slide tables of a reading mode, once
    if mode_data is not None:
        params = params.replace(mode_data=mode_data)
        env = dataclasses.replace(env, _default_params=params)
    return env, params


def slide_paths(
    env_id: str, slide=None, slides=None, dataset=None, split: str = "train", fold: int | None = None, **overrides
) -> list:
    """The bundle paths ``make`` would load for these arguments (one for a single slide)."""
    return resolve_slides(
        env_id, spec_of(env_id).slide, {**spec_of(env_id).settings, **overrides}, slide, slides, dataset, split, fold
    )


MAX_STRIDE_PX = 2**30  # a move of stride × tile_size px plus a position (< 2**30 px) stays inside int32


def validate_params(values: dict, tile_size: int, where: str = "make") -> None:
    """Check ``EnvParams`` values given to ``make`` (Python or array scalars; arrays element-wise):
    ``stride`` finite with ``1 <= stride × tile_size <= 2**30`` px (moves cannot wrap int32),
    ``max_steps_in_episode`` an integer in ``[1, 2**31 - 2]``, ``success_threshold`` in ``(0, 1]``,
    rewards (``step_cost``, ``success_bonus``, ``histogym_scale``, ``dense_weight``, ``diagnosis_reward``)
    finite, ``random_start`` a bool, ``start_level`` a whole number. Raises ValueError naming the field."""

    def bad(field, value, rule):
        raise ValueError(f"{where}: {field}={value!r} {rule}")

    def numbers(field):
        try:
            return np.asarray(values[field], dtype=np.float64)
        except (TypeError, ValueError):
            bad(field, values[field], "is not a number")

    for field in values:
        if field == "random_start":
            v = np.asarray(values[field])
            if v.dtype != bool and not (np.issubdtype(v.dtype, np.integer) and np.isin(v, (0, 1)).all()):
                bad(field, values[field], "must be True or False")
            continue
        v = numbers(field)
        if not np.isfinite(v).all():
            bad(field, values[field], "must be finite")
        if field == "stride" and not ((v * tile_size >= 1).all() and (v * tile_size <= MAX_STRIDE_PX).all()):
            bad(
                field,
                values[field],
                f"must be > 0 view widths with 1 <= stride × tile_size ({tile_size}) <= 2**30 px "
                "(a move of stride × tile_size px must stay inside int32)",
            )
        if field == "max_steps_in_episode" and not (
            (v == np.round(v)).all() and (v >= 1).all() and (v <= 2**31 - 2).all()
        ):
            bad(field, values[field], "must be a whole number of steps in [1, 2**31 - 2]")
        if field == "start_level" and not ((v == np.round(v)).all() and (np.abs(v) <= 2**31 - 1).all()):
            bad(field, values[field], "must be a whole level number (0 = coarsest, -1 = finest)")
        if field == "success_threshold" and not ((v > 0).all() and (v <= 1).all()):
            bad(field, values[field], "must be a tumour fraction in (0, 1]")


def check_params(env, params, where: str = "params") -> None:
    """Host-side check of an ``EnvParams`` changed after ``make`` (e.g. ``params.replace(stride=...)``, or a
    vmapped batch of them) against the rules of :func:`validate_params`, for ``env``'s tile size: raises
    ``ValueError`` naming the field instead of letting a move wrap int32, a NaN freeze the view or a
    negative step limit truncate every step. Called by the trainers, ``evaluate`` and the Gymnasium
    adapters; inside ``jit`` use :func:`histojax.debug.checked`, which makes the same checks with
    ``checkify``."""
    values = {k: getattr(params, k) for k in PARAM_FIELDS}
    if any(isinstance(v, jax.core.Tracer) for v in values.values()):
        raise TypeError(f"{where}: check_params runs on the host, not inside jit; use histojax.debug.checked")
    values = {
        k: v.addressable_data(0) if isinstance(v, jax.Array) and not v.is_fully_addressable else v
        for k, v in values.items()
    }  # replicated over several processes: this process's copy
    validate_params(values, env.tile_size, where=where)
    _check_start_level(env.action, values["start_level"], where)


def _check_start_level(mode, start_level, where: str) -> None:
    """``ValueError`` for a ``start_level`` other than 0 with a reading mode (its episodes start at the coarsest
    level; the env would ignore it)."""
    if not isinstance(mode, Navigation) and np.any(np.asarray(start_level) != 0):
        raise ValueError(
            f"{where}: start_level={start_level!r} is for the navigation modes (discrete, continuous); "
            f"{mode.name!r} episodes start at the coarsest level"
        )
