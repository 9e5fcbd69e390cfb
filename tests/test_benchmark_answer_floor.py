"""benchmarks/answer_floor.py: what it counts, and the premise it rests on (a convolution's output at a
cell whose inputs did not change is the same to the bit)."""
import argparse
import importlib.util
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from dagr_lite.engine.checkpoint import load_checkpoint

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def floor():
    sys.path.insert(0, str(BENCHMARKS))  # the script imports its sibling streaming.py
    try:
        spec = importlib.util.spec_from_file_location("answer_floor_benchmark", BENCHMARKS / "answer_floor.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_multiply_adds_of_a_cell_by_hand(floor):
    assert floor.conv_macs_per_cell(nn.Conv2d(4, 6, 3, groups=2)) == 6 * 2 * 9
    assert floor.conv_macs_per_cell(nn.Conv2d(16, 64, 1)) == 64 * 16
    assert floor.conv_macs_per_cell(nn.Conv2d(7, 32, (4, 4), stride=4)) == 32 * 7 * 16


@pytest.mark.parametrize("channels_last", [False, True])
def test_unchanged_inputs_give_the_same_cells_to_the_bit(floor, channels_last):
    """Two pixels of the input changed: exactly the cells of a 3x3 convolution's output whose window
    holds one of them differ (4 at the corner, 9 inside), each compared to brute force, and the
    others are equal to the bit, the premise of counting changed cells by exact equality."""
    torch.manual_seed(0)
    conv = nn.Conv2d(64, 64, 3, padding=1).eval()
    x = torch.randn(1, 64, 23, 40)
    y = x.clone()
    y[0, :, 0, 0] += 1.0
    y[0, :, 10, 20] -= 1.0
    if channels_last:
        conv, x, y = (t.to(memory_format=torch.channels_last) for t in (conv, x, y))
    with torch.no_grad():
        a, b = conv(x), conv(y)
    assert floor.changed_cells(a, b) == 4 + 9
    differs = (a != b).any(dim=1)[0]
    for i in range(23):
        for j in range(40):
            near = (i <= 1 and j <= 1) or (abs(i - 10) <= 1 and abs(j - 20) <= 1)
            assert bool(differs[i, j]) == near, (i, j)


def test_a_hybrids_image_branch_is_unchanged_and_its_head_changes_everywhere(floor, trained_checkpoints):
    """The default hybrid on the stub, answers 5 ms apart with the same image: its image branch reads
    the same frame (nothing to recompute), while the recency maps, which join before the head's
    towers, change (nearly) every cell of the head at every answer."""
    state = load_checkpoint(trained_checkpoints["hybrid"])
    assert not state.detector.late_query
    _, rec = floor.recording((180, 320), 0.5, Path("unused"))
    result = floor.floor_scene(state, rec, "stub", argparse.Namespace(updates_ms=5.0, answers=3, seconds=0.5), {})
    assert result["pairs"] >= 2
    assert result["shares"]["image branch"] == 0.0
    assert result["shares"]["head"] > 0.99  # a cell may round to the same value by chance
    assert result["floor"] > result["full"] > 0


def test_an_events_only_model_compares_every_pair(floor, trained_checkpoints):
    """Without an image every two consecutive answers are a pair; a part's changed share is a share."""
    state = load_checkpoint(trained_checkpoints["events_only"])
    _, rec = floor.recording((180, 320), 0.5, Path("unused"))
    result = floor.floor_scene(state, rec, "stub", argparse.Namespace(updates_ms=5.0, answers=3, seconds=0.5), {})
    assert result["pairs"] == 3 and result["name"] == "events_only"
    assert result["shares"] and all(0.0 <= share <= 1.0 for share in result["shares"].values())
    assert result["floor"] >= result["full"] > 0


def test_priced_settings_are_checked_and_typed(floor):
    assert floor.detector_settings(["late_query=true", "carry_width=0", "time_scale_us=1e5",
                                    "strides=[16, 32]"]) == {
        "late_query": True, "carry_width": 0, "time_scale_us": 100000.0, "strides": (16, 32)}
    for item, named in (("no_such_key=1", "no_such_key"), ("height=90", "height"), ("late_query=2", "late_query"),
                        ("carry_width=0.5", "carry_width"), ("late_query", "KEY=VALUE")):
        with pytest.raises(ValueError, match=named):
            floor.detector_settings([item])
