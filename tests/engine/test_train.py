"""Training and evaluation end to end on the stub dataset, on CPU, with tiny limits."""
import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import dagr_lite.engine.train as train_module
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.engine.evaluate import evaluate
from dagr_lite.engine.train import train
from dagr_lite.synth.stub import stub_root

CONF = Path(__file__).resolve().parents[2] / "conf"
METRIC_KEYS = {"mAP", "AP50", "AP75", "APs", "APm", "APl", "AR100"}


def config(name, *overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def small(run_dir, *overrides):
    return config("train", f"run_dir={run_dir}", "loader.batch_size=4", "loader.num_workers=0", "optim.lr=2e-3",
                  "trainer.warmup_steps=5", "trainer.log_every=1", "trainer.image_every=0", "data.max_events=6000",
                  *overrides)


def test_smoke_training_lowers_the_loss_then_evaluate_scores_the_checkpoint(tmp_path):
    result = train(small(tmp_path / "run", "trainer.max_steps=40", "trainer.val_every=40",
                         "trainer.image_every=20", "loader.num_workers=2"))
    losses = result["losses"]
    assert len(losses) == 40 and sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5
    run = tmp_path / "run"
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "checkpoints" / "best.pt").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert METRIC_KEYS <= set(metrics) and metrics["split"] == "valid"
    assert metrics["num_images"] == len(EventEgoHands(stub_root(), "valid"))  # every sample scored
    assert list((run / "tensorboard").iterdir())
    evaluated = evaluate(config("evaluate", f"ckpt={run / 'checkpoints' / 'last.pt'}", f"run_dir={tmp_path / 'eval'}",
                                "split=test", "save_images=2", "loader.num_workers=0"))
    out = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert METRIC_KEYS <= set(out) and out["split"] == "test"
    assert out["num_images"] == len(EventEgoHands(stub_root(), "test"))
    assert evaluated["metrics"]["mAP"] == out["mAP"]
    detections = json.loads((tmp_path / "eval" / "detections.json").read_text())
    assert detections and {"image_id", "category_id", "bbox", "score", "file_name"} <= set(detections[0])
    assert len(list((tmp_path / "eval" / "images").glob("*.png"))) == 2
    # The command line itself, as a user runs it.
    import subprocess
    import sys
    repo = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, str(repo / "evaluate.py"), f"ckpt={run / 'checkpoints' / 'best.pt'}",
                          f"run_dir={tmp_path / 'cli'}", "loader.num_workers=0", "split=valid"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads((tmp_path / "cli" / "metrics.json").read_text())["split"] == "valid"


def test_resume_continues_exactly(tmp_path, monkeypatch):
    saved = {}
    original = train_module.save_checkpoint

    def keep_copies(path, state):
        original(path, state)
        if path.name == "last.pt":
            copy = path.with_name(f"step{state['step']}.pt")
            original(copy, state)
            saved[state["step"]] = copy

    monkeypatch.setattr(train_module, "save_checkpoint", keep_copies)
    whole = train(small(tmp_path / "a", "trainer.max_steps=5", "trainer.val_every=3"))
    resumed = train(small(tmp_path / "b", "trainer.max_steps=5", "trainer.val_every=3", f"resume={saved[3]}"))
    assert resumed["step"] == 5 and len(resumed["losses"]) == 2
    assert torch.allclose(torch.tensor(resumed["losses"]), torch.tensor(whole["losses"][3:]), rtol=1e-4)


def test_non_finite_loss_stops_with_the_step(tmp_path, monkeypatch):
    import dagr_lite.nn.detector as detector_module
    real = detector_module.yolox_losses
    calls = []

    def poisoned(*args, **kwargs):
        out = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == 2:
            out["loss"] = out["loss"] * float("nan")
        return out

    monkeypatch.setattr(detector_module, "yolox_losses", poisoned)
    with pytest.raises(FloatingPointError, match="non-finite loss nan at step 1"):
        train(small(tmp_path / "run", "trainer.max_steps=3"))


@pytest.mark.parametrize("variant", ["image_only", "events_only"])
def test_variants_train_and_report(tmp_path, variant):
    result = train(small(tmp_path / variant, f"model={variant}", "trainer.max_steps=2"))
    assert METRIC_KEYS <= set(result["metrics"])


def test_runs_never_overwrite_and_bad_checkpoints_are_named(tmp_path):
    train(small(tmp_path / "run", "model=image_only", "trainer.max_steps=1"))
    with pytest.raises(FileExistsError, match="holds an earlier run"):
        train(small(tmp_path / "run", "model=image_only", "trainer.max_steps=1"))
    with pytest.raises(FileNotFoundError, match="checkpoint file is missing"):
        evaluate(config("evaluate", f"ckpt={tmp_path / 'nope.pt'}", f"run_dir={tmp_path / 'e1'}"))
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read as a dagr_lite checkpoint"):
        evaluate(config("evaluate", f"ckpt={tmp_path / 'junk.pt'}", f"run_dir={tmp_path / 'e2'}"))
    with pytest.raises(Exception, match="ckpt"):
        evaluate(config("evaluate", f"run_dir={tmp_path / 'e3'}"))  # ckpt is required
