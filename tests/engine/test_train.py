"""Training and evaluation end to end on the stub dataset, on CPU, with tiny limits."""
import itertools
import json
from pathlib import Path

import pytest
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import dagr_lite.engine.clock as clock_module
import dagr_lite.engine.loop as loop_module
from dagr_lite.config import ConfigError
from dagr_lite.data import format as fmt
from dagr_lite.data.labels import read_labels
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.engine.evaluate import evaluate
from dagr_lite.engine.schedule import warmup_cosine
from dagr_lite.engine.starting import ResumeError
from dagr_lite.engine.train import train
from dagr_lite.eval.operating import NMS_IOUS
from dagr_lite.errors import UserError
from dagr_lite.synth.stub import stub_root
from dagr_lite.data.collate import collate
from dagr_lite.nn.detector import Detector
from tests.models import small_detector_config
from tests.settings import sample_set

CONF = Path(__file__).resolve().parents[2] / "conf"
METRIC_KEYS = {"mAP", "AP50", "AP75", "APs", "APm", "APl", "AR100"}


def config(name, *overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def small(run_dir, *overrides):
    """A tiny training config, on the CPU in float32: the exactness checks (resume, processes)
    hold there (CUDA's atomics and bfloat16 make runs differ in the last digits);
    tests/engine/test_cuda.py trains on a GPU where there is one. Validation reads 16 samples
    spread over the valid split (``trainer.val_samples``)."""
    return config("train", f"run_dir={run_dir}", "device=cpu", "trainer.amp=false", "loader.batch_size=4", "loader.num_workers=0", "optim.lr=2e-3",
                  "trainer.schedule_by=steps", "trainer.val_samples=16",
                  "trainer.warmup_steps=5", "trainer.log_every=1", "trainer.image_every=0", "data.window_us=20000",
                  *overrides)


def test_smoke_training_lowers_the_loss_then_evaluate_scores_the_checkpoint(tmp_path):
    result = train(small(tmp_path / "run", "trainer.max_steps=40", "trainer.val_every=40",
                         "trainer.image_every=20", "loader.num_workers=2", "trainer.val_samples=null"))
    losses = result["losses"]
    assert len(losses) == 40 and sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5
    run = tmp_path / "run"
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "checkpoints" / "best.pt").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert METRIC_KEYS <= set(metrics) and metrics["split"] == "valid"
    assert metrics["num_images"] == len(sample_set(stub_root(), "valid"))  # every sample scored
    assert list((run / "tensorboard").iterdir())
    evaluated = evaluate(config("evaluate", f"ckpt={run / 'checkpoints' / 'last.pt'}", f"run_dir={tmp_path / 'eval'}",
                                "split=test", "save_images=2", "loader.num_workers=0"))
    out = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert METRIC_KEYS <= set(out) and out["split"] == "test"
    assert out["num_images"] == len(sample_set(stub_root(), "test"))
    assert evaluated["metrics"]["mAP"] == out["mAP"]
    detections = json.loads((tmp_path / "eval" / "detections.json").read_text())
    assert detections and {"image_id", "category_id", "bbox", "score", "file_name"} <= set(detections[0])
    independent = pycocotools_metrics(detections, "test")  # the written detections, against the label file
    for key in ("mAP", "AP50", "AP75"):
        assert abs(out[key] - independent[key]) < 1e-9, (key, out[key], independent[key])
    test_set = sample_set(stub_root(), "test")
    first, last = (fmt.label_key(*test_set.sample_name(i)) for i in (0, len(test_set) - 1))
    assert sorted(p.name for p in (tmp_path / "eval" / "images").glob("*.png")) == sorted([f"{first}.png", f"{last}.png"])
    # The command line itself, as a user runs it.
    import subprocess
    import sys
    repo = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, str(repo / "evaluate.py"), f"ckpt={run / 'checkpoints' / 'best.pt'}",
                          f"run_dir={tmp_path / 'cli'}", "loader.num_workers=0", "split=valid"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads((tmp_path / "cli" / "metrics.json").read_text())["split"] == "valid"


