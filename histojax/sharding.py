"""Slides sharded over devices: each device of a 1-D ``jax.sharding.Mesh`` holds its own slides.

A *sharded dataset* is a ``SlideArrays`` whose every leaf has a leading device axis ``G`` (the
mesh size) split over the mesh axis (``"batch"`` by default): row ``d`` is the stacked dataset
(:func:`histojax.loading.stack_slides`) of the slides of device ``d``, with offsets local to it, so
device ``d`` stores only its slides' pixels / pools / tables / feature grids and memory per device
falls as ``1 / G``. Groups are padded to one shape: flat arrays with zeros at the end (never
read: the offsets stay inside each group's data), per-slide arrays by repeating the group's last
slide with sampling weight 0 (``slide_logits = -inf``, never drawn), start logits with ``-inf``.
Slides go to devices round-robin (slide ``i`` to device ``i % G``), so group sizes differ by at
most one; every device draws uniformly (or by ``slide_weights``) among its own slides only.

Environments run with :func:`vmap_local`: the env batch is split in ``G`` contiguous blocks and
block ``d`` steps on device ``d`` against row ``d`` of the slides (``jax.shard_map``), so no slide
byte crosses devices. ``state.slide_index`` is the index *within the device's group*; the global
slide is ``groups[d][state.slide_index]`` (:func:`slide_groups`).

Several processes (``jax.distributed.initialize``): each process loads only the groups of the
mesh devices it addresses; the padded shapes are agreed with one small all-gather.
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from histojax.core.slide import SlideArrays

# leaves of a stacked SlideArrays with one row per slide (the others are flat pools / tables)
PER_SLIDE = (
    "level_offset",
    "level_width",
    "level_height",
    "downsample",
    "sat_offset",
    "start_logits",
    "feature_offset",
    "feature_grid_width",
    "feature_grid_height",
    "feature_stride",
    "slide_label",
    "slide_logits",
    "tile_offset",
    "tile_grid_width",
)


def round_robin(items: list, n: int) -> list[list]:
    """``items`` dealt to ``n`` groups: group ``d`` = ``items[d::n]`` (sizes differ by at most 1).
    Raises ``ValueError`` when there are fewer items than groups."""
    if len(items) < n:
        raise ValueError(
            f"{len(items)} slide(s) cannot be sharded over {n} devices: every device needs at "
            "least one slide (use fewer devices, or more slides)"
        )
    return [list(items[d::n]) for d in range(n)]


def pad_leaf(a: np.ndarray, shape: tuple, name: str) -> np.ndarray:
    """``a`` padded at the end of every axis to ``shape`` (see the module doc for the fill)."""
    if a.shape == tuple(shape):
        return a
    if name not in PER_SLIDE:  # flat pool / table: zeros, never read
        return np.pad(a, [(0, s - d) for s, d in zip(shape, a.shape)])
    if name == "slide_logits":
        return np.pad(a, [(0, shape[0] - a.shape[0])], constant_values=-np.inf)
    if name == "start_logits":  # spatial padding -inf, then the slide axis by repetition
        a = np.pad(a, [(0, 0)] + [(0, s - d) for s, d in zip(shape[1:], a.shape[1:])], constant_values=-np.inf)
    return np.pad(a, [(0, shape[0] - a.shape[0])] + [(0, 0)] * (a.ndim - 1), mode="edge")


def host_leaves(slide: SlideArrays) -> dict[str, np.ndarray]:
    """The non-None leaves of a ``SlideArrays`` as host numpy arrays (copies), by field name."""
    return {
        f.name: np.array(getattr(slide, f.name))
        for f in dataclasses.fields(slide)
        if getattr(slide, f.name) is not None and f.name != "start_cdf"
    }  # derived: padding changes it


def _global_shapes(local: list[dict[str, np.ndarray]]) -> dict[str, tuple]:
    """Per leaf, the elementwise-largest shape over all groups of all processes."""
    names = sorted(local[0])
    if any(sorted(g) != names for g in local):
        raise ValueError("the slide groups differ in which arrays they hold (features, tiled): build them alike")
    flat = np.array([[d for n in names for d in g[n].shape] for g in local], np.int64).max(axis=0)
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        flat = np.asarray(multihost_utils.process_allgather(flat)).reshape(-1, flat.size).max(axis=0)
    shapes, i = {}, 0
    for n in names:
        k = local[0][n].ndim
        shapes[n] = tuple(int(v) for v in flat[i : i + k])
        i += k
    return shapes


def place_groups(groups: dict[int, SlideArrays], mesh: Mesh, axis: str = "batch") -> SlideArrays:
    """A sharded dataset from ``groups[d]``: the stacked ``SlideArrays`` (host or any device) of
    mesh position ``d``, for every position this process addresses. Leaves get shape
    ``(G, *padded)`` with ``G = mesh.size``, placed with ``NamedSharding(mesh, P(axis))`` so
    device ``d`` holds only row ``d``. Raises ``ValueError`` when a local position is missing."""
    devices = list(mesh.devices.flat)
    local = [d for d, dev in enumerate(devices) if dev.process_index == jax.process_index()]
    missing = sorted(set(local) - set(groups))
    if missing:
        raise ValueError(f"no slides given for mesh devices {missing} of this process")
    host = {d: host_leaves(groups[d]) for d in local}
    shapes = _global_shapes([host[d] for d in local])
    sharding = NamedSharding(mesh, P(axis))
    out = {}
    for name, shape in shapes.items():
        dtype = np.result_type(*[host[d][name].dtype for d in local])
        shards = [jax.device_put(pad_leaf(host[d][name].astype(dtype), shape, name)[None], devices[d]) for d in local]
        out[name] = jax.make_array_from_single_device_arrays((len(devices), *shape), sharding, shards)
    return SlideArrays(**{f.name: out.get(f.name) for f in dataclasses.fields(SlideArrays)})


def local_view(slide: SlideArrays) -> SlideArrays:
    """Row 0 of every leaf: inside :func:`vmap_local` the device's own stacked dataset."""
    return jax.tree.map(lambda a: a[0], slide)


