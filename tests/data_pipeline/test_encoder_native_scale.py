"""``pcam-cnn96``: the pcam-cnn family at PCam's native 0.97 µm/px (96-px patches), and the training machinery's
options it was trained with (brightness jitter, checkpoint and resume, the linear probe of the model card)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from data_tools.features import ENCODERS, pcam_cnn, pcam_cnn96
from data_tools.features.efficientnet import load_encoder
from data_tools.features.encoders import ENCODER_MPP, encoder_scale


def test_pcam_cnn96_is_registered_at_pcams_own_scale():
    assert ENCODERS["pcam-cnn96"][0] == pcam_cnn96.DIM == 64
    assert ENCODER_MPP["pcam-cnn96"] == pcam_cnn96.SCALE_MPP == 0.972
    assert encoder_scale("pcam-cnn96", 0.972)["ok"] and not encoder_scale("pcam-cnn96", 1.944)["ok"]
    assert pcam_cnn.ARCHS["pcam-cnn96"] is pcam_cnn96.ARCH and pcam_cnn.ARCHS["pcam-cnn"] is pcam_cnn.PCAM_CNN
    # the first network of the family is unchanged by the parametrisation
    assert pcam_cnn.PcamCNN().layers == pcam_cnn.LAYERS == pcam_cnn.PCAM_CNN.layers


def test_pcam_cnn96_loads_and_embeds_a_view_and_a_patch():
    enc = load_encoder("pcam-cnn96")
    assert enc.name == "pcam-cnn96" and enc.dim == 64
    views = np.full((2, 128, 128, 3), 230, np.uint8)
    views[1, 32:96, 32:96] = (120, 40, 160)
    emb, logit = np.asarray(enc.embed(views)), np.asarray(enc.logits(views))
    assert emb.shape == (2, 64) and emb.dtype == np.float32 and logit.shape == (2,)
    np.testing.assert_allclose(emb[:, pcam_cnn.VIEW_LOGIT], logit, rtol=1e-5, atol=1e-5)


def test_pcam_cnn96_report_beside_its_weights_names_its_scale_and_test_pool_figures():
    report = json.loads(pcam_cnn96.WEIGHTS.with_suffix(".json").read_text())
    assert report["encoder"] == "pcam-cnn96" and report["patch_px"] == 96 and report["mpp"] == 0.972
    assert report["layers"] == [list(c) for c in pcam_cnn96.LAYERS]
    auc = report["test_pool_auc"]
    assert auc["patches"] == report["test_pool_patches"] > 10_000 // 2
    for key in ("raw", "mosaic", "probe_raw", "probe_mosaic"):
        iv = auc["intervals"][key]
        assert iv["auc_low"] <= auc[key] == iv["auc"] <= iv["auc_high"]


def test_weights_of_the_other_network_are_refused_naming_the_file():
    from data_tools.features.torch_weights import WeightsError

    with pytest.raises(WeightsError, match="pcam_cnn.msgpack"):
        pcam_cnn.read_weights(pcam_cnn.WEIGHTS, pcam_cnn96.ARCH)


def test_brightness_jitter_scales_each_patch_by_one_factor():
    import jax

    from data_tools.features.train_pcam_cnn import mosaic_augment

    x = np.random.default_rng(0).uniform(60, 180, (8, 12, 12, 3)).astype(np.float32)
    y = np.array([0, 1] * 4)
    key = jax.random.PRNGKey(1)
    plain = np.asarray(mosaic_augment(key, x, y, shift=0))
    bright = np.asarray(mosaic_augment(key, x, y, shift=0, brightness=0.1))
    ratio = bright / plain
    assert not np.allclose(ratio, 1.0)
    np.testing.assert_allclose(ratio, ratio[:, :1, :1, :1] * np.ones_like(ratio), rtol=1e-4)
    assert ((ratio[:, 0, 0, 0] >= 0.9 - 1e-5) & (ratio[:, 0, 0, 0] <= 1.1 + 1e-5)).all()
    np.testing.assert_array_equal(np.asarray(mosaic_augment(key, x, y, shift=0, brightness=0.0)), plain)


def test_linear_probe_separates_what_a_line_separates():
    from data_tools.features.train_pcam_cnn import fit_linear_probe
    from data_tools.metrics import roc_auc

    rng = np.random.default_rng(0)
    emb = rng.normal(size=(400, 5))
    y = (emb[:, 2] - 0.5 * emb[:, 4] > 0).astype(int)
    score = fit_linear_probe(emb, y)
    assert roc_auc(score(emb), y) > 0.99
    assert roc_auc(score(-emb), y) < 0.01


def test_a_checkpoint_of_other_settings_is_refused_naming_it(tmp_path):
    from data_tools.errors import HistojaxDataError
    from data_tools.features.train_pcam_cnn import train

    ck = tmp_path / "ck.pkl"
    ck.write_bytes(pickle.dumps({"settings": {"arch": "pcam-cnn", "epochs": 99}}))
    with pytest.raises(HistojaxDataError, match="ck.pkl: a checkpoint of other settings"):
        train(None, epochs=1, batch=32, max_patches=32, progress=False, checkpoint=ck)
    ck.write_bytes(b"\x00 not a pickle")
    with pytest.raises(HistojaxDataError, match="ck.pkl: not a train-encoder checkpoint"):
        train(None, epochs=1, batch=32, max_patches=32, progress=False, checkpoint=ck)


@pytest.mark.slow  # three short trainings (~20 s on 2 cores): make test-all
def test_an_interrupted_training_resumes_to_the_same_weights(tmp_path, monkeypatch):
    import jax

    from data_tools.features import train_pcam_cnn as t

    kw = dict(seed=1, epochs=2, batch=32, max_patches=64, progress=False)
    whole, report = t.train(None, **kw)
    calls = {"n": 0}
    real = t.predict

    def interrupted(*a, **k):
        calls["n"] += 1
        if calls["n"] > 2:  # both validation figures of epoch 1 pass; epoch 2's first one stops the run
            raise KeyboardInterrupt
        return real(*a, **k)

    ck = tmp_path / "ck.pkl"
    monkeypatch.setattr(t, "predict", interrupted)
    with pytest.raises(KeyboardInterrupt):
        t.train(None, checkpoint=ck, **kw)
    monkeypatch.setattr(t, "predict", real)
    resumed, report2 = t.train(None, checkpoint=ck, **kw)
    for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert report2["history"] == report["history"]
