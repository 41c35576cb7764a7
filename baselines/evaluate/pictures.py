"""The pictures of an evaluation: ``trajectory_<policy>.png``, ``reading_<policy>_tumour.png`` / ``_normal.png``
and ``trajectory.gif`` of one episode (``histojax.render``). Through a slide head (``evaluate --head``, or a reader's
own head), each reading map also shows the head's per-view scores of the slide's finest views beside where the
agent read (:func:`head_scores_map`, :func:`reading_with_scores`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from baselines import outputs
from baselines.episodes.rollout import episode_labels, trajectory
from histojax.render import animate, bundle_of, render_reading_map, render_trajectory, tumour_rings, view_box_level0


def head_scores_map(env, env_params, head, slide_index: int) -> tuple[np.ndarray, float] | None:
    """``(scores (gh, gw) float32, level-0 px per grid cell)``: ``head``'s per-view scores (``head.view_logits``:
    a learned head's calibrated instance logits, a logit head's view logit) of slide ``slide_index``'s finest
    feature grid; None when the slides carry no feature grid or not of the head's length."""
    slides = getattr(env_params, "slide", None)
    if slides is None or getattr(slides, "features", None) is None or not hasattr(head, "view_logits"):
        return None
    s = slides.select(int(slide_index))
    z = env.n_levels - 1
    off = int(np.asarray(s.feature_offset)[z])
    gw, gh = int(np.asarray(s.feature_grid_width)[z]), int(np.asarray(s.feature_grid_height)[z])
    grid = np.asarray(s.features[off : off + gw * gh], np.float32).reshape(gh, gw, -1)
    want = getattr(head, "features_dim", None)
    if (want is not None and grid.shape[-1] != want) or (
        want is None and not 0 <= getattr(head, "dim", -1) < grid.shape[-1]
    ):
        return None
    cell = float(np.asarray(s.feature_stride)) * float(bundle_of(env, slide_index).downsamples[z])
    return np.asarray(head.view_logits(grid), np.float32), cell


def reading_with_scores(env, env_params, head, record: dict, slide_index: int, score, path: Path, title: str) -> Path:
    """The reading map of one episode (``record``: its per-step ``z``, ``x``, ``y``, ``length``;
    :func:`histojax.render.render_reading_map`) with, beside it, ``head``'s per-view scores of the slide's finest
    views (:func:`head_scores_map`), every view the agent stood on outlined and the annotated tumour in green; the
    map alone when the head gives no per-view scores of these features. Written to ``path`` (PNG); returns it."""
    scored = head_scores_map(env, env_params, head, slide_index)
    if scored is None:
        render_reading_map(env, env_params, record, slide_index=slide_index, score=score, path=path, title=title)
        return Path(path)
    picture = render_reading_map(env, env_params, record, slide_index=slide_index, score=score, title=title)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    values, cell = scored
    gh, gw = values.shape
    h, w = picture.shape[:2]
    fig = Figure(figsize=(w / 100 + 6.0, max(h / 100, 4.0)), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2)
    left.imshow(picture)
    left.set_axis_off()
    im = right.imshow(values, cmap="magma", interpolation="nearest", extent=(0, gw * cell, gh * cell, 0))
    fig.colorbar(im, ax=right, fraction=0.04, label="head's per-view score (logit)")
    n = int(record["length"]) + 1
    seen = sorted({(int(a), int(b), int(c)) for a, b, c in zip(record["z"][:n], record["x"][:n], record["y"][:n])})
    for zi, xi, yi in seen:
        x0, y0, x1, y1 = view_box_level0(env, zi, xi, yi, slide_index)
        right.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="#00c8ff", linewidth=1.0))
    for ring in tumour_rings(env, slide_index):
        right.plot(ring[:, 0], ring[:, 1], color="#2ecc71", linewidth=1.2)
    right.set_xlim(0, gw * cell)  # a view box larger than the grid (the overview at reset) is cut at its edge
    right.set_ylim(gh * cell, 0)
    right.set_title(panel_title(head.name, len(seen)), fontsize="small")
    right.set_xticks([])
    right.set_yticks([])
    return outputs.save_figure(fig, path)


