"""A learned head's parameters are bounded on load as the logit heads' are (a floor on ``sd``, a ceiling on every
weight and the calibration), and every host-side scorer refuses non-finite logits in one line naming the head's
``params.npz``."""

from __future__ import annotations

import io

import jax
import numpy as np
import pytest

from histojax.reading.heads import files
from histojax.reading.heads.learned import LearnedHead, init_params


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A small learned head (4-d features, 4 units, 2 attention units) saved to a folder; its arrays."""
    folder = tmp_path_factory.mktemp("learned") / "head"
    head = LearnedHead(
        params=init_params(jax.random.PRNGKey(0), 4, hidden=4, attention=2), features_dim=4, hidden=4, attention=2
    )
    head.save(folder)
    with np.load(folder / files.PARAMS) as z:
        return folder, {k: z[k] for k in z.files}


def _with(tmp_path, saved, **changes):
    folder, arrays = saved
    out = tmp_path / "head"
    out.mkdir(parents=True)
    (out / files.CONFIG).write_bytes((folder / files.CONFIG).read_bytes())
    buf = io.BytesIO()
    np.savez(buf, **{**arrays, **{k: np.full(arrays[k].shape, v, np.float32) for k, v in changes.items()}})
    (out / files.PARAMS).write_bytes(buf.getvalue())
    return out


@pytest.mark.parametrize(
    "name, value", [("cal_a", 3e38), ("sd", 1e-40), ("w1", 1e30), ("prior_logit", -1e9), ("sd", 0.0)]
)
def test_absurd_but_finite_values_are_refused_on_load(tmp_path, saved, name, value):
    folder = _with(tmp_path, saved, **{name: value})
    with pytest.raises(files.HeadFileError, match=rf"params\.npz: array {name} holds values"):
        LearnedHead.load(folder)


def test_a_fitted_heads_values_load(tmp_path, saved):
    head = LearnedHead.load(_with(tmp_path, saved))
    assert head.source == str(tmp_path / "head")


def test_non_finite_logits_are_refused_naming_params_npz(tmp_path, saved):
    head = LearnedHead.load(_with(tmp_path, saved))
    assert files.check_finite_logits(head, np.array([0.5, -2.0])).tolist() == [0.5, -2.0]
    with pytest.raises(
        files.HeadFileError,
        match=rf"{tmp_path / 'head' / 'params.npz'}: scores 1 of 2 slide logits "
        r"non-finite",
    ):
        files.check_finite_logits(head, np.array([0.5, np.inf]))
    in_memory = LearnedHead(params=head.params, features_dim=4, hidden=4, attention=2)
    with pytest.raises(files.HeadFileError, match="params.npz of the head"):
        files.check_finite_logits(in_memory, np.array([np.nan]))


def test_the_readers_and_the_learned_fit_scorers_refuse_them(tmp_path, saved):
    from baselines.reading.learned_head_fit import FlatSet
    from baselines.reading.reader_scores import terms_scores

    head = LearnedHead.load(_with(tmp_path, saved))
    terms = np.zeros((2, 2, 2), np.float32)
    terms[..., 1] = np.inf  # every view's instance logit infinite: the slide logit is too
    with pytest.raises(files.HeadFileError, match="params.npz: scores 1 of 1 slide logits non-finite"):
        terms_scores(head, [terms], [np.ones((2, 2), bool)])
    big = LearnedHead.load(_with(tmp_path / "big", saved, w1=1e6, wc=1e6))  # at the bound: loads
    flat = FlatSet(
        [
            {"features": np.full((3, 4), 1e30, np.float32), "label": 1},  # and overflows on these features
            {"features": np.zeros((3, 4), np.float32), "label": 0},
        ]
    )
    with pytest.raises(files.HeadFileError, match=rf"{tmp_path / 'big' / 'head' / 'params.npz'}: scores 1 of 2"):
        flat.logits(big)
