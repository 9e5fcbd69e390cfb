"""benchmarks/streaming.py's full pass runs the sample its checkpoint reads (the baseline of its ratios)."""
import importlib.util
from pathlib import Path

from dagr_lite.apps.demo import Recording
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.synth.stub import stub_root

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "streaming.py"


def test_the_full_pass_reads_the_default_hybrids_carry_picture(trained_checkpoints):
    """The default hybrid's carry branch reads the frame beside a four-channel picture; the
    benchmark's full pass builds that sample (a three-channel picture is refused by the model)."""
    spec = importlib.util.spec_from_file_location("streaming_benchmark", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    checkpoint = load_checkpoint(trained_checkpoints["hybrid"])
    assert checkpoint.detector.carry_channels == 4 and checkpoint.sample.carry_recent_us > 0
    model = checkpoint.model(checkpoint.detector).eval()
    rec = Recording(stub_root(), "test", None)
    seconds, macs, events = bench.full_pass(model, rec, float(rec.frame_times[3]) + 20_000, sample=checkpoint.sample,
                                            repeats=1)
    assert seconds > 0 and macs > 0 and events > 0