def pycocotools_metrics(detections: list[dict], split: str) -> dict:
    """mAP, AP50, AP75 of ``detections`` (the results format, with ``file_name``) scored by
    pycocotools against the stub's label file, over every sample of ``split``."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    dataset = sample_set(stub_root(), split)
    labels = read_labels(stub_root())
    height, width = dataset.image_size
    names = [dataset.sample_name(i) for i in range(len(dataset))]
    images = [{"id": i + 1, "file_name": fmt.label_key(v, k), "height": height, "width": width}
              for i, (v, k) in enumerate(names)]
    ids = {image["file_name"]: image["id"] for image in images}
    annotations = [{"id": n + 1, "image_id": i + 1, "category_id": 1, "bbox": list(map(float, box)),
                    "area": float(box[2] * box[3]), "iscrowd": 0}
                   for n, (i, box) in enumerate((i, box) for i, (v, k) in enumerate(names)
                                                for box in labels.get(v, {}).get(k, np.zeros((0, 4))))]
    truth = COCO()
    truth.dataset = {"images": images, "annotations": annotations, "categories": [{"id": 1, "name": "hand"}]}
    truth.createIndex()
    found = truth.loadRes([{"image_id": ids[d["file_name"]], "category_id": 1, "bbox": d["bbox"], "score": d["score"]}
                           for d in detections])
    scoring = COCOeval(truth, found, "bbox")
    scoring.evaluate(), scoring.accumulate(), scoring.summarize()
    return {"mAP": scoring.stats[0], "AP50": scoring.stats[1], "AP75": scoring.stats[2]}


@pytest.mark.parametrize("faster", ["float32", "bfloat16", "bfloat16 by less than a tenth"])
def test_a_cpu_run_with_native_bfloat16_trains_in_the_precision_its_trial_chose(tmp_path, monkeypatch, capsys, faster):
    """``trainer.amp_dtype=auto`` on a CPU with native bfloat16 times a first batch in each precision
    and trains in bfloat16 only if it took under 0.9 of float32's time (the trial replaced here by
    fixed times); the run says which and why."""
    import dagr_lite.engine.precision as precision
    import dagr_lite.engine.train as train_module
    from dagr_lite.engine.precision import PrecisionTrial

    timed = []

    def trial(model, batch, **_):
        timed.append(len(batch))
        return PrecisionTrial(float32_s=0.2, bfloat16_s={"float32": 0.3, "bfloat16": 0.1}.get(faster, 0.19))

    monkeypatch.setattr(precision, "cpu_has_bfloat16", lambda: True)
    monkeypatch.setattr(train_module, "time_precisions", trial)
    cfg = small(tmp_path / "run", "trainer.max_steps=1", "trainer.val_every=1", "trainer.val_samples=2",
                "trainer.dense_first=0")  # no first phase: one kind of step
    cfg.trainer.amp = True
    train(cfg)
    out = capsys.readouterr().out
    assert timed == [cfg.loader.batch_size]  # one trial, on one batch of the run's size
    precision_line = "mixed precision bfloat16" if faster == "bfloat16" else "float32"
    assert f"training on cpu in {precision_line} (a step's forward and backward took 0.200 s in float32" in out
    assert "bfloat16 only if it takes under 0.9 of float32's time" in out  # the rule, beside the times
    other = "trainer.amp=false keeps float32" if faster == "bfloat16" else "trainer.amp_dtype=bfloat16 keeps bfloat16"
    assert other in out  # how to have the other precision


def test_a_run_with_a_first_phase_times_both_of_its_steps(tmp_path, monkeypatch, capsys):
    """With ``trainer.dense_first`` the trial also times the phase's step, the graph left out as the
    phase trains, and the run chooses by the schedule's mean step, naming both."""
    import dagr_lite.engine.precision as precision
    import dagr_lite.engine.train as train_module
    from dagr_lite.engine.precision import PrecisionTrial

    timed = []

    def trial(model, batch, **step):
        timed.append(step)
        return PrecisionTrial(float32_s=0.1, bfloat16_s=0.05) if step else PrecisionTrial(float32_s=0.3, bfloat16_s=0.32)

    monkeypatch.setattr(precision, "cpu_has_bfloat16", lambda: True)
    monkeypatch.setattr(train_module, "time_precisions", trial)
    cfg = small(tmp_path / "run", "trainer.max_steps=2", "trainer.val_every=2", "trainer.val_samples=2",
                "trainer.dense_first=0.5")
    cfg.trainer.amp = True
    train(cfg)
    out = capsys.readouterr().out
    assert timed == [{}, {"graph": False}]
    assert ("training on cpu in float32 (a step of the run's schedule took 0.200 s in float32 and 0.185 s in bfloat16 "
            "on this CPU (its first 50%, without the graph (trainer.dense_first): 0.100 s and 0.050 s; the rest: "
            "0.300 s and 0.320 s); bfloat16 only if") in out
    # the quick recipes' schedule by time: the shares are of the run's time, the harmonic mean turns the choice
    cfg = small(tmp_path / "by_time", "trainer.max_steps=2", "trainer.val_every=2", "trainer.val_samples=2",
                "trainer.dense_first=0.5", "trainer.schedule_by=time", "trainer.max_minutes=30")
    cfg.trainer.amp = True
    train(cfg)
    assert ("training on cpu in mixed precision bfloat16 (a step of the run's schedule took 0.150 s in float32 and "
            "0.086 s in bfloat16") in capsys.readouterr().out
    # resumed past the phase: only the whole step is left to time; resumed a quarter in: a third of what is left
    timed.clear()
    cfg = small(tmp_path / "resumed", "trainer.max_steps=4", "trainer.val_every=4", "trainer.val_samples=2",
                "trainer.dense_first=0.5", f"resume={tmp_path / 'run' / 'checkpoints' / 'last.pt'}")
    cfg.trainer.amp = True
    train(cfg)  # the checkpoint of step 2 of 4: half done, the phase over
    out = capsys.readouterr().out
    assert timed == [{}] and "step's forward and backward took 0.300 s in float32 and 0.320 s in bfloat16 on" in out
    timed.clear()
    cfg = small(tmp_path / "resumed8", "trainer.max_steps=8", "trainer.val_every=8", "trainer.val_samples=2",
                "trainer.dense_first=0.5", f"resume={tmp_path / 'run' / 'checkpoints' / 'last.pt'}")
    cfg.trainer.amp = True
    train(cfg)  # step 2 of 8: a quarter done, a quarter of the phase left, a third of the rest
    assert timed == [{}, {"graph": False}] and "(its first 33.3%, without the graph" in capsys.readouterr().out


def test_val_samples_validates_on_samples_spread_over_the_split(tmp_path, capsys):
    from dagr_lite.engine.loop import spread_subset

    assert spread_subset(list(range(10)), 4).indices == [0, 2, 5, 7]
    whole = list(range(3))
    assert spread_subset(whole, 3) is whole and spread_subset(whole, 8) is whole
    result = train(small(tmp_path / "run", "trainer.max_steps=2", "trainer.val_every=2", "trainer.val_samples=6"))
    assert result["metrics"]["num_images"] == 6
    assert "validating on 6 samples at each age (trainer.val_samples)" in capsys.readouterr().out
    with pytest.raises(ConfigError, match=r"trainer\.val_samples must be a positive integer or null"):
        train(small(tmp_path / "bad", "trainer.val_samples=0"))
    assert not (tmp_path / "bad").exists()


def keep_last_copies(monkeypatch) -> dict:
    """``{step: path}`` of a copy of every ``last.pt`` the run saves."""
    saved = {}
    original = loop_module.save_checkpoint

    def keep_copies(path, state):
        original(path, state)
        if path.name == "last.pt":
            copy = path.with_name(f"step{state['step']}.pt")
            original(copy, state)
            saved[state["step"]] = copy

    monkeypatch.setattr(loop_module, "save_checkpoint", keep_copies)
    return saved