def panel_title(head_name: str, stood_on: int, width: int = 60) -> str:
    """The title of the head's panel beside a reading map, wrapped to lines of at most ``width`` characters so
    that no word of it is cut at the figure's edge: the head, then what the outlines mean."""
    import textwrap

    return "\n".join(
        [
            *textwrap.wrap(f"per-view scores of {head_name}", width),
            *textwrap.wrap(
                f"cyan: the {stood_on} view{'' if stood_on == 1 else 's'} the agent stood on; green: tumour", width
            ),
        ]
    )


def _tag(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "")


def _shown_episode(ep: dict, among=None) -> int:
    """The episode a picture shows: the first successful one (of ``among``, default all), else the first."""
    among = np.arange(ep["success"].size) if among is None else np.asarray(among)
    hit = among[ep["success"][among].astype(bool)]
    return int(hit[0] if hit.size else among[0])


def picked_words(ep: dict, i: int) -> str:
    """How episode ``i`` (:func:`_shown_episode`) was picked among ``ep``'s episodes, for a picture's title:
    ``"1 of 187 successes among 1,024 episodes"``, or ``"none of 1,024 episodes succeeded: the first"`` (a picture
    of a success says nothing about the success rate)."""
    n, hits = int(ep["success"].size), int(np.asarray(ep["success"]).astype(bool).sum())
    if not bool(ep["success"][i]):
        return f"none of {n:,} episodes succeeded: the first" if n > 1 else "the only episode"
    return f"1 of {hits:,} success{'es' if hits != 1 else ''} among {n:,} episode{'s' if n != 1 else ''}"


def write_pictures(env, env_params, episodes: dict, out: Path, env_id: str, head=None) -> list[Path]:
    """For every policy of ``episodes`` (:func:`run_episodes` output by name): ``trajectory_<policy>.png`` of
    one episode on its own slide (the first that succeeded, else the first; its title says so: :func:`picked_words`),
    ``trajectory.gif`` of
    the first policy's, and reading maps ``reading_<policy>_tumour.png`` / ``_normal.png`` (where it read on
    the first episode of a tumour and of a normal slide, with its tumour score when it has one; with ``head``, the
    head's per-view scores beside it: :func:`reading_with_scores`). Returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, ep in episodes.items():
        i = _shown_episode(ep)
        z, x, y = trajectory(ep, i)
        s = int(ep["slide"][i])
        path = out / f"trajectory_{_tag(name)}.png"
        render_trajectory(
            env,
            z,
            x,
            y,
            path=path,
            slide_index=s,
            title=f"{env_id}, {name}, {len(z) - 1} steps, "
            f"{'success' if ep['success'][i] else 'no success'} ({picked_words(ep, i)})",
        )
        written.append(path)
        known = getattr(env_params.slide, "slide_label", None) is not None
        labels = episode_labels(env_params, ep["slide"]) if known else np.full(ep["slide"].shape, -1)
        for label, kind in ((1, "tumour"), (0, "normal"), (-1, "slide")):  # -1: slides without a label
            on = np.flatnonzero(labels == label)
            if not on.size:
                continue
            j = int(on[0])
            score = (
                float(ep["tumour_score"][j])
                if "tumour_score" in ep
                else ("target reached" if ep["success"][j] else "target not reached")
            )
            path = out / f"reading_{_tag(name)}_{kind}.png"
            record = {"z": ep["z"][:, j], "x": ep["x"][:, j], "y": ep["y"][:, j], "length": ep["length"][j]}
            if "fraction_read" in ep:  # the legend's figure: what the table says it read
                record["fraction_read"] = float(np.asarray(ep["fraction_read"]).reshape(-1)[j])
            if head is not None:
                reading_with_scores(
                    env, env_params, head, record, int(ep["slide"][j]), score, path, f"{env_id}, {name}"
                )
            else:
                render_reading_map(
                    env,
                    env_params,
                    record,
                    slide_index=int(ep["slide"][j]),
                    score=score,
                    path=path,
                    title=f"{env_id}, {name}",
                )
            written.append(path)
    first = next(iter(episodes))
    ep = episodes[first]
    i = _shown_episode(ep)
    written.append(
        animate(env, *trajectory(ep, i), out / "trajectory.gif", slide_index=int(ep["slide"][i]), params=env_params)
    )
    return written
