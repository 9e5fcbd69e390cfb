"""benchmarks/late_fusion.py pools two models' boxes per frame as one answer would: one NMS over both."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "late_fusion.py"


def load():
    spec = importlib.util.spec_from_file_location("late_fusion_benchmark", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def entry(name, boxes, scores):
    truth = np.array([[0, 0, 10, 10]], np.float32)
    return (name, 48, 64, truth, np.asarray(boxes, np.float32).reshape(-1, 4), np.asarray(scores, np.float32))


def test_pooled_boxes_keep_the_higher_of_two_overlapping_and_every_separate_one():
    """By hand: frame a, the hybrid's box and the events' box overlap by IoU 81/119 (0.68): at 0.65 the
    higher score stays; with the events' scores halved, the other one. The events' separate box
    stays either way. Frame b: the hybrid has none, the events' box is the answer."""
    bench = load()
    hybrid = [entry("a", [[0, 0, 10, 10]], [0.6]), entry("b", [], [])]
    events = [entry("a", [[1, 1, 11, 11], [30, 30, 40, 40]], [0.9, 0.2]), entry("b", [[5, 5, 9, 9]], [0.4])]
    pooled = bench.pooled_entries(hybrid, events, iou=0.65)
    np.testing.assert_array_equal(pooled[0][4], [[1, 1, 11, 11], [0, 0, 10, 10], [30, 30, 40, 40]][::2])
    np.testing.assert_allclose(pooled[0][5], [0.9, 0.2])
    np.testing.assert_array_equal(pooled[1][4], [[5, 5, 9, 9]])
    halved = bench.pooled_entries(hybrid, events, iou=0.65, weight=0.5)
    np.testing.assert_array_equal(halved[0][4], [[0, 0, 10, 10], [30, 30, 40, 40]])
    np.testing.assert_allclose(halved[0][5], [0.6, 0.1])
    apart = bench.pooled_entries(hybrid, events, iou=0.7)  # below the overlap: both stay
    assert len(apart[0][4]) == 3
    with pytest.raises(ValueError, match="different frames"):
        bench.pooled_entries(hybrid, events[::-1], iou=0.65)


def test_the_second_checkpoint_is_needed_unless_the_hybrid_answers_again_on_a_grey_frame(tmp_path, capsys):
    """Without --events only --grey has a second set of boxes (the hybrid's own); a missing file is named."""
    bench = load()
    with pytest.raises(SystemExit):
        bench.main(["--hybrid", str(tmp_path / "h.pt")])
    assert "--events is needed" in capsys.readouterr().err
    assert bench.main(["--hybrid", str(tmp_path / "h.pt"), "--grey"]) == 1
    assert f"{tmp_path / 'h.pt'}: checkpoint file is missing" in capsys.readouterr().err