def test_resume_continues_exactly(tmp_path, monkeypatch):
    saved = keep_last_copies(monkeypatch)
    whole = train(small(tmp_path / "a", "trainer.max_steps=5", "trainer.val_every=3"))
    resumed = train(small(tmp_path / "b", "trainer.max_steps=5", "trainer.val_every=3", f"resume={saved[3]}"))
    assert resumed["step"] == 5 and len(resumed["losses"]) == 2
    assert torch.allclose(torch.tensor(resumed["losses"]), torch.tensor(whole["losses"][3:]), rtol=1e-4)


def test_resume_continues_exactly_across_epoch_ends(tmp_path, monkeypatch):
    """22 training samples in batches of 4: 5 steps an epoch. One loader iterator serves every
    epoch; runs resumed mid-epoch and right after an epoch's last step see the same batches."""
    from tests.conftest import make_dataset
    written = make_dataset(tmp_path / "ds", num_frames=12, compression=None)
    saved = keep_last_copies(monkeypatch)

    def run(name, *overrides):
        return train(config("train", f"run_dir={tmp_path / name}", "device=cpu", "trainer.amp=false", "dataset=custom",
                            f"dataset.root={written.root}", "loader.batch_size=4", "trainer.max_steps=12", "trainer.val_every=100",
                            "trainer.checkpoint_every=1", "trainer.image_every=0", "trainer.warmup_steps=2",
                            *overrides))

    whole = run("whole", "loader.num_workers=2")
    assert whole["step"] == 12
    for start in (3, 5, 10):  # mid-epoch, after the first epoch's last step, after the second's
        resumed = run(f"from{start}", "loader.num_workers=0", f"resume={saved[start]}")
        assert resumed["step"] == 12 and len(resumed["losses"]) == 12 - start
        assert torch.allclose(torch.tensor(resumed["losses"]), torch.tensor(whole["losses"][start:]), rtol=1e-4)


def test_a_run_on_crops_trains_at_the_crop_and_validates_and_saves_at_the_frame(tmp_path, monkeypatch):
    """``data.augment.crop=0.5``: the stub's 320x180 frames are cut to 160x96 for training; the
    checkpoints record the 320x180 detector, validation scores the EMA weights at that size (as
    evaluate does from the saved checkpoint), and a resumed run continues exactly."""
    saved = keep_last_copies(monkeypatch)
    sizes, original = [], loop_module.train_step

    def recording_step(state, batch, **kwargs):
        sizes.append(tuple(batch.images.shape[-2:]))
        assert (state.model.cfg.height, state.model.cfg.width) == (96, 160)
        return original(state, batch, **kwargs)

    monkeypatch.setattr(loop_module, "train_step", recording_step)
    overrides = ("trainer.max_steps=3", "trainer.val_every=3", "trainer.checkpoint_every=1", "data.augment.crop=0.5",
                 "trainer.val_samples=null", "data.train_image_age=[1,1]")  # validation at age 1 alone
    whole = train(small(tmp_path / "a", *overrides))
    assert sizes == [(96, 160)] * 3
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    detector = load_checkpoint(last).detector
    assert (detector.height, detector.width) == (180, 320)
    evaluated = evaluate(config("evaluate", f"ckpt={last}", f"run_dir={tmp_path / 'e'}", "loader.num_workers=0",
                                "split=valid"))
    assert evaluated["metrics"]["num_images"] == whole["metrics"]["num_images"] == 118
    for key in ("mAP", "AP50", "AP75"):
        assert abs(evaluated["metrics"][key] - whole["metrics"][key]) < 1e-9, key
    resumed = train(small(tmp_path / "b", *overrides, f"resume={saved[2]}"))
    assert resumed["step"] == 3 and sizes[3:] == [(96, 160)]
    assert torch.allclose(torch.tensor(resumed["losses"]), torch.tensor(whole["losses"][2:]), rtol=1e-4)
    with pytest.raises(ConfigError, match=r"data\.augment\.crop must be a number in \(0, 1\]"):
        train(small(tmp_path / "bad", "data.augment.crop=0"))


def six_seconds_a_step(monkeypatch) -> list[float]:
    """A training clock that advances 6 s at each reading (one when it is made, one at the loop's
    start, then one after each step; only differences count); returns the learning rate each
    step of the runs uses."""
    readings = itertools.count()
    monkeypatch.setattr(clock_module.TrainingClock, "now", staticmethod(lambda: 6.0 * next(readings)))
    lrs, original = [], loop_module.train_step

    def recording_step(state, batch, **kwargs):
        lrs.append(state.lr)
        return original(state, batch, **kwargs)

    monkeypatch.setattr(loop_module, "train_step", recording_step)
    return lrs


def test_a_time_budget_schedule_decays_by_the_budget_and_stops_there(tmp_path, monkeypatch):
    """max_minutes=1 at 6 s a step: the warm-up ends after step 2 (12 s), the cosine then spans the
    48 s left, and the run stops after step 11 (66 s > 60 s). The step count alone (max_epochs
    100000) would keep the rate at its top."""
    lrs = six_seconds_a_step(monkeypatch)
    result = train(small(tmp_path / "run", "trainer.max_steps=null", "trainer.max_epochs=100000",
                         "trainer.max_minutes=1", "trainer.schedule_by=time", "trainer.warmup_steps=2",
                         "trainer.val_every=1000", "optim.lr=1e-3", "trainer.min_lr_ratio=0.05"))
    assert result["step"] == 11 and len(lrs) == 11
    # step k runs at the schedule's step k - 1, from the clock read after step k - 1: 6 (k - 1) s
    expected = [1e-3 * warmup_cosine(k - 1, warmup=2, total=10**9, min_ratio=0.05,
                                     progress=max(0.0, (6 * (k - 1) - 12) / 48)) for k in range(1, 12)]
    assert lrs == pytest.approx(expected)
    assert lrs[:3] == pytest.approx([0.5e-3, 1e-3, 1e-3])  # warm-up, then the cosine's top
    assert lrs[6] == pytest.approx(1e-3 * 0.525)  # step 7, halfway through the time left: cos(pi / 2)
    assert lrs[-1] == pytest.approx(1e-3 * 0.05)  # the last step, with the budget spent: the floor
    saved = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt").training
    assert saved["position"]["elapsed_s"] == 66.0 and saved["position"]["warmup_end_s"] == 12.0


