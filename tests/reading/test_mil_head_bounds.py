"""A MIL head's parameters (the published ``pooled-statistics`` head here; ``attention-mil`` heads alike) are
bounded on load as the learned and logit heads' are: finite but absurd values are refused in one line naming
``params.npz`` and the array."""

from __future__ import annotations

import io
import shutil

import numpy as np
import pytest

from baselines.published_agents import PUBLISHED
from histojax.reading.heads import files, mil


@pytest.mark.parametrize("name, value", [("w", 1e30), ("prior_logit", 3e38), ("sd", 1e-40), ("mu", -1e9)])
def test_absurd_but_finite_values_of_the_published_mil_head_are_refused(tmp_path, name, value):
    folder = tmp_path / "head"
    shutil.copytree(PUBLISHED / "c16-v2-head-mil", folder)
    with np.load(folder / files.PARAMS) as z:
        arrays = {k: z[k] for k in z.files}
    mil.load(folder)  # as published: loads
    arrays[name] = np.full(arrays[name].shape, value, np.float32)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    (folder / files.PARAMS).write_bytes(buf.getvalue())
    with pytest.raises(files.HeadFileError, match=rf"params\.npz: array {name} holds values"):
        mil.load(folder)


def test_the_mil_fit_scorer_refuses_non_finite_slide_logits():
    from baselines.reading.head_mil_fit import dense_scores

    head = mil.load(PUBLISHED / "c16-v2-head-mil")
    d = int(head.dim) + 1
    slides = [{"features": np.full((4, 4, d), np.inf, np.float32), "tissue": np.ones((4, 4), bool), "label": 1}]
    where = PUBLISHED / "c16-v2-head-mil" / "params.npz"
    with pytest.raises(files.HeadFileError, match=rf"{where}: scores 1 of 1 slide logits non-finite"):
        dense_scores(head, slides, np.ones((1, 4, 4), bool), (4, 4))
