"""The pictures of an evaluation: ``trajectory_<policy>.png``, ``reading_<policy>_tumour.png`` / ``_normal.png``
and ``trajectory.gif`` of one episode (``histojax.render``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from histojax.render import animate, render_reading_map, render_trajectory
from baselines.evaluate.rollout import episode_labels, trajectory



def _tag(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "")


def _shown_episode(ep: dict, among=None) -> int:
    """The episode a picture shows: the first successful one (of ``among``, default all), else the first."""
    among = np.arange(ep["success"].size) if among is None else np.asarray(among)
    hit = among[ep["success"][among].astype(bool)]
    return int(hit[0] if hit.size else among[0])


def write_pictures(env, env_params, episodes: dict, out: Path, env_id: str) -> list[Path]:
    """For every policy of ``episodes`` (:func:`run_episodes` output by name): ``trajectory_<policy>.png`` of
    one episode on its own slide (the first that reached its target, else the first), ``trajectory.gif`` of
    the first policy's, and reading maps ``reading_<policy>_tumour.png`` / ``_normal.png`` (where it read on
    the first episode of a tumour and of a normal slide, with its tumour score when it has one). Returns
    the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, ep in episodes.items():
        i = _shown_episode(ep)
        z, x, y = trajectory(ep, i)
        s = int(ep["slide"][i])
        path = out / f"trajectory_{_tag(name)}.png"
        render_trajectory(env, z, x, y, path=path, slide_index=s,
                          title=f"{env_id}, {name}, {len(z) - 1} steps, "
                                f"target {'reached' if ep['success'][i] else 'not reached'}")
        written.append(path)
        known = getattr(env_params.slide, "slide_label", None) is not None
        labels = episode_labels(env_params, ep["slide"]) if known else np.full(ep["slide"].shape, -1)
        for label, kind in ((1, "tumour"), (0, "normal"), (-1, "slide")):  # -1: slides without a label
            on = np.flatnonzero(labels == label)
            if not on.size:
                continue
            j = int(on[0])
            score = float(ep["tumour_score"][j]) if "tumour_score" in ep else \
                ("target reached" if ep["success"][j] else "target not reached")
            path = out / f"reading_{_tag(name)}_{kind}.png"
            render_reading_map(env, env_params, {"z": ep["z"][:, j], "x": ep["x"][:, j], "y": ep["y"][:, j],
                                                 "length": ep["length"][j]},
                               slide_index=int(ep["slide"][j]), score=score, path=path, title=f"{env_id}, {name}")
            written.append(path)
    first = next(iter(episodes))
    ep = episodes[first]
    i = _shown_episode(ep)
    written.append(animate(env, *trajectory(ep, i), out / "trajectory.gif", slide_index=int(ep["slide"][i]),
                           params=env_params))
    return written
