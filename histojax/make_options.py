"""The options of :func:`histojax.make`: one typed set.

:class:`MakeOptions` is a frozen dataclass whose fields are every keyword setting ``make`` (and a registered id's
:class:`~histojax.registry.EnvSpec`) takes beyond the slides; each field says in its metadata where it goes:

* ``"static"`` — a :class:`~histojax.core.env.HistoEnv` setting, fixed at trace time (``action_mode``, ``n_levels``, …);
* ``"params"`` — an :class:`~histojax.core.env.EnvParams` field, a traced value (``max_steps_in_episode``, …);
* ``"mode"`` — a setting of the action mode's ``prepare`` (``read_budget``, ``glimpse_grid``, …);
* ``"dataset"`` — how ``make`` draws and checks a dataset's slides (``tumour_slides_only``, …).

A field not given holds :data:`UNSET` (the id's registered value, else the env's default, applies). Dict
settings (a scenario file, a trainer's ``env_kwargs``, ``--set key=value``) become options through
:meth:`MakeOptions.of`, which refuses an unknown name in one line.
"""

from __future__ import annotations

import dataclasses
from typing import Any

STATIC, PARAMS, MODE, DATASET = "static", "params", "mode", "dataset"
KINDS = (STATIC, PARAMS, MODE, DATASET)


class _Unset:
    """The value of an option not given."""

    def __repr__(self) -> str:
        return "UNSET"

    def __reduce__(self):
        return "UNSET"


UNSET: Any = _Unset()


def option(kind: str, doc: str):
    """A :class:`MakeOptions` field of ``kind`` (one of :data:`KINDS`), unset by default."""
    assert kind in KINDS, kind
    return dataclasses.field(default=UNSET, metadata={"kind": kind, "doc": doc})


@dataclasses.dataclass(frozen=True)
class MakeOptions:
    """Every setting of ``make`` beyond the slides, typed; each field's ``metadata["kind"]`` says where it goes."""

    # static: HistoEnv settings (trace-time constants)
    tile_size: int = option(STATIC, "view size in px; only for the sample slide, where it selects another bundle")
    action_mode: Any = option(STATIC, "discrete | continuous | glimpse[:LEVEL] | zoom_select[:K] | an ActionMode")
    obs_mode: Any = option(STATIC, "pixels | features | …, or an ObsMode")
    with_position: bool = option(STATIC, "observation dict with the view position")
    reward: str = option(STATIC, "reward preset (histojax.core.rewards.PRESETS)")
    auto_reset: bool = option(STATIC, "reset inside step at the end of an episode")
    n_levels: int = option(STATIC, "levels of the pyramid the agent moves through")
    task: str = option(STATIC, "detection | classification")
    augment: bool = option(STATIC, "a random orientation of the slide per episode")
    final_observation: bool = option(STATIC, "info carries the last observation of an episode")
    step_obs: bool = option(STATIC, "reading modes: a step observes only what it changed")
    # params: EnvParams fields (traced)
    max_steps_in_episode: int = option(PARAMS, "truncation at this many steps")
    stride: float = option(PARAMS, "move length in view widths")
    success_threshold: float = option(PARAMS, "tumour fraction of the finest view that counts as found")
    step_cost: float = option(PARAMS, "paid every step")
    success_bonus: float = option(PARAMS, "paid on success")
    histogym_scale: float = option(PARAMS, "'histogym' reward per unit tumour fraction at the finest level")
    dense_weight: float = option(PARAMS, "'dense' reward: weight of the potential difference")
    random_start: bool = option(PARAMS, "False: HistoGym's fixed start, top-left of the coarsest level")
    start_level: int = option(PARAMS, "navigation modes: the level episodes start at")
    diagnosis_reward: float = option(PARAMS, "classification: + for a right diagnosis, - for a wrong one")
    # mode: the action mode's prepare (histojax.core.modes.base and the reading modes)
    read_budget: float = option(MODE, "fraction of finest-level tissue views an episode may read")
    track_reading: bool = option(MODE, "pan/zoom modes report fraction_read and fields_of_view in info")
    glimpse_grid: tuple = option(MODE, "glimpse: the padded cell grid (H, W)")
    read_slots: int = option(MODE, "glimpse: slots of the cells-read list of a step observation")
    map_feature: int = option(MODE, "discrete:map: the feature entry the coarse map shows")
    map_level: int = option(MODE, "discrete:map: the level of the coarse map")
    map_head: str = option(
        MODE, "discrete:map: a slide head folder whose per-view scores the coarse map shows (instead of map_feature)"
    )
    # dataset: how make draws and checks a dataset's slides
    tumour_slides_only: bool = option(DATASET, "detection: reset draws only slides with tumour annotated")
    dataset_format: int = option(DATASET, "the least dataset.json format this id needs")
    dataset_encoder: str = option(DATASET, "the feature encoder this id's datasets must have")

    @classmethod
    def names(cls, *kinds: str) -> tuple[str, ...]:
        """The option names of ``kinds`` (all kinds when none is given), in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls) if not kinds or f.metadata["kind"] in kinds)

    @classmethod
    def of(cls, settings: dict, where: str = "make", allowed: tuple[str, ...] = KINDS) -> MakeOptions:
        """``settings`` (a dict of option names) as options; ``TypeError`` naming ``where`` and the unknown names
        (and the static and params names) when a name is not an option of ``allowed`` kinds."""
        unknown = set(settings) - set(cls.names(*allowed))
        if unknown:
            raise TypeError(
                f"{where} got unknown settings {sorted(unknown)}; "
                f"static: {cls.names(STATIC)}; params: {cls.names(PARAMS)}"
            )
        return cls(**settings)

    def given(self, *kinds: str) -> dict:
        """``{name: value}`` of the options set (not :data:`UNSET`) of ``kinds`` (all when none is given)."""
        return {n: getattr(self, n) for n in self.names(*kinds) if getattr(self, n) is not UNSET}

    def over(self, base: MakeOptions) -> MakeOptions:
        """``base`` with the options set here put over it."""
        return dataclasses.replace(base, **self.given())