def test_a_time_budget_run_resumes_on_its_own_clock(tmp_path, monkeypatch):
    """Resumed after step 5 (30 s spent), the run's rate and its stop follow the whole run's;
    resumed with its budget spent, it takes no step."""
    saved = keep_last_copies(monkeypatch)
    lrs = six_seconds_a_step(monkeypatch)
    budget = ["trainer.max_steps=null", "trainer.max_epochs=100000", "trainer.max_minutes=1",
              "trainer.schedule_by=time", "trainer.warmup_steps=2", "trainer.val_every=1000",
              "trainer.checkpoint_every=1"]
    whole = train(small(tmp_path / "whole", *budget))
    whole_lrs = list(lrs)
    lrs.clear()
    resumed = train(small(tmp_path / "resumed", *budget, f"resume={saved[5]}"))
    assert whole["step"] == resumed["step"] == 11
    assert lrs == pytest.approx(whole_lrs[5:])
    assert torch.allclose(torch.tensor(resumed["losses"]), torch.tensor(whole["losses"][5:]), rtol=1e-4)
    lrs.clear()
    spent = train(small(tmp_path / "spent", *budget, f"resume={saved[11]}"))  # 66 s of the 60 spent
    assert spent["step"] == 11 and spent["losses"] == [] and lrs == []


def image_steps(monkeypatch) -> list[tuple[bool, float, float]]:
    """Records, for each training step: whether it reads the image, and the sums of the absolute
    image-reading weights (the event branch's, the fusion's and the head's image stems') and of
    the image branch's weights before it."""
    seen, original = [], loop_module.train_step

    @torch.no_grad()
    def sums(model):
        reading = model.fuse[0][0].weight[:, :model.image.channels[1]].abs().sum() if model.image is not None else 0
        if model.image is not None and model.head.has_image:  # late_query: the head's image towers
            reading = reading + sum(stem[0].weight.abs().sum() for stem in model.head.image_stems)
        if model.image is not None and model.events is not None:
            reading = reading + model.events.stages[0][0].conv.weight[-model.events.image_channels[0]:].abs().sum()
        branch = sum(p.abs().sum() for p in model.image.parameters()) if model.image is not None else 0
        return float(reading), float(branch)

    def recording_step(state, batch, *, image=True):
        seen.append((image, *sums(state.model)))
        return original(state, batch, image=image)

    monkeypatch.setattr(loop_module, "train_step", recording_step)
    return seen


def test_events_first_learns_from_the_events_alone_then_the_image_joins(tmp_path, monkeypatch):
    """trainer.events_first=0.5 over 6 steps: steps 1-3 read no image, the weights that read it
    stay exactly zero and the image branch does not move; from step 4 it learns. An events-only
    model is left as it is."""
    seen = image_steps(monkeypatch)
    train(small(tmp_path / "hybrid", "trainer.max_steps=6", "trainer.events_first=0.5", "trainer.dense_first=0", "trainer.val_every=1000",
                "data.augment.image_dropout=0"))
    assert [image for image, _, _ in seen] == [False] * 3 + [True] * 3
    assert [reading for _, reading, _ in seen[:4]] == [0.0] * 4 and seen[5][1] > 0
    assert len({branch for _, _, branch in seen[:4]}) == 1 and seen[5][2] != seen[0][2]
    seen.clear()
    train(small(tmp_path / "events", "model=events_only", "trainer.max_steps=2", "trainer.events_first=0.5",
                "trainer.val_every=1000"))
    assert [image for image, _, _ in seen] == [True, True]
    seen.clear()  # a run started from init_from starts from those weights: no phase, nothing zeroed
    train(small(tmp_path / "started", "trainer.max_steps=2", "trainer.events_first=0.5", "trainer.val_every=1000",
                f"init_from={tmp_path / 'events' / 'checkpoints' / 'last.pt'}"))
    assert [image for image, _, _ in seen] == [True, True] and seen[0][1] > 0
    with pytest.raises(ConfigError, match=r"trainer\.events_first must be a number in \[0, 1\)"):
        train(small(tmp_path / "bad", "trainer.events_first=1.0"))


def test_image_first_learns_from_the_image_alone_then_the_events_join(tmp_path, monkeypatch):
    """trainer.image_first=0.5 over 6 steps: steps 1-3 run no event branch, the fusion's weights
    for the event and recency maps stay exactly zero and the event branch does not move; from
    step 4 they learn. Both phases at once, or with late_query, are refused."""
    seen, original = [], loop_module.train_step

    @torch.no_grad()
    def sums(model):
        c, e = model.image.channels[1], model.events.out_channels[0]
        reading = float(model.fuse[0][0].weight[:, c:c + e + model.num_recency].abs().sum())
        return reading, float(sum(p.abs().sum() for p in model.events.parameters()))

    def recording_step(state, batch, *, image=True, events=True):
        seen.append((image, events, *sums(state.model)))
        return original(state, batch, image=image, events=events)

    monkeypatch.setattr(loop_module, "train_step", recording_step)
    calls = []
    real = Detector._image_features
    monkeypatch.setattr(Detector, "_image_features", lambda self, batch: calls.append(1) or real(self, batch))
    train(small(tmp_path / "hybrid", "trainer.max_steps=6", "trainer.image_first=0.5", "trainer.dense_first=0", "trainer.val_every=1000",
                "data.augment.image_dropout=0"))
    assert [(image, events) for image, events, _, _ in seen] == [(True, False)] * 3 + [(True, True)] * 3
    assert len(calls) == 3  # the event branch was not run in the phase
    assert [reading for _, _, reading, _ in seen[:4]] == [0.0] * 4 and seen[5][2] > 0
    assert len({branch for *_, branch in seen[:4]}) == 1 and seen[5][3] != seen[0][3]
    with pytest.raises(ConfigError, match=r"a run has one first phase, not two"):
        train(small(tmp_path / "both", "trainer.image_first=0.5", "trainer.events_first=0.5"))
    with pytest.raises(ConfigError, match=r"trainer\.image_first=0\.5 needs model\.late_query=false"):
        train(small(tmp_path / "late", "trainer.image_first=0.5", "trainer.dense_first=0", "model.late_query=true", "model.carry_width=0"))


