"""The learned attention-MIL head (histojax.reading.heads.learned), its guarded folder reader / writer
(histojax.reading.heads.files) and its fit (baselines.reading.learned_head_fit) on a TRIDENT-layout cohort whose
tumour direction is planted in a random orientation (no entry is the logit: tests/learned_fixture.py)."""

from __future__ import annotations

import io
import json
import os
import re
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from learned_fixture import make_cohort

import baselines.reading.learned_head_fit as fit
from baselines.validation import split_train
from data_tools.metrics import roc_auc
from histojax.reading.heads import files
from histojax.reading.heads.learned import KIND, LearnedHead, init_params, param_shapes


def small_head(dim=8, hidden=6, attention=4, layers=1, seed=0) -> LearnedHead:
    p = init_params(jax.random.PRNGKey(seed), dim, hidden, attention, layers)
    p["bc"] = jnp.float32(0.3)
    return LearnedHead(
        params=p,
        cal_a=jnp.float32(1.7),
        cal_b=jnp.float32(-0.4),
        prior_logit=jnp.float32(-0.9),
        features_dim=dim,
        hidden=hidden,
        attention=attention,
        layers=layers,
    )


# ----------------------------------------------------------------------------- the head's arithmetic
HEAD2 = small_head(layers=2, seed=3)
N, K = 48, 8
_add = jax.jit(lambda st_, x, m: HEAD2.add_views(st_, x, m))
_logit = jax.jit(HEAD2.logit)
_score = jax.jit(HEAD2.score_views)


@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**31 - 1), p=st.floats(0.0, 1.0), scale=st.floats(0.1, 30.0))
def test_incremental_state_equals_full_score(seed, p, scale):
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(N, HEAD2.features_dim)) * scale).astype(np.float32)
    mask = rng.random(N) < p
    order = rng.permutation(N)  # views read in any order, K at a time
    state = HEAD2.init_state()
    for i in range(0, N, K):
        idx = order[i : i + K]
        state = _add(state, x[idx], mask[idx])
    full = float(_score(x, mask))
    assert np.isclose(float(_logit(state)), full, rtol=1e-4, atol=1e-4)
    if not mask.any():
        assert full == pytest.approx(-0.9)  # nothing read: the prior


def test_the_state_rescales_when_the_maximum_moves():
    h = small_head()
    x = np.random.default_rng(1).normal(size=(6, h.features_dim)).astype(np.float32)
    hs = h.embed(x)
    a = jnp.asarray([-50.0, 0.0, 40.0, 3.0, 80.0, -5.0])  # a max that moves up twice, by far
    st_ = h.init_state()
    for i in range(6):
        st_ = h.add(st_, hs[i : i + 1], a[i : i + 1], jnp.ones(1, bool))
    w = jax.nn.softmax(a)
    want = h.calibrate(h.raw_logit((w[:, None] * hs).sum(0)))
    assert np.isfinite(float(st_.s)) and float(st_.m) == 80.0
    assert float(h.logit(st_)) == pytest.approx(float(want), abs=1e-5)


def test_vmap_over_padded_slides_equals_a_loop():
    h = small_head(seed=5)
    rng = np.random.default_rng(2)
    shapes = [(5, 7), (9, 4), (3, 3)]
    grids = [rng.normal(size=s + (h.features_dim,)).astype(np.float32) for s in shapes]
    masks = [rng.random(s) < 0.6 for s in shapes]
    H, W = 9, 7
    g = np.full((3, H, W, h.features_dim), 1e3, np.float32)  # padding holds junk: it is never read
    m = np.zeros((3, H, W), bool)
    for i, (gi, mi) in enumerate(zip(grids, masks)):
        g[i, : gi.shape[0], : gi.shape[1]] = gi
        m[i, : mi.shape[0], : mi.shape[1]] = mi
    batched = np.asarray(jax.jit(jax.vmap(lambda a, b: h.score(a, b)))(g, m))
    loop = np.asarray([float(h.score(gi, mi)) for gi, mi in zip(grids, masks)])
    np.testing.assert_allclose(batched, loop, rtol=1e-5, atol=1e-5)
    vs = h.view_logits(grids[0])
    assert vs.shape == shapes[0] and vs.dtype == jnp.float32
    hh = h.embed(grids[0])
    np.testing.assert_allclose(vs, 1.7 * (hh @ h.params["wc"] + 0.3) - 0.4, rtol=1e-5, atol=1e-5)


