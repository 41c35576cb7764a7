"""The slide head with spatial context (histojax.reading.heads.logit), its fitting (baselines.reading.head_fit), CAMELYON lesion
classes and the scripted readers with the one-head budget curve (baselines.reading.readers).

A tiny synthetic pcam-cnn-style dataset is written once for the module (no pixels: metadata.json, feature
grids whose entry 62 is a view logit, a tissue mask, tumour polygons). Normal slides carry isolated
false-positive views hotter than any tumour view; tumour slides a block of moderately hot views: the plain
maximum cannot separate them, a neighbourhood mean can."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines.reading import head_fit, reader_scores, readers, slides
from baselines.reading.orders import logit_order, random_order, read_mask, search_order
from baselines.reading.slides import CLASSES, lesion_class
from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.seals import write_metadata
from histojax.reading.heads import score
from histojax.reading.heads.logit import LogitHead, neighbourhood_mean

GH, GW, TILE, MPP, D = 24, 16, 16, 10.0, 64  # views; px per view; µm/px (a view is 160 µm)
# (name, lesion (y, x, h, w) in views or None, polygon side in px when smaller than the block)
TUMOUR = {"micro": (4, 3, 4, 4), "macro": (10, 4, 12, 8), "itc": (18, 10, 2, 2)}


def _write_slide(root, name: str, rng, lesion=None, poly_px=None) -> dict:
    b = root / "bundles" / name
    b.mkdir(parents=True)
    logit = rng.normal(-3.0, 0.7, (GH, GW))
    fp = rng.choice(GH * GW, 4, replace=False)  # isolated false positives, hotter than any tumour view
    logit.reshape(-1)[fp] = 4.0 + rng.random(4)
    tumour = None
    if lesion is not None:
        y, x, h, w = lesion
        logit[y : y + h, x : x + w] = 2.0 + 0.3 * rng.random((h, w))
        side_x, side_y = (poly_px, poly_px) if poly_px else (w * TILE, h * TILE)
        tumour = [
            [x * TILE, y * TILE],
            [x * TILE + side_x, y * TILE],
            [x * TILE + side_x, y * TILE + side_y],
            [x * TILE, y * TILE + side_y],
            [x * TILE, y * TILE],
        ]
    levels = []
    for lv in range(3):
        f = 2**lv
        g = logit.reshape(GH // f, f, GW // f, f).mean((1, 3))
        feats = np.zeros(g.shape + (D,), np.float16)
        feats[..., 62] = g
        np.save(b / f"features_{lv:02d}.npy", feats)
        levels.append({"file": f"features_{lv:02d}.npy", "grid": list(g.shape)})
    tissue = np.ones((GH * 4, GW * 4), bool)  # 4 mask px per view
    tissue[:, :4] = False  # the first view column holds no tissue
    np.save(b / "tissue.npy", tissue)
    meta = {
        "tile_size": TILE,
        "source": {"mpp": MPP},
        "levels": [
            {"width": GW * TILE // 2**lv, "height": GH * TILE // 2**lv, "downsample": 2.0**lv} for lv in range(3)
        ],
        "tissue": {"file": "tissue.npy"},
        "features": {"encoder": "pcam-cnn", "dim": D, "stride": TILE, "levels": levels},
    }
    feats = (
        []
        if tumour is None
        else [
            {
                "type": "Feature",
                "properties": {"label": "tumour"},
                "geometry": {"type": "Polygon", "coordinates": [tumour]},
            }
        ]
    )
    (b / "annotations.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    # a feature-only stand-in of a dense bundle: the head tools read features, tissue and annotations only (the
    # pixel arrays it names are never opened), through the checked loader: checksums and the metadata seal
    for k, lv in enumerate(meta["levels"]):
        lv.update(pixels=f"pixels_{k:02d}.npy", tumour=f"tumour_{k:02d}.npy")
    meta.update(
        format_version=1,
        magnification_range=4.0,
        annotations={"tumour_area_px": 1.0 if tumour else 0.0},
        checksums={n: sha256(b / n) for n in ("tissue.npy", "annotations.geojson", *(lv["file"] for lv in levels))},
    )
    write_metadata(b, meta)
    return {"bundle": f"bundles/{name}", "label": int(lesion is not None)}


def make_dataset(root, n_train: int = 20, n_test: int = 10, seed: int = 0):
    rng = np.random.default_rng(seed)
    spec = {"train": [], "test": [], "labels": {}, "slides": [], "encoder": "pcam-cnn"}
    kinds = ["micro", "macro", "itc"]
    for split, n in (("train", n_train), ("test", n_test)):
        for i in range(n):
            tumour = i % 2 == 0
            kind = kinds[(i // 2) % 3] if tumour else None
            name = f"{split}_{'tumour' if tumour else 'normal'}_{i:02d}_{kind or ''}".rstrip("_")
            rec = _write_slide(root, name, rng, TUMOUR[kind] if tumour else None, 6 if kind == "itc" else None)
            spec[split].append(rec["bundle"])
            spec["labels"][name] = rec["label"]
            spec["slides"].append({**rec, "name": name, "split": split})
    (root / "dataset.json").write_text(json.dumps(spec))
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("head-ds"))


@pytest.fixture(scope="module")
def fitted(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("head")
    head, table = head_fit.fit(dataset, out, ks=(1, 3), minus_median=True, val_fraction=0.3)  # 3 + 3 validate
    return out, head, table


# ----------------------------------------------------------------------------- the head
def test_neighbourhood_mean_is_the_mean_over_read_neighbours():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(7, 9)).astype(np.float32)
    m = rng.random((7, 9)) < 0.6
    for k in (1, 2, 3, 4):
        got = np.asarray(neighbourhood_mean(jnp.asarray(x), jnp.asarray(m), k))
        lo, hi = (k - 1) // 2, k // 2
        for i in range(7):
            for j in range(9):
                sl = (slice(max(0, i - lo), i + hi + 1), slice(max(0, j - lo), j + hi + 1))
                n = m[sl].sum()
                want = (x[sl] * m[sl]).sum() / n if n else 0.0
                assert got[i, j] == pytest.approx(want, abs=1e-5), (k, i, j)


def test_score_is_jittable_padding_free_and_empty_gives_the_prior():
    rng = np.random.default_rng(2)
    g = rng.normal(size=(10, 6, 64)).astype(np.float32)
    m = rng.random((10, 6)) < 0.5
    head = LogitHead(
        cal_a=jnp.float32(1.5), cal_b=jnp.float32(-2.0), prior_logit=jnp.float32(-0.7), k=3, top=3, minus_median=True
    )
    plain = float(score(head, g, m))
    assert float(jax.jit(score)(head, g, m)) == pytest.approx(plain, abs=1e-5)
    gp = np.zeros((13, 11, 64), np.float32)
    gp[:10, :6] = g
    mp = np.zeros((13, 11), bool)
    mp[:10, :6] = m
    assert float(jax.jit(score)(head, gp, mp)) == pytest.approx(plain, abs=1e-5)  # padding is never read
    assert float(score(head, g, np.zeros((10, 6), bool))) == pytest.approx(-0.7)
    # by hand: top-3 mean of the 3x3 neighbourhood means, minus the median of the read logits, calibrated
    nb = np.asarray(neighbourhood_mean(jnp.asarray(g[..., 62]), jnp.asarray(m), 3))[m]
    s = np.sort(nb)[-3:].mean() - np.median(g[..., 62][m])
    assert plain == pytest.approx(1.5 * s - 2.0, abs=1e-4)


def test_head_saves_and_loads(tmp_path):
    head = LogitHead(
        cal_a=jnp.float32(0.8),
        cal_b=jnp.float32(0.1),
        prior_logit=jnp.float32(0.2),
        k=2,
        top=1,
        info=json.dumps({"chosen_on": {"validation_auc": 0.9}}),
    )
    head.save(tmp_path / "h")
    back = LogitHead.load(tmp_path / "h")
    assert (back.k, back.top, back.minus_median, back.dim) == (2, 1, False, 62)
    assert float(back.cal_a) == pytest.approx(0.8) and float(back.prior_logit) == pytest.approx(0.2)
    assert json.loads((tmp_path / "h" / "config.json").read_text())["chosen_on"] == {"validation_auc": 0.9}
    (tmp_path / "h" / "params.json").write_text('{"a": 1}')
    with pytest.raises(ValueError, match="params.json: lacks 'b'"):
        LogitHead.load(tmp_path / "h")
    with pytest.raises(ValueError, match="config.json: missing"):
        LogitHead.load(tmp_path / "nothing")


# ----------------------------------------------------------------------------- fitting
def test_fit_chooses_spatial_context_on_validation(fitted, dataset):
    out, head, table = fitted
    by = {(r["k"], r["top"], r["minus_median"]): r for r in table}
    # isolated false positives beat the tumour views: the plain maximum fails, the 3x3 mean does not
    assert by[(1, 1, False)]["validation_auc"] < 0.7 and by[(3, 1, False)]["validation_auc"] == 1.0
    assert head.k == 3
    assert not any(c.minus_median for c in head_fit.candidates())  # by default: reader-independent heads only
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["k"] == 3 and cfg["chosen_on"]["validation_slides"] >= 2 and len(cfg["candidates"]) == 8
    spec = json.loads((dataset / "dataset.json").read_text())
    assert cfg["fitted_on"]["slides"] == len(spec["train"])  # training slides only
    seen = cfg["slides_seen"]  # re-calibrated on the whole train split: every train slide fitted, 3 + 3 validated
    assert seen["fitted"] == sorted(Path(e).name for e in spec["train"]) and len(seen["validation"]) == 6
    assert set(seen["validation"]) <= set(seen["fitted"]) and seen["fold"] is None and seen["split"] == "train"
    test = slides.load_slides(dataset, "test")
    logits = reader_scores.head_scores(LogitHead.load(out), test, [s["tissue"] for s in test])
    labels = [s["label"] for s in test]
    from data_tools.metrics import roc_auc

    assert roc_auc(logits, labels) == 1.0


def test_fit_command_refuses_a_folder_without_dataset_json(tmp_path, capsys):
    assert head_fit.main(["--dataset", str(tmp_path), "--out", str(tmp_path / "h")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dataset.json: missing" in err[0]
    assert not (tmp_path / "h").exists()


# ----------------------------------------------------------------------------- lesions and readers
def test_lesion_classes_follow_camelyon_thresholds(dataset):
    test = slides.load_slides(dataset, "test")
    got = {s["name"]: lesion_class(s) for s in test}
    for name, (cls, mm) in got.items():
        if "normal" in name:
            assert cls == "normal"
        elif name.endswith("itc"):  # a 6-px square: 85 µm
            assert cls == "ITC" and mm == pytest.approx(6 * np.sqrt(2) * MPP / 1000)
        elif name.endswith("micro"):  # 4 x 4 views of 160 µm: 0.91 mm
            assert cls == "micro" and mm == pytest.approx(4 * TILE * np.sqrt(2) * MPP / 1000)
        else:  # 12 x 8 views: 2.31 mm
            assert cls == "macro" and mm > 2.0


def test_scripted_readers_respect_the_budget_and_follow_the_logits(dataset, fitted):
    _, head, _ = fitted
    test = slides.load_slides(dataset, "test", levels=(0, 1))
    for s in test:
        cells = reader_scores.cell_table(s, 1)
        assert cells["cell_views"].sum() == s["tissue"].sum() == cells["total"]
        search = search_order(s, cells)
        assert sorted(search) == sorted(np.flatnonzero(cells["valid"]))  # every valid cell once
        for b in (0.05, 0.2):
            for order in (logit_order(cells), search, random_order(cells, np.random.default_rng(0))):
                mask, fraction = read_mask(cells, s["tissue"], order, b)
                assert mask.sum() == pytest.approx(fraction * cells["total"]) and fraction <= b + 1e-9
                assert not (mask & ~s["tissue"]).any()
        if s["label"] and lesion_class(s)[0] != "ITC":  # the coarse logits point at the block
            mask, _ = read_mask(cells, s["tissue"], logit_order(cells), 0.05)
            assert (mask & reader_scores.tumour_views(s)).any()
        flat = np.flatnonzero(s["tissue"].reshape(-1))
        pick = np.asarray([0, 5, len(flat) - 1])
        m = reader_scores.masks_from_instances(s, pick)
        assert m.sum() == 3 and m.reshape(-1)[flat[pick]].all()


def test_readers_command_writes_the_curve(dataset, fitted, tmp_path, capsys):
    out, head, _ = fitted
    assert (
        readers.main(
            [
                "--dataset",
                str(dataset),
                "--head",
                str(out),
                "--budgets",
                "0.05",
                "0.2",
                "--seeds",
                "2",
                "--cell-level",
                "1",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    with open(tmp_path / "readers.csv") as f:
        rows = {(r["reader"], float(r["budget"])): r for r in csv.DictReader(f)}
    assert set(rows) == {("overview only", 0.0), ("read everything", 1.0)} | {
        (n, b) for n in ("random reader", "logit reader", "search reader") for b in (0.05, 0.2)
    }
    assert float(rows[("read everything", 1.0)]["auc"]) == 1.0
    assert float(rows[("overview only", 0.0)]["fraction_read"]) == 0.0
    assert int(rows[("random reader", 0.05)]["seeds"]) == 2
    for (name, b), r in rows.items():
        assert float(r["fraction_max"]) <= b + 1e-6 and 0.0 <= float(r["auc"]) <= 1.0
    every = rows[("read everything", 1.0)]
    assert (int(every["ITC_slides"]), int(every["micro_slides"]), int(every["macro_slides"])) == (1, 2, 2)
    assert float(every["micro_tumour_read"]) == 2.0 and float(every["macro_found"]) == 2.0
    assert float(rows[("logit reader", 0.05)]["macro_tumour_read"]) == 2.0
    with open(tmp_path / "lesions.csv") as f:
        assert len(list(csv.DictReader(f))) == 5
    assert (tmp_path / "readers.png").stat().st_size > 10_000
    # a learned reader's masks join the same table, scored by the same head
    test = slides.load_slides(dataset, "test")
    res = reader_scores.add_reader(
        reader_scores.new_results(),
        head,
        test,
        "my reader",
        {0.1: [[s["tissue"] for s in test], [np.zeros_like(s["tissue"]) for s in test]]},
    )
    row = reader_scores.rows_from_results(res, test)[0]
    assert row["seeds"] == 2 and row["fraction_read"] == pytest.approx(0.5) and row["kind"] == "learned"
    assert len(row["auc_per_seed"]) == 2 and np.mean(row["auc_per_seed"]) == pytest.approx(row["auc"], abs=1e-4)
    assert row["auc_per_seed"][1] == 0.5  # nothing read: every slide scores the prior
    assert "auc_per_seed" not in reader_scores.csv_rows([row])[0]  # one number per CSV cell; the list in readers.json
    with open(tmp_path / "readers.csv") as f:
        assert "auc_per_seed" not in next(csv.DictReader(f))
    saved = json.loads((tmp_path / "readers.json").read_text())["rows"]
    assert all(isinstance(r["read_nothing"], list) for r in saved)  # the slides a row read nothing on, and why
    assert len(row["read_nothing"]) == len(test)  # seed 1 read nothing: every slide named, in 1 of the 2 seeds
    assert {(e["reason"], e["seeds"]) for e in row["read_nothing"]} == {("it read no view", "1 of 2")}


def test_readers_command_refuses_a_bad_head(dataset, tmp_path, capsys):
    assert readers.main(["--dataset", str(dataset), "--head", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "config.json: missing" in err[0]
    LogitHead(encoder="uni").save(tmp_path / "uni")  # a head for another encoder's features
    assert readers.main(["--dataset", str(dataset), "--head", str(tmp_path / "uni"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a head for uni features" in err[0] and "pcam-cnn" in err[0]
    assert not (tmp_path / "o").exists()


def test_lesion_census_of_the_shipped_annotations(capsys):
    """The lesion classes of a C16 annotation source by split, from geometry alone (the shipped NCRF files)."""
    import importlib.util
    from pathlib import Path

    from data_tools.ncrf import SHIPPED_DIR, read_ncrf

    path = Path(__file__).resolve().parents[2] / "experiments" / "c16_slide_ceiling.py"
    spec = importlib.util.spec_from_file_location("c16_slide_ceiling", path)
    ceiling = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ceiling)
    rows = ceiling.lesion_census(SHIPPED_DIR)
    every = read_ncrf(SHIPPED_DIR)
    assert sorted(r["slide"] for r in rows) == sorted(n for n in every if every[n].is_tumour_slide)
    for r in rows:
        assert r["split"] in ("train", "test") and r["class"] in CLASSES
        assert (r["class"] == "ITC") == (r["diameter_mm"] < 0.2) and (r["class"] == "macro") == (r["diameter_mm"] > 2)
    assert ceiling.main(["--lesions", str(SHIPPED_DIR)]) == 0
    assert "| test |" in capsys.readouterr().out