def first_local_group(slide: SlideArrays) -> SlideArrays:
    """The stacked dataset of this process's first mesh device, on that device (an ordinary
    multi-slide ``SlideArrays``, e.g. for an evaluation on one device)."""
    return jax.tree.map(lambda a: a.addressable_shards[0].data[0], slide)


def param_specs(params, axis: str = "batch"):
    """``shard_map`` specs for env params holding a sharded dataset: the slide leaves split over
    ``axis``, every other field replicated."""
    others = {f.name: P() for f in dataclasses.fields(params) if f.name != "slide"}
    return params.replace(slide=P(axis), **others)


def vmap_local(fn, mesh: Mesh, num_args: int, axis: str = "batch"):
    """``call(*batched_args, params)``: ``fn(*args_of_one_env, params)`` over an env batch (leading
    axis of every batched arg, divisible by the mesh size) whose ``d``-th contiguous block runs on
    mesh device ``d`` with that device's slides (``params.slide`` a sharded dataset, see
    :func:`place_groups`). Outputs keep the env batch axis, split the same way. Works under
    ``jax.vmap`` (e.g. over seeds) and inside ``jit``."""

    def per_device(params, *args):
        params = params.replace(slide=local_view(params.slide))
        return jax.vmap(fn, in_axes=(0,) * num_args + (None,))(*args, params)

    def call(*args):
        *batched, params = args
        assert len(batched) == num_args, (len(batched), num_args)
        mapped = jax.shard_map(
            per_device,
            mesh=mesh,
            in_specs=(param_specs(params, axis),) + (P(axis),) * num_args,
            out_specs=P(axis),
            check_vma=False,
        )
        return mapped(params, *batched)

    return call


@contextmanager
def on_host():
    """Arrays made inside land on the host's CPU device (``jax.default_device``), not the accelerator."""
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        yield


def slide_groups(paths: list, mesh: Mesh) -> list[list]:
    """The bundle paths of each mesh position (round-robin, see the module doc)."""
    return round_robin(list(paths), mesh.size)


def make_sharded(
    env_id: str,
    mesh: Mesh,
    axis: str = "batch",
    slide=None,
    slides=None,
    dataset=None,
    split: str = "train",
    **overrides,
):
    """``(env, params)`` like :func:`histojax.make` but with the slides sharded over ``mesh``:
    the dataset's bundles (``slides=``, ``dataset=``, or the id's registered dataset) are dealt
    round-robin to the mesh devices (:func:`slide_groups`); each process loads only its devices'
    groups, in host memory (:func:`on_host`), and places each on its device. ``max_device_bytes``
    (an override) bounds one device's group. The other params fields stay as ``make`` gives them
    (replicated when passed to a jitted function on the mesh)."""
    from histojax.registry import make, slide_paths

    kwargs = {k: overrides.pop(k) for k in ("verify", "max_device_bytes", "labels", "slide_weights") if k in overrides}
    if kwargs.get("slide_weights") is not None:
        raise ValueError(
            "slide_weights are not supported with sharded slides (each device draws uniformly among its own slides)"
        )
    kwargs.pop("slide_weights", None)
    paths = slide_paths(env_id, slide=slide, slides=slides, dataset=dataset, split=split, **overrides)
    groups = slide_groups(paths, mesh)
    env = base = None
    stacked = {}
    for d, dev in enumerate(mesh.devices.flat):
        if dev.process_index != jax.process_index():
            continue
        with on_host():
            e, p = make(env_id, slides=groups[d], slide_weights=[1.0] * len(groups[d]), **kwargs, **overrides)
        if env is None:
            env, base = e, p
        stacked[d] = p.slide
    params = base.replace(slide=place_groups(stacked, mesh, axis))
    return dataclasses.replace(env, _default_params=params, _bundle=None, _bundles=()), params


def local_slides(slide: SlideArrays) -> tuple[int, int]:
    """``(slides, bytes)`` of a sharded dataset held by this process's devices (padding slides,
    which are never drawn, not counted among the slides; padding bytes are)."""
    n = sum(int(np.isfinite(np.asarray(s.data)).sum()) for s in slide.slide_logits.addressable_shards)
    return n, sum(device_bytes(slide).values())


def device_bytes(tree) -> dict:
    """Bytes of the jax arrays of ``tree`` per device, from their addressable shards:
    ``{device: bytes}``."""
    out: dict = {}
    for leaf in jax.tree.leaves(tree):
        for shard in leaf.addressable_shards:
            out[shard.device] = out.get(shard.device, 0) + int(shard.data.nbytes)
    return out
