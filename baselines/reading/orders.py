"""The cell orders of the scripted readers and the glimpse env's reading rule, shared by the readers
(:mod:`baselines.reading.readers`) and the budget curve (:mod:`baselines.reading.budget_curve`). A cell table
(``cells``) holds ``valid (C,)`` and ``cell_views (C,)`` per cell and ``total`` tissue views; the readers' tables
also ``cell (H, W)``, ``logit (C,)`` and ``grid``, the budget curve's ``cells (C, D)`` (each cell's coarse features).
The run loop that reads them at every budget is :func:`baselines.reading.pipeline.read_all`.
"""

from __future__ import annotations

import numpy as np

SEARCH_THRESHOLD = 1.0  # pcam-cnn view logit; the scripted features policy's threshold (chosen on v1 validation)


def random_order(cells: dict, rng) -> np.ndarray:
    """The valid cells in a uniformly random order."""
    return rng.permutation(np.flatnonzero(cells["valid"]))


def logit_order(cells: dict) -> np.ndarray:
    """The valid cells by their low-resolution logit, highest first (ties by index)."""
    v = np.flatnonzero(cells["valid"])
    return v[np.argsort(-cells["logit"][v], kind="stable")]


def search_order(slide: dict, cells: dict, threshold: float = SEARCH_THRESHOLD, limit: float = 1.0) -> np.ndarray:
    """The logit order, but after reading a cell whose hottest finest view logit exceeds ``threshold``
    its unread valid neighbours (8-connected) are read next, hottest evidence first. Stops after
    ``limit`` of the tissue views (the largest budget needs no more)."""
    ch, cw = cells["grid"]
    valid = cells["valid"]
    hot = np.full(valid.shape, -np.inf)  # per cell: evidence from read neighbours
    np.maximum.at(hot, cells["cell"][slide["tissue"]], slide["logits"][slide["tissue"]])
    cell_max = hot.copy()  # the hottest tissue view under each cell (known once read)
    hot[:] = -np.inf
    base = logit_order(cells)
    done = np.zeros(valid.shape, bool)
    order, pos, views, stop = [], 0, 0, limit * cells["total"]
    while views < stop:
        frontier = np.where(done | ~valid, -np.inf, hot)
        c = int(np.argmax(frontier))
        if not frontier[c] > -np.inf:
            while pos < len(base) and done[base[pos]]:
                pos += 1
            if pos == len(base):
                break
            c = int(base[pos])
        done[c] = True
        order.append(c)
        views += int(cells["cell_views"][c])
        if cell_max[c] > threshold:
            y, x = divmod(c, cw)
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if (dy or dx) and 0 <= y + dy < ch and 0 <= x + dx < cw:
                        n = (y + dy) * cw + x + dx
                        hot[n] = max(hot[n], cell_max[c])
    return np.asarray(order, np.int64)


def attention_order(table: dict, head) -> np.ndarray:
    """The valid cells by the head's attention on their low-resolution features ``cells (C, D)``, highest first: a
    head that pools the views it reads by attention (its :meth:`view_terms`' attention logit; the softmax weights of
    the cells read as one bag rank the same)."""
    cells = np.flatnonzero(table["valid"])
    att = np.asarray(head.view_terms(np.asarray(table["cells"][cells], np.float32)))[:, 0]
    return cells[np.argsort(-att, kind="stable")]


def score_order(table: dict, head) -> np.ndarray:
    """The valid cells by the head's per-view score (:meth:`view_logits`, any head of the protocol of
    :mod:`histojax.reading.heads`) of their low-resolution features ``cells (C, D)``, highest first: the score reader
    (a logit head's per-view score is its feature entry: the logit reader)."""
    cells = np.flatnonzero(table["valid"])
    score = np.asarray(head.view_logits(np.asarray(table["cells"][cells], np.float32)))
    return cells[np.argsort(-score, kind="stable")]


def read_cells(table: dict, order, budget: float) -> tuple[np.ndarray, float]:
    """Cells read when picking ``order`` (cell indices) under ``budget``, as the glimpse env reads:
    an unread valid cell is read if ``read + its views <= floor(budget · total)``; the first one that
    does not fit ends the reading. Returns ``(cells read, fraction of tissue views read)``."""
    limit = int(np.floor(budget * table["total"] + 1e-4))
    done, read = [], 0
    for c in order:
        c = int(c)
        if not table["valid"][c] or c in done:
            continue
        n = int(table["cell_views"][c])
        if read + n > limit:
            break
        done.append(c)
        read += n
        if read >= limit:
            break
    return np.asarray(done, np.int64), read / table["total"]


def read_mask(cells: dict, tissue: np.ndarray, order, budget: float) -> tuple[np.ndarray, float]:
    """``(mask (H, W) bool, fraction read)`` of the tissue views under the cells read picking ``order``
    at ``budget`` (the glimpse env's rule: :func:`read_cells`)."""
    read, fraction = read_cells(cells, order, budget)
    return np.isin(cells["cell"], read) & tissue, fraction
