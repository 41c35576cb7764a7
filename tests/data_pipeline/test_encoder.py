"""``pcam-cnn`` (histojax's PCam-trained encoder) and the PCam patch pools it was trained on.

The shipped 1,000-patch bank (``data_tools/pcam/bank.npz``, CC0, a subsample of the 20,000 patches the
weights were trained on) is cut by the same pool rule: its test-pool patches are patches the shipped
weights never saw, so their AUC here is a held-out figure (small: ~500 patches)."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from data_tools.datasets.pcam_bank import in_test_pool, load_bank, pool_rule, split_pools
from data_tools.features import ENCODERS, pcam_cnn
from data_tools.features.efficientnet import load_encoder


@pytest.fixture(scope="module")
def bank():
    return load_bank()


def test_pools_are_disjoint_and_independent_of_the_bank(bank):
    train, test = split_pools(bank)
    assert len(train) + len(test) == len(bank)
    key = lambda b: {(int(lab), str(n)) for lab, n in zip(b.labels, b.names)}  # noqa: E731
    assert not key(train) & key(test)
    for pool in (train, test):
        assert set(np.unique(pool.labels)) == {0, 1}
    # the rule depends on each patch alone: any subset or order puts a patch on the same side
    rng = np.random.default_rng(0)
    idx = rng.permutation(len(bank))[:300]
    assert (in_test_pool(bank.names[idx], bank.labels[idx]) == in_test_pool(bank.names, bank.labels)[idx]).all()
    assert abs(len(test) / len(bank) - pool_rule()["test_fraction"]) < 0.06


def test_registered_encoders_include_pcam_cnn():
    assert ENCODERS["pcam-cnn"][0] == pcam_cnn.DIM <= 64
    assert {"colour-stats", "efficientnet-lite0"} <= set(ENCODERS)


# a view (128 px) in `make test`; a patch (48 px) and the size between under `make test-all`
@pytest.mark.parametrize(
    "side", [pytest.param(48, marks=pytest.mark.slow), pytest.param(96, marks=pytest.mark.slow), 128]
)
def test_any_image_size_patch_or_view(side):
    enc = load_encoder("pcam-cnn")
    rng = np.random.default_rng(1)
    x = rng.integers(0, 256, (3, side, side, 3), dtype=np.uint8)
    emb, logit = np.asarray(enc.embed(x)), np.asarray(enc.logits(x))
    assert emb.shape == (3, pcam_cnn.DIM) and logit.shape == (3,)
    assert np.isfinite(emb).all()
    np.testing.assert_allclose(emb[:, -2], logit, rtol=1e-5, atol=1e-5)  # mean of the logit map
    assert (emb[:, -1] >= emb[:, -2] - 1e-5).all()  # its max
    np.testing.assert_array_equal(np.asarray(enc.embed(x)), emb)  # deterministic


def test_a_view_of_tumour_scores_above_a_view_of_normal_tissue(bank):
    """4 × 4 tiles of 48-px test-pool patches make a 192-px view: tumour views score higher."""
    from data_tools.features.train_pcam_cnn import box_half

    _, test = split_pools(bank)
    enc = load_encoder("pcam-cnn")
    scores = {}
    for lab in (0, 1):
        patches = box_half(test.decode(test.indices(lab)[:64]))
        views = patches.reshape(4, 4, 4, 48, 48, 3).transpose(0, 1, 3, 2, 4, 5).reshape(4, 192, 192, 3)
        scores[lab] = np.asarray(enc.logits(views))
    assert scores[1].min() > scores[0].max()


def test_shipped_weights_beat_chance_on_held_out_patches(bank):
    """Patch AUC on the shipped bank's test pool (never trained on). The model card's figure (on ~10,000
    test-pool patches) is higher; this guards against broken weights or preprocessing."""
    from data_tools.features.train_pcam_cnn import test_pool_auc

    auc = test_pool_auc(pcam_cnn.read_weights(), None)
    assert auc["patches"] == len(split_pools(bank)[1])
    assert auc["raw"] > 0.85 and auc["mosaic"] > 0.8, auc


def test_weights_file_errors_name_the_file(tmp_path):
    from data_tools.features.torch_weights import WeightsError

    bad = tmp_path / "w.msgpack"
    bad.write_bytes(b"\x00not msgpack")
    with pytest.raises(WeightsError, match="w.msgpack"):
        pcam_cnn.read_weights(bad)
    with pytest.raises(WeightsError, match="missing.msgpack"):
        pcam_cnn.read_weights(tmp_path / "missing.msgpack")


def test_train_command_writes_loadable_weights_and_a_report(tmp_path):
    """The training command end to end on a few shipped patches (1 epoch): weights load, report complete."""
    from data_tools.__main__ import main

    out = tmp_path / "enc.msgpack"
    assert (
        main(["train-encoder", "--out", str(out), "--epochs", "1", "--max-patches", "64", "--batch", "32", "--quiet"])
        == 0
    )
    variables = pcam_cnn.read_weights(out)
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["fitted_patches"] + report["validation_patches"] == 64
    assert report["pool_rule"] == pool_rule() and len(report["patches_sha256"]) == 64
    assert 0 <= report["test_pool_auc"]["raw"] <= 1
    x = jnp.zeros((2, 48, 48, 3), jnp.uint8)
    assert pcam_cnn.apply(variables, x)[0].shape == (2, pcam_cnn.DIM)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_training_is_reproducible_from_its_seed():
    from data_tools.features.train_pcam_cnn import train

    a, ra = train(None, seed=3, epochs=1, batch=32, max_patches=64, progress=False)
    b, rb = train(None, seed=3, epochs=1, batch=32, max_patches=64, progress=False)
    for x, y in zip(jax_leaves(a), jax_leaves(b)):
        np.testing.assert_array_equal(x, y)
    assert ra["history"] == rb["history"]


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def test_pcam_patches_as_distributed_are_brought_to_the_benchmark_scale(bank):
    from data_tools.features.train_pcam_cnn import box_half

    x = bank.decode(np.arange(8))
    np.testing.assert_array_equal(np.asarray(pcam_cnn.to_benchmark_scale(x, 0.972)), box_half(x))
    assert pcam_cnn.to_benchmark_scale(x[:, :48, :48], pcam_cnn.SCALE_MPP).shape == (8, 48, 48, 3)
    assert pcam_cnn.to_benchmark_scale(x, 0.486).shape == (8, 24, 24, 3)
