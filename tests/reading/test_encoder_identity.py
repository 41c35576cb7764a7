"""What features a head, a dataset and an agent record, and how every scorer compares them: imported ``.h5`` features
by their folder and file layout (not one slide's file name), a published agent's training scale and encoder (its
``published.json``) against the dataset ``histojax evaluate`` scores."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from baselines.evaluate.checks import trained_record_warnings
from baselines.evaluate.heads import check_head_features
from baselines.publish import dataset_scale_record
from baselines.reading.budget_curve import load_head
from data_tools.features.hdf5 import imported_encoder
from histojax.reading.heads import encoder_mismatch, same_encoder
from histojax.reading.heads.learned import LearnedHead, init_params

UNI = "imported:20x_256px_0px_overlap/features_uni_v1/*.h5"
CONCH = "imported:20x_256px_0px_overlap/features_conch_v15/*.h5"


def test_an_import_records_its_folder_and_layout_not_one_slides_file(tmp_path):
    """Was: ``imported:Normal_141.h5``, one name per slide, so two 512-d encoders looked alike."""
    f = tmp_path / "job" / "20x_256px_0px_overlap" / "features_uni_v1" / "Normal_141.h5"
    assert imported_encoder(f) == UNI
    assert imported_encoder(tmp_path / "clam" / "h5_files" / "a.h5") == "imported:clam/h5_files/*.h5"


def test_two_imported_encoders_differ_and_older_names_stay_one_family():
    assert not same_encoder(UNI, CONCH) and same_encoder(UNI, UNI)
    assert same_encoder("imported:Normal_141.h5", UNI)  # an older import's record names one file: cannot tell
    assert same_encoder("imported", CONCH) and not same_encoder("pcam-cnn", UNI)
    assert same_encoder(None, "pcam-cnn")  # unknown is no difference


def _head(encoder, dim=8):
    p = init_params(jax.random.PRNGKey(0), dim, 4, 2, 1)
    return LearnedHead(params=p, features_dim=dim, hidden=4, attention=2, layers=1, encoder=encoder)


def test_scorers_refuse_a_head_of_another_import_folder():
    head = _head(UNI)
    assert encoder_mismatch(head, [UNI, UNI]) is None
    assert encoder_mismatch(head, [CONCH]) == f"a slide head for {UNI} features; these slides hold {CONCH} features"
    with pytest.raises(ValueError, match="features_conch_v15"):  # histojax evaluate --head
        check_head_features(head, [CONCH], 8)
    check_head_features(head, [UNI], 8)


def test_the_budget_curve_refuses_a_head_of_another_encoder(tmp_path):
    folder = _head(UNI).save(tmp_path / "head")
    tables = [{"encoder": CONCH, "instances": np.zeros((3, 8), np.float32)}]
    with pytest.raises(ValueError, match=r"head/config.json: a slide head for .*features_uni_v1.*features_conch_v15"):
        load_head(folder, tables)
    assert load_head(folder, [{**tables[0], "encoder": UNI}]) is not None


def _dataset(tmp_path, name, mpp, encoder="pcam-cnn") -> Path:
    d = tmp_path / name
    d.mkdir()
    (d / "dataset.json").write_text(
        json.dumps(
            {
                "kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
                "scale": {"mpp": mpp},
                "encoder": encoder,
                "train": [],
                "test": [],
            }
        )
    )
    return d


def _published(tmp_path, name="agent", **trained_on) -> Path:
    run = tmp_path / name
    run.mkdir()
    (run / "published.json").write_text(
        json.dumps({"name": "agent", "trained_on": {"dataset": "c16-full", "split": "train", **trained_on}})
    )
    return run


def test_a_published_agent_scored_at_another_scale_is_warned(tmp_path):
    """Was: the published agents, trained at 1.94 µm/px, were scored on the 7.78 µm/px small set without a word."""
    run = _published(tmp_path, mpp=1.944, encoder="pcam-cnn")
    small, full = _dataset(tmp_path, "small", 7.776), _dataset(tmp_path, "full", 1.944)
    scored = lambda d: {"env_kwargs": {"dataset": str(d), "split": "test"}}  # noqa: E731
    (line,) = trained_record_warnings(run, scored(small), run / "config.json")
    assert "trained at 1.94 µm/px ('c16-full'" in line and "scored at 7.78 µm/px" in line and "another scale" in line
    assert trained_record_warnings(run, scored(full), run / "config.json") == []
    other = _dataset(tmp_path, "other", 1.944, encoder="efficientnet-lite0")
    (line,) = trained_record_warnings(run, scored(other), run / "config.json")
    assert "trained on pcam-cnn features" in line and "efficientnet-lite0" in line
    bare = _published(tmp_path, "bare")  # a record without a scale or encoder: nothing to compare
    assert trained_record_warnings(bare, scored(small), "c.json") == []


def test_every_published_agent_records_its_training_scale_and_encoder():
    from baselines.published_agents import PUBLISHED

    for f in sorted(PUBLISHED.glob("*/published.json")):
        where = json.loads(f.read_text())["trained_on"]
        assert where["mpp"] == 1.944 and where["encoder"] == "pcam-cnn", f


def test_publish_records_the_datasets_scale_and_encoder(tmp_path):
    d = _dataset(tmp_path, "set", 0.5, encoder=UNI)
    assert dataset_scale_record(d) == {"mpp": 0.5, "encoder": UNI}
    assert dataset_scale_record(tmp_path / "gone") == {}


def test_a_dataset_of_your_own_slides_is_compared_by_its_slides_median_scale(tmp_path):
    """``histojax dataset`` records each slide's µm/px, not a ``scale``: its median is the dataset's scale."""
    from baselines.evaluate.checks import dataset_mpp, provenance_warnings

    def own(name, mpps):
        d = tmp_path / name
        d.mkdir()
        slides = [{"name": f"s{i}", "mpp": m} for i, m in enumerate(mpps)]
        (d / "dataset.json").write_text(
            json.dumps({"kind": "histojax dataset", "train": [], "test": [], "slides": slides})
        )
        return str(d)

    at20, at40 = own("at20", [0.50, 0.49, 0.51]), own("at40", [0.25, 0.25, 0.26])
    assert dataset_mpp(json.loads((Path(at20) / "dataset.json").read_text())) == 0.5
    trained = {"env_id": "HistoJAX-Reading-v0", "env_kwargs": {"dataset": at20, "split": "train"}}
    (line,) = provenance_warnings(trained, {"env_kwargs": {"dataset": at40, "split": "test"}}, "c.json")
    assert "trained at 0.5 µm/px" in line and "scored at 0.25 µm/px" in line
    near = own("near", [0.51, 0.505])  # a percent or two apart: one scanner's spread, not another scale
    assert provenance_warnings(trained, {"env_kwargs": {"dataset": near, "split": "test"}}, "c.json") == []
    assert dataset_scale_record(at40) == {"mpp": 0.25}
