"""train_readers' guards and words on any dataset: the encoder-scale warning of dataset.json is repeated in one
line; --resume without a checkpoint is one line, exit 2."""

from __future__ import annotations

from pathlib import Path

from baselines.reading import train_readers


def test_the_scale_warning_is_repeated_from_dataset_json(tmp_path):
    spec = {
        "encoder_scale": {
            "encoder": "pcam-cnn",
            "encoder_mpp": 1.944,
            "tolerance": 1.5,
            "slides_out_of_scale": {"s1": 0.5},
        }
    }
    line = train_readers.scale_warning(tmp_path, spec)
    assert line.startswith(f"warning: {tmp_path / 'dataset.json'}: 1 slide(s)") and "\n" not in line
    assert train_readers.scale_warning(tmp_path, {"encoder_scale": {"slides_out_of_scale": {}}}) is None
    assert train_readers.scale_warning(tmp_path, {}) is None


def test_resume_without_a_checkpoint_is_one_line(tmp_path, capsys):
    head = Path(__file__).parents[2] / "baselines" / "published" / "c16-v2-head"
    assert (
        train_readers.main(["--dataset", str(tmp_path), "--head", str(head), "--out", str(tmp_path / "o"), "--resume"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no checkpoint to resume" in err[0]
    assert not (tmp_path / "o").exists()


def test_a_folder_without_dataset_json_is_one_line(tmp_path, capsys):
    head = Path(__file__).parents[2] / "baselines" / "published" / "c16-v2-head"
    assert train_readers.main(["--dataset", str(tmp_path), "--head", str(head), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dataset.json" in err[0]