def test_no_entry_is_read_on_its_own():
    """Rotating the features and the first layer together leaves every score unchanged (no entry is special)."""
    h = small_head(dim=8)
    rng = np.random.default_rng(4)
    q, _ = np.linalg.qr(rng.normal(size=(8, 8)))
    g = rng.normal(size=(4, 5, 8)).astype(np.float32)
    m = rng.random((4, 5)) < 0.5
    rot = h.replace(params={**h.params, "w1": jnp.asarray(q.T @ np.asarray(h.params["w1"]), jnp.float32)})
    assert float(rot.score(g @ q, m)) == pytest.approx(float(h.score(g, m)), abs=1e-4)
    with pytest.raises(ValueError, match="feature grid"):
        h.score_logits(g[..., 0], m)


# ----------------------------------------------------------------------------- files
def test_save_load_round_trip(tmp_path):
    h = small_head(layers=2).replace(encoder="imported:x.h5", info=json.dumps({"note": 1}))
    h.save(tmp_path / "h", extras={"learning_curve.png": b"\x89PNG"})
    assert sorted(os.listdir(tmp_path / "h")) == ["config.json", "learning_curve.png", "params.npz"]
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]  # no temporary left
    back = LearnedHead.load(tmp_path / "h")
    g = np.random.default_rng(0).normal(size=(4, 6, 8)).astype(np.float32)
    m = np.random.default_rng(1).random((4, 6)) < 0.5
    assert float(back.score(g, m)) == pytest.approx(float(h.score(g, m)), abs=1e-6)
    np.testing.assert_allclose(back.view_logits(g), h.view_logits(g), atol=1e-6)
    assert back.encoder == "imported:x.h5" and back.layers == 2 and json.loads(back.info) == {"note": 1}
    h.save(tmp_path / "h")  # its own folder: replaced
    assert sorted(os.listdir(tmp_path / "h")) == ["config.json", "params.npz"]


def test_save_refuses_user_files_and_other_kinds(tmp_path):
    h = small_head()
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a slide head's"):
        h.save(user)
    assert (user / "notes.txt").read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"kind": "neighbourhood-pooled-logit"}))
    (other / "params.json").write_text("{}")
    with pytest.raises(ValueError, match="kind 'neighbourhood-pooled-logit'"):
        h.save(other)
    mine = tmp_path / "mine"
    h.save(mine)
    (mine / "extra.csv").write_text("x")
    with pytest.raises(ValueError, match="did not write"):
        h.save(mine)
    assert (mine / "extra.csv").is_file() and not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def _saved(tmp_path) -> Path:
    return small_head().save(tmp_path / "h")


def test_reader_refuses_a_fifo_and_a_link(tmp_path):
    folder = _saved(tmp_path)
    (folder / "config.json").unlink()
    os.mkfifo(folder / "config.json")  # opening it blocking would hang: refused before opening
    with pytest.raises(ValueError, match=r"config.json: is not a regular file"):
        LearnedHead.load(folder)
    (folder / "config.json").unlink()
    real = tmp_path / "real.json"
    real.write_text(json.dumps(small_head().config()))
    (folder / "config.json").symlink_to(real)
    with pytest.raises(ValueError, match="symbolic link"):
        LearnedHead.load(folder)


