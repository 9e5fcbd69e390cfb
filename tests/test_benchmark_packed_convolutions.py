"""benchmarks/packed_convolutions.py: its two detectors are the packed and the unpacked one, and both answer
as the batch model's copy does (the ratio it prints compares the same function)."""
import importlib.util
from pathlib import Path

import torch

from dagr_lite.apps.demo import Recording
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.nn.blocks import PackedConv2d
from dagr_lite.stream import StreamingDetector
from dagr_lite.synth.stub import stub_root

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "packed_convolutions.py"


def test_the_packed_and_the_baseline_detector_stream_the_same_answers(trained_checkpoints):
    spec = importlib.util.spec_from_file_location("packed_benchmark", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    checkpoint = load_checkpoint(trained_checkpoints["hybrid"])
    model = checkpoint.model(checkpoint.detector).eval()
    operating = OperatingPoint(score=0.25, nms_iou=0.65)
    baseline = StreamingDetector(model, checkpoint.sample, operating, packed=False)
    packed = StreamingDetector(model, checkpoint.sample, operating, packed=True)
    assert not any(isinstance(m, PackedConv2d) for m in baseline.net.modules())
    assert any(isinstance(m, PackedConv2d) for m in packed.net.modules())
    rec = Recording(stub_root(), "test", None)
    factor_a, raws_a, answers_a = bench.stream(baseline, rec, 5_000, 0.05)
    factor_b, raws_b, answers_b = bench.stream(packed, rec, 5_000, 0.05)
    assert answers_a == answers_b == 10 and len(raws_a) == len(raws_b) == 2
    assert factor_a > 0 and factor_b > 0
    for a, b in zip(raws_a, raws_b):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-5)
