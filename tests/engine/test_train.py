from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from dagr_lite.engine.evaluate import evaluate
from dagr_lite.engine.train import train

CONF = Path(__file__).resolve().parents[2] / "conf"


def test_train_builds_the_default_stub_data_and_reads_a_batch(capsys):
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(config_name="train", overrides=["loader.num_workers=0", "loader.batch_size=4"])
    result = train(cfg)
    out = capsys.readouterr().out
    assert "name: stub" in out and "[train]: 4 videos" in out and "[valid]: 1 videos" in out
    batch = result["batch"]
    assert len(batch) == 4 and batch.images.shape == (4, 3, 180, 320)
    assert batch.events.shape[1] == 4 and len(batch.events) > 0
    assert torch.all(batch.events[:, 2] < 33333) and torch.all(batch.events[:, 2] >= 0)
    assert len(result["datasets"]["train"]) == 4 * 89


def test_evaluate_opens_the_requested_split(capsys):
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(config_name="evaluate", overrides=["split=test"])
    result = evaluate(cfg)
    assert result["dataset"].split == "test" and len(result["dataset"]) == 89
    assert "[test]: 1 videos" in capsys.readouterr().out