def test_reader_refuses_deep_json_without_recursion_error(tmp_path):
    folder = _saved(tmp_path)
    (folder / "config.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(ValueError, match="nested 200000 deep") as e:
        LearnedHead.load(folder)
    assert len(str(e.value).splitlines()) == 1
    (folder / "config.json").write_bytes(b"x" * (files.MAX_CONFIG_BYTES + 1))
    with pytest.raises(ValueError, match="more than the"):
        LearnedHead.load(folder)


@pytest.mark.parametrize(
    "key,value,problem",
    [
        ("layers", "1", "not an int"),
        ("layers", True, "not an int"),
        ("hidden", 6.0, "not an int"),
        ("layers", 3, "outside"),
        ("format", 2, "format 2"),
    ],
)
def test_reader_refuses_wrong_types(tmp_path, key, value, problem):
    folder = _saved(tmp_path)
    cfg = json.loads((folder / "config.json").read_text())
    cfg[key] = value
    (folder / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=problem):
        LearnedHead.load(folder)


def test_strict_fields():
    where = Path("config.json")
    assert files.field({"b": False}, "b", bool, where) is False
    with pytest.raises(ValueError, match="'b' is \"false\", not a bool"):
        files.field({"b": "false"}, "b", bool, where)
    with pytest.raises(ValueError, match="not a bool"):
        files.field({"b": 0}, "b", bool, where)
    with pytest.raises(ValueError, match="not a finite number"):
        files.field({"f": True}, "f", float, where)
    with pytest.raises(ValueError, match="not valid JSON"):
        files.read_config(_write(Path(os.environ.get("TMPDIR", "/tmp")) / f"nan-{os.getpid()}.json", b'{"a": NaN}'))


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _npz(arrays: dict, raw: dict | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for k, v in arrays.items():
            b = io.BytesIO()
            np.lib.format.write_array(b, np.asarray(v))
            z.writestr(f"{k}.npy", b.getvalue())
        for k, v in (raw or {}).items():
            z.writestr(f"{k}.npy", v)
    return buf.getvalue()


def test_reader_refuses_bad_params(tmp_path):
    folder = _saved(tmp_path)
    par = folder / "params.npz"
    good = par.read_bytes()
    arrays = dict(np.load(par))
    cases = [
        (b"", "empty file"),
        (good[: len(good) // 2], "not a complete .npz"),
        (_npz({**arrays, "junk": np.zeros(3)}), "does not use \\(junk\\)"),
        (_npz({k: v for k, v in arrays.items() if k != "wc"}), "lacks the arrays wc"),
        (_npz({**arrays, "wc": arrays["wc"].astype(np.complex64)}), "dtype complex64"),
        (_npz({**arrays, "wc": np.zeros(7, np.float32)}), "shape \\(7,\\), the config implies \\(6,\\)"),
        (_npz({**arrays, "wc": np.full(6, np.nan, np.float32)}), "non-finite"),
    ]
    # a member whose header claims 10^12 floats: refused from its header, nothing that size allocated
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (10**12,)})
    cases.append((_npz(arrays, {"huge": header.getvalue() + b"\0" * 64}), "does not use \\(huge\\)"))
    cases.append(
        (
            _npz({k: v for k, v in arrays.items() if k != "w1"}, {"w1": header.getvalue() + b"\0" * 64}),
            "array w1 has shape \\(1000000000000,\\)",
        )
    )
    obj = io.BytesIO()
    np.lib.format.write_array_header_1_0(obj, {"descr": "|O", "fortran_order": False, "shape": (6,)})
    cases.append(
        (_npz({k: v for k, v in arrays.items() if k != "wc"}, {"wc": obj.getvalue() + b"\0" * 48}), "dtype object")
    )
    for data, problem in cases:
        par.write_bytes(data)
        with pytest.raises(ValueError, match=problem) as e:
            LearnedHead.load(folder)
        assert str(e.value).startswith(str(par)) and len(str(e.value).splitlines()) == 1
    par.write_bytes(good)
    LearnedHead.load(folder)


# ----------------------------------------------------------------------------- the fit on a planted cohort
@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    return make_cohort(tmp_path_factory.mktemp("learned") / "ds", signal=4.0)


@pytest.fixture(scope="module")
def fitted(cohort):
    root = cohort["root"]
    spec = fit.read_spec(root)
    kept, held = split_train(spec, 0.2, 0)
    tr = fit.load_split(root, kept, spec, progress=False)
    va = fit.load_split(root, held, spec, progress=False)
    te = fit.load_split(root, spec["test"], spec, progress=False)
    head, curve = fit.train(
        tr,
        fit.FlatSet(va),
        fit.CANDIDATES[1],
        seed=0,
        steps=150,
        batch_size=8,
        views=128,
        eval_every=25,
        lr=5e-3,
        progress=False,
    )
    head, slope = fit.calibrate(head, fit.FlatSet(va))
    return head, slope, te, curve


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_the_fit_finds_the_planted_direction(cohort, fitted):
    head, slope, test, curve = fitted
    assert slope > 0 and len(curve) == 6
    flat = fit.FlatSet(test)
    assert flat.aucs(head, draws=1)["full"] >= 0.9  # held-out slides, reading everything
    # per-view scores find the planted tumour views of the held-out tumour slides
    scores, truth = [], []
    for s in test:
        if s["label"]:
            v = np.asarray(head.view_logits(np.asarray(s["features"], np.float32)))
            scores.append(v)
            truth.append(cohort["tumour"][s["name"]][s["yx"][:, 0], s["yx"][:, 1]])
    within = [roc_auc(v, t) for v, t in zip(scores, truth)]  # where on a slide: what maps and readers use
    assert np.mean(within) >= 0.85 and min(within) >= 0.7, within
    assert roc_auc(np.concatenate(scores), np.concatenate(truth)) >= 0.8  # across slides too (random: 0.5)
    # the direction of the first layer's most used input is spread over the entries, as planted
    assert np.abs(cohort["direction"]).max() < 0.6


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_loader_reads_views_through_the_checked_bundle_loader(cohort):
    root = cohort["root"]
    name = cohort["names"]["train"][0]
    s = fit.load_views(root / "bundles" / name, spec=fit.read_spec(root))
    assert s["features"].shape == (14 * 18, 48) and s["label"] == 1 and s["encoder"] == "imported:ds/features/*.h5"
    arr = root / "bundles" / name / "features_00.npy"
    data = bytearray(arr.read_bytes())
    data[-1] ^= 0xFF
    backup = arr.read_bytes()
    arr.write_bytes(bytes(data))
    try:
        with pytest.raises(Exception, match="checksum mismatch"):
            fit.load_views(root / "bundles" / name)
    finally:
        arr.write_bytes(backup)


def _main(argv) -> int:
    return fit._main()(argv)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_too_few_slides_per_class_is_refused(cohort, tmp_path, capsys):
    spec = json.loads((cohort["root"] / "dataset.json").read_text())
    tum = [e for e in spec["train"] if "tumour" in e][:4]
    nor = [e for e in spec["train"] if "normal" in e]
    small = {**spec, "train": [str(cohort["root"] / e) for e in tum + nor]}
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(small))
    out = tmp_path / "head"
    assert _main(["--dataset", str(tmp_path / "ds"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    # 4 tumour slides cannot give both a validation share of 3 and a training side of 5: whichever minimum the
    # split breaks first is named, before anything is trained
    assert len(err.splitlines()) == 1 and not out.exists()
    assert (f"at least {fit.MIN_SLIDES_PER_CLASS} of each class" in err) or (
        "validation share" in err and "Nothing was trained" in err
    )


def test_guards_refuse_inverted_heads():
    where = Path("ds/dataset.json")
    fit.check_head(where, 0.5, 0.0)
    with pytest.raises(fit.FitError, match="validation AUC is 0.333 .< 0.5"):
        fit.check_head(where, 1 / 3, 1.0)
    with pytest.raises(fit.FitError, match="validation AUC is nan"):
        fit.check_head(where, float("nan"), 1.0)
    with pytest.raises(fit.FitError, match="slope on validation is -0.208"):
        fit.check_head(where, 0.9, -0.208)


@pytest.mark.slow
def test_an_inverted_head_is_refused(cohort, tmp_path, capsys, monkeypatch):
    """A fit whose best head ranks tumour below normal on validation (labels that disagree between training and
    validation, or a broken encoder) is refused and nothing is saved."""
    real = fit.train

    def inverted(*args, **kwargs):
        head, curve = real(*args, **{**kwargs, "steps": 60, "eval_every": 30})
        return head.replace(params={**head.params, "wc": -head.params["wc"], "bc": -head.params["bc"]}), curve

    monkeypatch.setattr(fit, "train", inverted)
    out = tmp_path / "head"
    code = _main(
        [
            "--dataset",
            str(cohort["root"]),
            "--out",
            str(out),
            "--quiet",
            "--hidden",
            "32",
            "--batch",
            "8",
            "--views",
            "64",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "validation AUC is 0." in err and "< 0.5" in err and "nothing saved" in err
    assert not out.exists()


def test_platt_slope_is_negative_for_inverted_scores():
    rng = np.random.default_rng(0)
    y = rng.random(200) < 0.4
    s = np.where(y, 1.0, -1.0) + rng.normal(0, 1, 200)
    assert fit.platt(s, y)[0] > 0 and fit.platt(-s, y)[0] < 0


@pytest.mark.slow
def test_the_command_fits_saves_and_scores(cohort, tmp_path, capsys):
    out = tmp_path / "head"
    assert (
        _main(
            [
                "--dataset",
                str(cohort["root"]),
                "--out",
                str(out),
                "--quiet",
                "--steps",
                "150",
                "--batch",
                "8",
                "--views",
                "128",
                "--eval-every",
                "25",
                "--lr",
                "5e-3",
            ]
        )
        == 0
    )
    assert sorted(os.listdir(out)) == ["config.json", "learning_curve.png", "params.npz"]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["kind"] == KIND and cfg["chosen_on"]["validation_auc"] >= 0.5 and cfg["calibration"]["slope"] > 0
    capsys.readouterr()
    assert _main(["--dataset", str(cohort["root"]), "--score", str(out), "--split", "test", "--quiet"]) == 0
    printed = capsys.readouterr()
    res = json.loads(printed.out.strip().splitlines()[-1])
    assert res["auc"] >= 0.9 and res["slides"] == 8
    # the AUC's 95 % interval over the 8 slides beside it, and the word that 4 + 4 slides cannot rank heads
    assert res["auc_low"] < res["auc"] <= res["auc_high"] <= 1.0 and res["auc_high"] - res["auc_low"] > 0.2
    shown = re.search(r"AUC (\d\.\d{3}) \[(\d\.\d{3}), (\d\.\d{3})\] reading everything", printed.err)
    assert shown and np.allclose(
        [float(v) for v in shown.groups()], [res["auc"], res["auc_low"], res["auc_high"]], atol=6e-4
    ), printed.err
    assert "holds 4 tumour and 4 normal slides" in printed.err
    # a second fit into the same folder replaces it; into a folder of user files is refused
    (tmp_path / "user").mkdir()
    (tmp_path / "user" / "a.txt").write_text("x")
    assert (
        _main(
            [
                "--dataset",
                str(cohort["root"]),
                "--out",
                str(tmp_path / "user"),
                "--quiet",
                "--steps",
                "20",
                "--hidden",
                "32",
                "--eval-every",
                "10",
            ]
        )
        == 2
    )
    assert os.listdir(tmp_path / "user") == ["a.txt"]


def test_score_refuses_a_head_of_another_import_folder(cohort, tmp_path, capsys):
    """Was: ``--score`` compared no encoder, and a head recorded one slide's file (``imported:NAME.h5``), so a head
    fitted on another encoder's 48-d import scored these slides without a word."""
    head = small_head(dim=48).replace(encoder="imported:20x_256px_0px_overlap/features_uni_v1/*.h5")
    head.save(tmp_path / "h")
    assert _main(["--dataset", str(cohort["root"]), "--score", str(tmp_path / "h"), "--split", "test", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "a slide head for imported:20x_256px_0px_overlap/features_uni_v1/*.h5 features" in err
    assert "these slides hold imported:ds/features/*.h5 features" in err and len(err.splitlines()) == 1
    from baselines.reading import diagnosis
    from data_tools.errors import HistojaxDataError

    with pytest.raises(HistojaxDataError, match=r"h/config.json: a slide head for .*features_uni_v1.*ds/features"):
        diagnosis.score_split(cohort["root"], tmp_path / "h", "test", budgets=(0.1,), seeds=1)  # diagnosis, navigators


def test_param_shapes_cover_every_saved_array():
    h = small_head(layers=2)
    assert set(h.arrays()) == set(param_shapes(8, 6, 4, 2))
    assert all(h.arrays()[k].shape == s for k, s in param_shapes(8, 6, 4, 2).items())


def test_the_heads_package_loads_and_scores_a_learned_head(tmp_path):
    from histojax.reading import heads

    h = small_head(layers=2)
    h.save(tmp_path / "h")
    back = heads.load(tmp_path / "h")
    assert isinstance(back, LearnedHead) and heads.HEADS[KIND] is LearnedHead
    assert isinstance(back, heads.SlideHeadProtocol) and back.kind == KIND
    g = np.random.default_rng(0).normal(size=(3, 5, 8)).astype(np.float32)
    m = np.random.default_rng(1).random((3, 5)) < 0.5
    assert float(heads.score(back, g, m)) == pytest.approx(float(h.score(g, m)), abs=1e-6)
    assert float(jax.jit(heads.score)(back, g, m)) == pytest.approx(float(h.score(g, m)), abs=1e-5)


def test_cached_view_terms_score_as_the_features():
    h = small_head(layers=2, seed=8)
    rng = np.random.default_rng(3)
    g = (rng.normal(size=(6, 7, 8)) * 4).astype(np.float32)
    m = rng.random((6, 7)) < 0.4
    terms = h.view_terms(g)
    assert terms.shape == (6, 7, 2)
    assert float(h.score_terms(terms, m)) == pytest.approx(float(h.score(g, m)), abs=1e-4)
    st_ = h.init_terms_state()
    flat_t, flat_m = terms.reshape(-1, 2), m.reshape(-1)
    for i in range(0, 42, 5):
        st_ = h.add_terms(st_, flat_t[i : i + 5], flat_m[i : i + 5])
    assert float(h.logit_terms(st_)) == pytest.approx(float(h.score(g, m)), abs=1e-4)
    assert float(h.score_terms(terms, np.zeros((6, 7), bool))) == pytest.approx(-0.9)


def _with_folds(cohort, tmp_path, k=3) -> Path:
    spec = json.loads((cohort["root"] / "dataset.json").read_text())
    train = [str(cohort["root"] / e) for e in spec["train"]]
    tum = [e for e in train if "tumour" in e]
    nor = [e for e in train if "normal" in e]
    lists = [sorted(tum[i::k] + nor[i::k]) for i in range(k)]
    ds = tmp_path / "folded"
    ds.mkdir()
    (ds / "dataset.json").write_text(
        json.dumps({**spec, "train": train, "test": [], "folds": {"k": k, "pool": "train", "seed": 0, "lists": lists}})
    )
    return ds


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_fold_refusals_are_one_line(cohort, tmp_path, capsys):
    ds = _with_folds(cohort, tmp_path)
    assert _main(["--dataset", str(ds), "--out", str(tmp_path / "h"), "--fold", "3", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fold=3 is out of range" in err and not (tmp_path / "h").exists()
    assert _main(["--dataset", str(cohort["root"]), "--out", str(tmp_path / "h"), "--fold", "0", "--quiet"]) == 2
    assert "has no folds" in capsys.readouterr().err


class _Stop(Exception):
    pass


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_a_fold_trains_and_validates_on_the_other_folds(cohort, tmp_path, monkeypatch):
    ds = _with_folds(cohort, tmp_path)
    folds = json.loads((ds / "dataset.json").read_text())["folds"]["lists"]
    seen = {}

    def spy(train_slides, val, *args, **kwargs):
        seen["train"] = [s["name"] for s in train_slides]
        seen["val"] = [s["name"] for s in val.slides]
        raise _Stop

    monkeypatch.setattr(fit, "train", spy)
    with pytest.raises(_Stop):
        _main(["--dataset", str(ds), "--out", str(tmp_path / "h"), "--fold", "1", "--val-fraction", "0.3", "--quiet"])
    other = {Path(e).name for i, lst in enumerate(folds) if i != 1 for e in lst}
    assert set(seen["train"]) | set(seen["val"]) == other and not set(seen["train"]) & set(seen["val"])
    assert {Path(e).name for e in folds[1]}.isdisjoint(seen["train"] + seen["val"])  # fold 1 is never read


def test_the_published_learned_head_loads_and_scores_any_c16_grid():
    """``baselines/published/c16-v2-learned-head`` (fitted on c16-full's pcam-cnn features): loads through the one
    head loader, scores a grid of any size batched as one by one, and its per-view scores are the calibrated
    instance logits of the views; nothing read scores its prior."""
    from baselines.published_agents import PUBLISHED
    from histojax.reading import heads

    head = heads.load(PUBLISHED / "c16-v2-learned-head")
    assert isinstance(head, LearnedHead) and head.features_dim == 64 and head.encoder == "pcam-cnn"
    config = json.loads((PUBLISHED / "c16-v2-learned-head" / "config.json").read_text())
    assert config["fitted_on"]["dataset"] == "c16-full" and "test" not in config["fitted_on"]["split"]
    rng = np.random.default_rng(0)
    for hw in ((7, 5), (31, 64)):  # slides of any shape
        grid = jnp.asarray(rng.normal(size=(*hw, 64)), jnp.float32)
        mask = jnp.asarray(rng.random(hw) < 0.3)
        logit = float(heads.score(head, grid, mask))
        assert np.isfinite(logit)
        assert float(heads.score(head, grid, jnp.zeros(hw, bool))) == pytest.approx(float(head.prior_logit))
        views = head.view_logits(grid)
        assert views.shape == hw and bool(jnp.all(jnp.isfinite(views)))
        st_ = head.add_views(head.init_state(), grid.reshape(-1, 64), mask.reshape(-1))
        assert float(head.logit(st_)) == pytest.approx(logit, abs=1e-4)