def test_a_hybrid_with_its_event_weights_zeroed_answers_what_it_answers_without_events():
    """``zero_event_weights``: the fused head then reads nothing of the events, so the hybrid's raw
    output with its events equals ``forward(events=False)``'s, and differs before the zeroing."""
    torch.manual_seed(0)
    model = Detector(small_detector_config(180, 320)).eval()
    dataset = sample_set(stub_root(), "valid", image_age=2, carry_picture=True)
    batch = collate([dataset[i] for i in (3, 30)])
    with torch.no_grad():
        before, _, _ = model.outputs(batch)
        blind, _, _ = model.outputs(batch, events=False)
        assert not torch.allclose(before, blind)
        model.zero_event_weights()
        after, _, _ = model.outputs(batch)
    torch.testing.assert_close(after, blind, rtol=0, atol=0)


def test_dense_first_learns_without_the_graph_then_the_graph_joins(tmp_path, monkeypatch):
    """trainer.dense_first=0.5 over 6 steps: steps 1-3 run no event branch and their batches come
    without a graph, the fusion's weights for the event maps stay exactly zero and the event branch
    does not move, while the recency and carry columns learn; from step 4 every batch has its graph
    and the event weights learn. With another first phase, or an event head, it is refused."""
    seen, original = [], loop_module.train_step

    @torch.no_grad()
    def sums(model):
        c, e = model.image.channels[1], model.events.out_channels[0]
        weight = model.fuse[0][0].weight
        return (float(weight[:, c:c + e].abs().sum()), float(weight[:, c + e:].abs().sum()),
                float(sum(p.abs().sum() for p in model.events.parameters())))

    def recording_step(state, batch, *, graph=True):
        seen.append((graph, batch.edge_index is not None, *sums(state.model)))
        return original(state, batch, graph=graph)

    monkeypatch.setattr(loop_module, "train_step", recording_step)
    train(small(tmp_path / "hybrid", "trainer.max_steps=6", "trainer.dense_first=0.5", "trainer.val_every=1000",
                "loader.num_workers=1"))
    assert [graph for graph, *_ in seen] == [False] * 3 + [True] * 3
    assert [has for _, has, *_ in seen[3:]] == [True] * 3  # the graph joined: every batch has one
    assert not seen[0][1]  # the workers built none in the phase
    assert [reading for _, _, reading, _, _ in seen[:4]] == [0.0] * 4 and seen[5][2] > 0
    assert seen[3][3] != seen[0][3]  # the recency and carry columns learnt in the phase
    assert len({branch for *_, branch in seen[:4]}) == 1 and seen[5][4] != seen[0][4]
    with pytest.raises(ConfigError, match=r"a run has one first phase, not two"):
        train(small(tmp_path / "both", "trainer.dense_first=0.5", "trainer.image_first=0.5"))
    with pytest.raises(ConfigError, match=r"trainer\.dense_first=0\.5 needs model\.event_head_weight=0"):
        train(small(tmp_path / "head", "trainer.dense_first=0.5", "model.event_head_weight=0.5"))
    with pytest.raises(ConfigError, match=r"trainer\.events_first=0\.5 hides the image .* data\.carry_align_us=5000"):
        train(small(tmp_path / "moved", "trainer.events_first=0.5", "trainer.dense_first=0",
                    "data.carry_align_us=5000"))


def test_a_hybrid_with_its_graph_weights_zeroed_answers_what_it_answers_without_its_graph():
    """``zero_graph_weights``: the fused head then reads nothing of the event branch, so the hybrid's
    raw output with its graph equals ``forward(graph=False)``'s, which needs no graph, and differs
    before the zeroing; the recency maps and the carry branch still read the events."""
    torch.manual_seed(0)
    model = Detector(small_detector_config(180, 320)).eval()
    dataset = sample_set(stub_root(), "valid", image_age=2, carry_picture=True)
    batch = collate([dataset[i] for i in (3, 30)])
    bare = collate([dataset[i] for i in (3, 30)])
    batch.edge_index = model.graph_spec.edges(batch.events, batch.batch_index)
    with torch.no_grad():
        before, _, _ = model.outputs(batch)
        dense, _, _ = model.outputs(bare, graph=False)
        assert not torch.allclose(before, dense)
        assert not torch.allclose(dense, model.outputs(bare, events=False)[0])  # the events still count
        model.zero_graph_weights()
        after, _, _ = model.outputs(batch)
    torch.testing.assert_close(after, dense, rtol=0, atol=0)


def test_events_first_follows_a_time_budget(tmp_path, monkeypatch):
    """With schedule_by=time at 6 s a step (warm-up of 2 steps, 48 s of cosine after it), the phase
    ends where the time spent after the warm-up reaches half: step k runs after the reading of
    6 (k - 1) s, events alone while (6 (k - 1) - 12) / 48 < 0.5, so steps 1-6 read no image and 7-11 do."""
    six_seconds_a_step(monkeypatch)
    seen = image_steps(monkeypatch)
    train(small(tmp_path / "run", "trainer.max_steps=null", "trainer.max_epochs=100000", "trainer.max_minutes=1",
                "trainer.schedule_by=time", "trainer.warmup_steps=2", "trainer.val_every=1000",
                "trainer.events_first=0.5", "trainer.dense_first=0", "data.augment.image_dropout=0"))
    assert [image for image, _, _ in seen] == [False] * 6 + [True] * 5


