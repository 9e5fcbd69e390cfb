"""benchmarks/streaming.py: its full pass runs the sample its checkpoint reads (the baseline of its ratios), and
the camera-rate scene it keeps reads as the video it copies."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from dagr_lite.apps.demo import Recording
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.synth.stub import stub_root

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "streaming.py"


def benchmark():
    """The benchmark script as a module."""
    spec = importlib.util.spec_from_file_location("streaming_benchmark", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def test_the_full_pass_reads_the_default_hybrids_carry_picture(trained_checkpoints):
    """The default hybrid's carry branch reads the frame beside a four-channel picture; the
    benchmark's full pass builds that sample (a three-channel picture is refused by the model)."""
    bench = benchmark()
    checkpoint = load_checkpoint(trained_checkpoints["hybrid"])
    assert checkpoint.detector.carry_channels == 4 and checkpoint.sample.carry_recent_us > 0
    model = checkpoint.model(checkpoint.detector).eval()
    rec = Recording(stub_root(), "test", None)
    seconds, macs, events = bench.full_pass(model, rec, float(rec.frame_times[3]) + 20_000, sample=checkpoint.sample,
                                            repeats=1)
    assert seconds > 0 and macs > 0 and events > 0


def test_a_kept_scene_reads_as_the_video_it_copies(tmp_path):
    """``--keep-camera``: the scene's event file and frames are copied in the dataset layout (so detect
    and ``Recording`` read it as they read the original), and a folder holding anything is refused."""
    bench = benchmark()
    root = stub_root()
    original = Recording(root, "test", None)
    kept = bench.keep_scene(root, original.video, tmp_path / "kept")
    assert kept == tmp_path / "kept" / "test" / "events" / f"{original.video}.h5"
    copy = Recording(tmp_path / "kept", "test", original.video)
    assert np.array_equal(copy.frame_times, original.frame_times)
    for key in ("x", "y", "t", "p"):
        assert np.array_equal(copy.events[key], original.events[key])
    assert len(copy.frames) == len(original.frames) and np.array_equal(copy.frames[-1], original.frames[-1])
    with pytest.raises(SystemExit, match="not an empty folder"):
        bench.keep_scene(root, original.video, tmp_path / "kept")
