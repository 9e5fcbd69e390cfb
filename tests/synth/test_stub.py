import numpy as np

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.synth.stub import generate_stub, simulate_video


def test_stub_is_a_valid_dataset_with_hands_and_events(tmp_path):
    root = generate_stub(tmp_path / "stub", seconds=1.0, splits={"train": 2, "valid": 1})
    assert check_dataset(root, decode_frames=True) == []
    ds = EventEgoHands(root, "train", image_size=(180, 320))
    assert len(ds) == 2 * 29
    boxes = [len(ds[i].boxes) for i in range(len(ds))]
    events = [len(ds[i].events) for i in range(len(ds))]
    assert max(boxes) >= 2 and min(events) > 0


def test_stub_is_deterministic_and_events_follow_the_hands():
    frames_a, events_a, boxes_a = simulate_video(7, num_frames=6)
    frames_b, events_b, boxes_b = simulate_video(7, num_frames=6)
    for name in "xytp":
        np.testing.assert_array_equal(events_a[name], events_b[name])
    np.testing.assert_array_equal(frames_a[3], frames_b[3])
    _, events_c, _ = simulate_video(8, num_frames=6)
    assert len(events_c["t"]) != len(events_a["t"]) or not np.array_equal(events_c["x"], events_a["x"])
    t = events_a["t"]
    assert np.all(np.diff(t) >= 0) and t[-1] <= fmt.frame_time_us(5)
    # Most events of the last frame interval fall inside a hand's box (grown by its motion).
    in_interval = t >= fmt.frame_time_us(4)
    x, y = events_a["x"][in_interval] + 0.5, events_a["y"][in_interval] + 0.5
    boxes = np.concatenate([fmt.xywh_to_xyxy(boxes_a[4]), fmt.xywh_to_xyxy(boxes_a[5])])
    inside = np.zeros(len(x), bool)
    for x1, y1, x2, y2 in boxes:
        inside |= (x >= x1 - 3) & (x <= x2 + 3) & (y >= y1 - 3) & (y <= y2 + 3)
    assert inside.mean() > 0.5