def test_a_time_schedule_needs_a_time_budget(tmp_path):
    with pytest.raises(ConfigError, match=r"trainer\.schedule_by=time needs .*trainer\.max_minutes"):
        train(small(tmp_path / "run", "trainer.schedule_by=time", "trainer.max_minutes=null"))
    with pytest.raises(ConfigError, match=r"trainer\.schedule_by must be steps or time, got 'epochs'"):
        train(small(tmp_path / "run", "trainer.schedule_by=epochs"))


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
    with pytest.raises(ValueError, match="cannot read as a dagr_lite checkpoint") as refused:
        evaluate(config("evaluate", f"ckpt={tmp_path / 'junk.pt'}", f"run_dir={tmp_path / 'e2'}"))
    assert "weights_only" not in str(refused.value)  # not torch's advice to load it unsafely
    with pytest.raises(Exception, match="ckpt"):
        evaluate(config("evaluate", f"run_dir={tmp_path / 'e3'}"))  # ckpt is required


def test_evaluation_takes_the_data_and_graph_settings_from_the_checkpoint(tmp_path, capsys):
    train(small(tmp_path / "run", "model=events_only", "trainer.max_steps=1", "data.window_us=20000",
                "data.image_age=2", "model.graph.radius=4"))
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    capsys.readouterr()
    evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'e'}", "loader.num_workers=0", "split=valid"))
    out = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert out["data"] == {"image_age": 2, "window_us": 20000, "context_us": 10000, "refractory_us": 0,
                           "max_events": 100000, "event_picture": False, "graph_context_us": 0,
                           "carry_picture": False, "carry_recent_us": 20000, "support_us": 0,
                           "carry_confirm_us": 0, "carry_align_us": 0, "carry_spans_us": [], "carry_onset": False}
    assert out["graph"] == {"radius": 4.0, "beta": 5e-4, "max_neighbors": 8} and out["overrides"] == {}
    assert out["num_images"] == len(sample_set(stub_root(), "valid", image_age=2))
    printed = OmegaConf.create(capsys.readouterr().out.split("\n\n")[0])  # the config, as the evaluation uses it
    assert printed.graph == out["graph"] and printed.data.window_us == 20000
    assert "augment" not in printed.data and "train_image_age" not in printed.data  # training's alone
    evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'o'}", "loader.num_workers=0", "split=valid",
                    "data.window_us=33333", "graph.radius=5"))
    assert "override: data.window_us=33333 (the checkpoint was trained with 20000)" in capsys.readouterr().out
    out = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert out["data"]["window_us"] == 33333 and out["graph"]["radius"] == 5.0
    assert out["overrides"] == {"data.window_us": {"checkpoint": 20000, "used": 33333},
                                "graph.radius": {"checkpoint": 4.0, "used": 5}}


def test_evaluation_refuses_what_the_model_cannot_take(tmp_path, dataset):
    train(small(tmp_path / "run", "model=image_only", "trainer.max_steps=1"))
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    with pytest.raises(ConfigError, match=r"trained on 320x180 frames, but the dataset's frames are 64x48"):
        evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'a'}", "dataset=custom",
                        f"dataset.root={dataset.root}", "loader.num_workers=0"))
    with pytest.raises(ConfigError, match=r"graph\.radius=3\.0 was given, but the checkpoint's model has no event branch"):
        evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'b'}", "graph.radius=3.0"))
    with pytest.raises(ConfigError, match=r"data\.event_picture=True changes the model's input"):
        evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'b'}", "data.event_picture=true"))
    with pytest.raises(UserError, match="split must be one of train, valid, test, got 'tset'"):
        evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 's'}", "split=tset"))
    assert not (tmp_path / "s").exists()  # refused before its run folder was made
    at_data = evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'c'}", "dataset=custom",
                              f"dataset.root={dataset.root}", "loader.num_workers=0", "model_size=data"))
    assert at_data["metrics"]["overrides"] == {"model_size": {"checkpoint": [320, 180], "used": [64, 48]}}
    with pytest.raises(ConfigError, match=r"model_size='sensor': expected one of \('checkpoint', 'data'\)"):
        evaluate(config("evaluate", f"ckpt={ckpt}", f"run_dir={tmp_path / 'd'}", "model_size=sensor"))
    assert not (tmp_path / "d").exists()


def test_bad_values_stop_before_the_run_folder_is_made(tmp_path):
    for i, override in enumerate(("trainer.max_steps=-3", "trainer.val_every=-1", "loader.batch_size=0",
                                  "data.window_us=abc")):
        with pytest.raises(ConfigError, match=override.split("=")[0].replace(".", r"\.")):
            train(small(tmp_path / f"run{i}", override))
        assert not (tmp_path / f"run{i}").exists()


def test_a_run_that_fails_on_its_dataset_leaves_no_folder_and_the_corrected_command_runs(tmp_path):
    """The dataset is read before the run folder is written, so the corrected command is not
    refused as "holds an earlier run"."""
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=str(empty)):
        train(small(tmp_path / "run", "dataset=custom", f"dataset.root={empty}"))
    assert not (tmp_path / "run").exists()
    assert train(small(tmp_path / "run", "model=image_only", "trainer.max_steps=1"))["step"] == 1


def test_a_mistake_on_the_command_line_is_one_line_and_leaves_no_folder(tmp_path):
    """No traceback, exit status 1, and the empty folders Hydra made (runs/train/<date>/<time>)
    are gone; with HYDRA_FULL_ERROR=1 the traceback is shown."""
    import os
    import subprocess
    import sys
    repo = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    run = subprocess.run([sys.executable, str(repo / "train.py"), "loader.batch_size=0"], capture_output=True,
                         text=True, cwd=tmp_path, env=env)
    assert run.returncode == 1
    assert run.stderr.strip() == "error: loader.batch_size must be a positive integer, got 0"
    assert list(tmp_path.iterdir()) == []
    full = subprocess.run([sys.executable, str(repo / "train.py"), "loader.batch_size=0"], capture_output=True,
                          text=True, cwd=tmp_path, env={**env, "HYDRA_FULL_ERROR": "1"})
    assert full.returncode == 1 and "Traceback" in full.stderr and "ConfigError" in full.stderr
    sweep = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", f"out={tmp_path / 'sweep'}"],
                           capture_output=True, text=True, cwd=tmp_path, env=env)
    assert sweep.returncode == 1
    assert sweep.stderr.strip() == ("error: invalid configuration: Missing mandatory value: ckpt; "
                                    "give it on the command line: ckpt=...")
    assert list(tmp_path.iterdir()) == []


