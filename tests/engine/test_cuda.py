"""The CUDA path: the same numbers as on the CPU where they must agree, and a training run.

Skipped where there is no CUDA GPU (CI has none). On a GPU machine:
``python -m pytest tests/engine/test_cuda.py``.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dagr_lite.data.collate import collate
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.engine.evaluate import evaluate
from dagr_lite.engine.train import train
from dagr_lite.eval import METRIC_KEYS
from dagr_lite.graph.radius import radius_graph
from dagr_lite.nn.detector import Detector
from dagr_lite.synth.stub import stub_root
from tests.engine.test_train import config, small
from tests.models import small_detector_config
from tests.settings import sample_set

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def test_the_gpu_builds_the_kdtree_graph():
    rng = np.random.default_rng(0)
    n = 20_000
    pos = np.stack([rng.integers(0, 320, n), rng.integers(0, 180, n), np.sort(rng.uniform(0, 33_333, n)) * 5e-4], 1)
    batch = torch.from_numpy(np.sort(rng.integers(0, 4, n)))
    order = np.lexsort((pos[:, 2], batch.numpy()))  # time-sorted within each sample
    pos, batch = torch.from_numpy(pos[order]), batch[order]
    on_cpu = radius_graph(pos, 5.0, 16, batch, backend="kdtree")
    on_gpu = radius_graph(pos.cuda(), 5.0, 16, batch.cuda())
    assert on_gpu.is_cuda and on_cpu.shape[1] > n and torch.equal(on_gpu.cpu(), on_cpu)


@pytest.mark.parametrize(("carry_attend", "event_dense"), [(0, 0), (5, 0), (0, 4)])
def test_the_detector_on_the_gpu_equals_the_detector_on_the_cpu(carry_attend, event_dense):
    """Losses and gradients of the same float64 weights on the same batch; the GPU builds its own
    graph (torch backend), the CPU its KD-tree one. Measured on an H100: losses within 1e-7 and
    gradients within 1e-6 (relative), from the order of the GPU's sums."""
    dataset = sample_set(stub_root(), "valid", window_us=15_000, carry_picture=True)  # the default hybrid's carry
    batch = collate([dataset[i] for i in (2, 30, 61)])
    torch.manual_seed(0)
    cfg = small_detector_config(image_width=8, event_channels=(8, 16, 16, 16), head_hidden=16, carry_attend=carry_attend,
                                event_dense=event_dense)
    model, twin = Detector(cfg).double(), Detector(cfg).double()
    twin.load_state_dict(model.state_dict())
    twin = twin.cuda()
    out, out_gpu = model(batch), twin(batch.to("cuda"))  # no edges given: each builds its own graph
    assert float(out_gpu["num_fg"]) == float(out["num_fg"]) > 0  # the same anchors assigned
    for key in ("loss", "iou_loss", "obj_loss", "cls_loss"):
        assert torch.allclose(out_gpu[key].detach().cpu(), out[key].detach(), rtol=1e-6, atol=1e-10), key
    out["loss"].backward()
    out_gpu["loss"].backward()
    for (name, p), p_gpu in zip(model.named_parameters(), twin.parameters()):
        assert (p.grad is None) == (p_gpu.grad is None), name
        if p.grad is not None:
            assert (p_gpu.grad.cpu() - p.grad).norm() <= 1e-5 * p.grad.norm() + 1e-12, name


def test_training_on_the_gpu_lowers_the_loss_and_its_checkpoint_evaluates_on_the_cpu(tmp_path):
    result = train(small(tmp_path / "run", "device=cuda", "trainer.max_steps=40", "trainer.val_every=40",
                         "loader.num_workers=2", "trainer.val_samples=null"))  # every sample, as evaluate scores
    losses = result["losses"]
    assert len(losses) == 40 and sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5
    saved = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt").training
    assert saved["step"] == 40
    evaluate(config("evaluate", f"ckpt={tmp_path / 'run' / 'checkpoints' / 'last.pt'}", f"run_dir={tmp_path / 'eval'}",
                    "split=valid", "device=cpu", "loader.num_workers=0"))
    on_cpu = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    on_gpu = result["metrics"]  # the run's own validation of the same EMA weights, on the GPU
    assert set(METRIC_KEYS) <= set(on_cpu) and on_cpu["num_images"] == on_gpu["num_images"]
    assert on_cpu["AP50"] == pytest.approx(on_gpu["AP50"], abs=0.01) and on_cpu["mAP"] == pytest.approx(on_gpu["mAP"], abs=0.01)
