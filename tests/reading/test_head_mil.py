"""The trained slide heads (histojax.reading.heads.mil) and their training data (baselines.reading.head_mil_fit): jittable,
vmap equals a loop, unread views do not count, the sparse training path equals the deployed dense one,
save / load round trip through heads.load, bad folders refused with one line naming the file."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines.reading import head_mil_fit
from histojax.reading import heads
from histojax.reading.heads import score, score_batch, score_logits
from histojax.reading.heads.mil import MilHead, StatsHead, load, statistics_of

H, W, D = 13, 10, 8


def _grid(seed):
    rng = np.random.default_rng(seed)
    g = rng.normal(0, 1, (H, W, D)).astype(np.float32)
    g[..., 2] = rng.normal(-2, 1.5, (H, W))  # the view logit entry
    tissue = rng.random((H, W)) < 0.8
    return g, tissue


def _mil(inputs="logit", seed=0):
    n_in = 4 + (D if inputs == "features" else 0)
    p = head_mil_fit.init_mil(
        jax.random.PRNGKey(seed), n_in, hidden=8, att=4, mu=np.linspace(-1, 1, n_in), sd=np.linspace(0.5, 2, n_in)
    )
    return MilHead(params=p, prior_logit=jnp.float32(-0.3), dim=2, inputs=inputs, hidden=8, encoder=None)


def _stats():
    n = 4 * 2 + 3 + 1
    p = {
        "mu": jnp.linspace(-1, 1, n),
        "sd": jnp.linspace(0.5, 2, n),
        "w": jnp.linspace(-0.5, 1, n),
        "b": jnp.float32(0.2),
    }
    return StatsHead(params=p, prior_logit=jnp.float32(-0.3), dim=2, encoder=None)


HEADS = {"mil-logit": _mil("logit"), "mil-features": _mil("features"), "stats": _stats()}


@pytest.mark.parametrize("name", sorted(HEADS))
def test_jit_vmap_equals_loop_and_prior(name):
    head = HEADS[name]
    grids, masks = zip(*[_grid(s) for s in range(3)])
    masks = [m & (np.random.default_rng(9 + i).random((H, W)) < 0.5) for i, m in enumerate(masks)]
    masks[2] = np.zeros((H, W), bool)  # nothing read: the prior
    f = jax.jit(jax.vmap(lambda g, m: score(head, g, m)))
    batch = np.asarray(f(np.stack(grids), np.stack(masks)))
    loop = np.asarray([score(head, g, m) for g, m in zip(grids, masks)])
    np.testing.assert_allclose(batch, loop, rtol=1e-5, atol=1e-5)
    assert batch[2] == pytest.approx(-0.3)
    assert np.all(np.isfinite(batch)) and batch[0] != batch[1]


@pytest.mark.parametrize("name", sorted(HEADS))
def test_unread_views_do_not_count(name):
    head = HEADS[name]
    g, tissue = _grid(1)
    read = tissue & (np.arange(H)[:, None] < 7)
    other = g.copy()
    other[~read] = 50.0  # hot everywhere not read
    s1, s2 = float(score(head, g, read)), float(score(head, other, read))
    assert s1 == pytest.approx(s2, abs=1e-5)
    hot = g.copy()
    hot[read.nonzero()[0][0], read.nonzero()[1][0]] = 50.0  # a read view changes the score
    assert float(score(head, hot, read)) != pytest.approx(s1, abs=1e-3)


def test_logit_heads_score_the_logit_map_through_histojax_head():
    g, tissue = _grid(2)
    for name in ("mil-logit", "stats"):
        head = HEADS[name]
        a = float(score(head, g, tissue))
        b = float(score_logits(head, g[..., 2], tissue))
        c = float(score_batch(head, g[None, ..., 2], tissue[None])[0])
        assert a == pytest.approx(b, abs=1e-6) and a == pytest.approx(c, abs=1e-5)
    with pytest.raises(ValueError, match="reads all feature entries"):
        score_logits(HEADS["mil-features"], g[..., 2], tissue)


@pytest.mark.parametrize("inputs", ["logit", "features"])
def test_sparse_training_instances_equal_the_dense_ones(inputs):
    """The training path (neighbour table over tissue views) computes the deployed head's instances."""
    head = _mil(inputs)
    slides = []
    for s in range(2):
        g, t = _grid(10 + s)
        slides.append({"features": g[: H - s, : W - 2 * s], "tissue": t[: H - s, : W - 2 * s], "label": s})
    data = head_mil_fit.bags(slides, dim=2)
    data = {k: (jnp.asarray(v) if isinstance(v, np.ndarray) else v) for k, v in data.items()}
    mask = head_mil_fit.random_reads(jax.random.PRNGKey(0), data, p_full=0.0, lo=0.5, hi=0.6)
    sparse = np.asarray(head_mil_fit.sparse_instances(head, data, mask))
    seg = np.asarray(data["seg"])
    for b, s in enumerate(slides):
        m = np.zeros(s["tissue"].shape, bool)
        m[s["tissue"]] = np.asarray(mask)[seg == b]
        dense = np.asarray(
            head.instances(jnp.asarray(s["features"][..., 2]), jnp.asarray(s["features"]), jnp.asarray(m))
        )
        np.testing.assert_allclose(sparse[seg == b][m[s["tissue"]]], dense[m], rtol=1e-5, atol=1e-5)


def test_statistics_read_nothing_and_top3_of_few():
    lg = jnp.asarray(np.arange(H * W, dtype=np.float32).reshape(H, W))
    assert np.all(np.asarray(statistics_of(lg, jnp.zeros((H, W), bool))) == 0)
    one = jnp.zeros((H, W), bool).at[3, 4].set(True)
    s = np.asarray(statistics_of(lg, one))
    assert s[0] == s[1] == float(lg[3, 4])  # top-1 and top-3 of a single read view: that view
    assert s[-1] == pytest.approx(np.log(2.0))


@pytest.mark.parametrize("name", sorted(HEADS))
def test_save_load_round_trip(tmp_path, name):
    head = HEADS[name].replace(info=json.dumps({"chosen_on": {"validation_auc": 0.9}}))
    head.save(tmp_path / name)
    back = heads.load(tmp_path / name)
    assert type(back) is type(head) and back.name == head.name and back.dim == 2
    assert json.loads((tmp_path / name / "config.json").read_text())["chosen_on"]["validation_auc"] == 0.9
    g, t = _grid(3)
    assert float(score(back, g, t)) == float(score(head, g, t))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c.update(kind="attention-mil-v9"), "not a slide head"),
        (lambda c: c.update(format=2), "format 2"),
        (lambda c: c.update(hidden=9), r"params.npz: array w1 has shape \(4, 8\), the config implies \(4, 9\)"),
        (lambda c: c.pop("ks"), "lacks 'ks'"),
    ],
)
def test_bad_config_refused_with_one_line(tmp_path, edit, message):
    folder = _mil().save(tmp_path / "h")
    cfg = json.loads((folder / "config.json").read_text())
    edit(cfg)
    (folder / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=message) as e:
        heads.load(folder)
    assert "\n" not in str(e.value) and ("config.json" in str(e.value) or "params.npz" in str(e.value))


def test_missing_or_non_finite_params_refused(tmp_path):
    folder = _stats().save(tmp_path / "s")
    z = dict(np.load(folder / "params.npz"))
    z["w"][0] = np.nan
    np.savez(folder / "params.npz", **z)
    with pytest.raises(ValueError, match="params.npz: array w holds non-finite values"):
        load(folder)
    (folder / "params.npz").unlink()
    with pytest.raises(ValueError, match="params.npz: missing"):
        load(folder)