def test_a_setting_or_option_that_does_not_exist_is_one_line_and_leaves_no_folder(tmp_path):
    """A misspelt key, a config group's option that does not exist and an override that cannot be
    read: one line naming it (the options of the group), exit status 1, no folder."""
    import os
    import subprocess
    import sys
    repo = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    cases = {
        "loader.batchsize=8": "error: loader.batchsize: no such setting in conf/train.yaml (`--cfg job` prints every setting)",
        "model=event_only": "error: model=event_only: no such option; model is one of events_only, hybrid, image_only",
        "seed=[1": "error: the command line cannot be read: no viable alternative at input '[1'",
        "+loader.batchsize=8": "error: +loader.batchsize: no such setting in conf/train.yaml; a setting added with '+'",
    }
    for argument, message in cases.items():
        run = subprocess.run([sys.executable, str(repo / "train.py"), argument], capture_output=True, text=True,
                             cwd=tmp_path, env=env)
        assert run.returncode == 1, argument
        assert run.stderr.strip().startswith(message) and "\n" not in run.stderr.strip(), run.stderr
        assert list(tmp_path.iterdir()) == []
    sweep = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", "ckpt=x.pt", "ags=[1]"], capture_output=True,
                           text=True, cwd=tmp_path, env=env)
    assert sweep.returncode == 1
    assert sweep.stderr.strip() == "error: ags: no such setting in conf/sweep.yaml (`--cfg job` prints every setting)"
    # Hydra's own flags still reach it.
    shown = subprocess.run([sys.executable, str(repo / "train.py"), "--cfg", "job"], capture_output=True, text=True,
                           cwd=tmp_path, env=env)
    assert shown.returncode == 0 and "dataset:" in shown.stdout


def test_a_refused_run_writes_nothing_into_the_earlier_one(tmp_path):
    import subprocess
    import sys
    repo = Path(__file__).resolve().parents[2]
    earlier = tmp_path / "run"
    (earlier / "checkpoints").mkdir(parents=True)
    (earlier / "config.yaml").write_text("the earlier run's config\n")
    run = subprocess.run([sys.executable, str(repo / "train.py"), f"run_dir={earlier}", "model=image_only"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode != 0 and "holds an earlier run" in run.stderr
    assert sorted(p.name for p in earlier.iterdir()) == ["checkpoints", "config.yaml"]
    assert (earlier / "config.yaml").read_text() == "the earlier run's config\n"
    assert not (tmp_path / "runs").exists()  # nor a stray folder of Hydra's


def test_resume_refuses_another_variant_and_keeps_the_best_checkpoint(tmp_path, monkeypatch):
    train(small(tmp_path / "a", "model=image_only", "trainer.max_steps=2", "trainer.val_every=1"))
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    with pytest.raises(ResumeError, match=r"use_events: False in the checkpoint, True here.*leave out the model= "):
        train(small(tmp_path / "b", "model=hybrid", "trainer.max_steps=3", f"resume={last}"))
    with pytest.raises(ResumeError, match=r"trained with AdamW, this run's optimizer is SGD; its state cannot continue"):
        train(small(tmp_path / "d", "model=image_only", "optim=sgd", "trainer.max_steps=3", f"resume={last}"))
    assert not (tmp_path / "d").exists()
    # The resumed run never beats the old best: its folder still holds the best weights.
    monkeypatch.setattr(loop_module, "validation_pass",
                        lambda *args, **kwargs: ({k: 0.0 for k in METRIC_KEYS}, {iou: [] for iou in NMS_IOUS}))
    train(small(tmp_path / "c", "model=image_only", "trainer.max_steps=3", "trainer.val_every=1", f"resume={last}"))
    best_old = load_checkpoint(tmp_path / "a" / "checkpoints" / "best.pt").training
    best_new = load_checkpoint(tmp_path / "c" / "checkpoints" / "best.pt").training
    assert best_new["step"] == best_old["step"] and best_new["best_metric"] == best_old["best_metric"]


def test_last_checkpoint_is_saved_when_validation_fails(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise OSError("a corrupt frame in the valid split")

    monkeypatch.setattr(loop_module, "validation_pass", broken)
    with pytest.raises(OSError, match="corrupt frame"):
        train(small(tmp_path / "run", "model=image_only", "trainer.max_steps=2", "trainer.val_every=2"))
    saved = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt").training
    assert saved["step"] == 2


def test_a_dataset_with_truncated_frame_times_passes_check_and_trains(tmp_path):
    from dagr_lite.data import format as fmt
    from dagr_lite.data.check import main as check_main
    from dagr_lite.data.events import EventFile
    from tests.conftest import make_dataset
    from tests.data.test_conventions import on_frame_events, reference_timeidx, write_by_hand
    written = make_dataset(tmp_path / "ds", num_frames=12, compression=None)
    for i, (video, split) in enumerate(written.splits.items()):
        events = on_frame_events("truncate", num_frames=12, seed=i)  # events exactly on the truncated frame times
        path = fmt.events_path(written.root, split, video)
        write_by_hand(path, events, 12, reference_timeidx(events["t"], 12, "truncate"))
        assert EventFile(path, num_frames=12).convention == "truncate"
    assert check_main([str(written.root)]) == 0
    result = train(config("train", f"run_dir={tmp_path / 'run'}", "dataset=custom", f"dataset.root={written.root}",
                          "loader.batch_size=4", "loader.num_workers=0", "trainer.max_steps=2",
                          "trainer.image_every=0"))
    assert result["step"] == 2 and METRIC_KEYS <= set(result["metrics"])


def train_until_saved_then(stop, run, *, workers: int):
    """``python train.py`` of an events-only model in ``run`` (a process group of its own, saving
    last.pt after every step) until its first last.pt, then ``stop(proc)``; the finished process and
    its output."""
    import os
    import signal
    import subprocess
    import sys
    import time

    stub_root()  # made here, not inside the timed wait below
    last = run / "checkpoints" / "last.pt"
    args = [sys.executable, str(CONF.parent / "train.py"), f"run_dir={run}", "device=cpu", "trainer.amp=false",
            "loader.batch_size=4", f"loader.num_workers={workers}", "trainer.max_steps=100000",
            "trainer.max_epochs=null", "trainer.max_minutes=null", "trainer.schedule_by=steps",
            "trainer.checkpoint_every=1", "trainer.val_every=100000", "trainer.image_every=0", "data.window_us=20000",
            "model=events_only"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        waited = 0.0
        while not last.exists() and proc.poll() is None and waited < 600:
            time.sleep(0.2)
            waited += 0.2
        assert last.exists(), proc.communicate()[0] if proc.poll() is not None else "no step was taken"
        stop(proc)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc, out


def test_a_first_ctrl_c_saves_last_like_a_sigterm(tmp_path):
    """Ctrl-C in a terminal: the run stops after its step, saves last.pt, prints the resume command
    and exits with 130; before, it stopped unsaved and left a folder that a rerun refused."""
    import signal

    run = tmp_path / "run"
    last = run / "checkpoints" / "last.pt"
    proc, out = train_until_saved_then(lambda proc: proc.send_signal(signal.SIGINT), run, workers=1)
    assert proc.returncode == 130, out
    step = load_checkpoint(last).training["step"]
    assert f"Ctrl-C: stopped after step {step} and saved {last}; continue with: python train.py resume={last} " in out


def test_a_sigterm_to_the_whole_process_group_still_saves_last(tmp_path):
    """What ``timeout`` and many schedulers do: SIGTERM to every process of the run's group. The
    loader's workers are in groups of their own, so the main process stops after its step, saves
    last.pt and exits with 143 (a worker killed by the signal first made the save fail)."""
    import os
    import signal

    run = tmp_path / "run"
    last = run / "checkpoints" / "last.pt"
    proc, out = train_until_saved_then(lambda proc: os.killpg(proc.pid, signal.SIGTERM), run, workers=2)
    assert proc.returncode == 143, out
    step = load_checkpoint(last).training["step"]
    assert f"SIGTERM: stopped after step {step} and saved {last}" in out and "could not be written" not in out


def test_sigterm_saves_last_and_the_run_resumes_from_it(tmp_path):
    """A real SIGTERM to ``python train.py`` (what a cluster sends before preemption): the step
    under way finishes, last.pt is saved and named, the process exits with 143, and resume=
    continues from that step."""
    import signal
    import subprocess
    import sys

    run = tmp_path / "run"
    last = run / "checkpoints" / "last.pt"
    proc, out = train_until_saved_then(lambda proc: proc.send_signal(signal.SIGTERM), run, workers=0)
    assert proc.returncode == 143, out
    step = load_checkpoint(last).training["step"]
    assert step >= 1
    assert f"SIGTERM: stopped after step {step} and saved {last}; continue with: python train.py resume={last} " in out
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.pt"]  # no temporary file left
    # the advice as printed, with one change: the run's own settings (events_only, the window) come back
    config_before = (run / "config.yaml").read_text()
    again = subprocess.run([sys.executable, str(CONF.parent / "train.py"), f"resume={last}",
                            f"trainer.max_steps={step + 2}"], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resumed from {last} at step {step}" in again.stdout
    assert load_checkpoint(last).training["step"] == step + 2 and load_checkpoint(last).model_name == "events_only"
    assert (run / "config.yaml").read_text() == config_before and (run / "metrics.json").is_file()
    resumes = OmegaConf.to_container(OmegaConf.load(run / "resumes.yaml"))  # how the run went on, logged
    assert resumes == [{"step": step, "resume": str(last), "overrides": [f"resume={last}", f"trainer.max_steps={step + 2}"]}]
    assert not (tmp_path / "runs").exists()  # no empty folder of Hydra's left behind


def test_pictures_are_spread_over_the_split():
    from dagr_lite.engine.evaluate import spread_indices
    assert spread_indices(10, 3) == [0, 4, 9] and spread_indices(10, 1) == [0] and spread_indices(2, 5) == [0, 1]
    assert spread_indices(0, 4) == [] and spread_indices(118, 4) == [0, 39, 78, 117]


def test_resuming_at_or_past_the_runs_end_says_there_is_nothing_to_train(tmp_path, capsys):
    train(small(tmp_path / "a", "model=image_only", "trainer.max_steps=2"))
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    capsys.readouterr()
    train(small(tmp_path / "a", "model=image_only", "trainer.max_steps=1", f"resume={last}"))
    out = capsys.readouterr().out
    assert "resumed from" in out and "at step 2 (it ran on 1 process)" in out
    assert "step 2 is at or past its length of 1 steps: nothing to train (raise trainer.max_steps" in out
    assert load_checkpoint(last).training["step"] == 2


def test_the_bars_time_left_follows_the_steps_when_they_end_the_run_first(tmp_path, capsys):
    """With a 9-minute budget a 6-step run's bar showed the budget's ~540 s left at its last step."""
    import re
    train(small(tmp_path / "a", "model=image_only", "trainer.max_steps=6", "trainer.max_minutes=9",
                "trainer.schedule_by=time"))
    err = capsys.readouterr().err
    left = [int(v) for v in re.findall(r"left=(\d+)s", err)]
    assert left and left[-1] < 270  # one step left at the steps' pace, not the budget's 500-odd seconds
