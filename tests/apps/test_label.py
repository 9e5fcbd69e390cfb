"""Labelling every frame: interpolation by hand, held-out frames, and the whole command with a tiny budget."""
import json
import re

import numpy as np
import pytest

from dagr_lite.data.labels import read_labels
from dagr_lite.apps.label import interpolate_frame, label_dataset, main, split_labels
from tests.conftest import make_dataset


def test_interpolation_between_kept_frames_by_hand():
    kept = {0: np.array([[10.0, 10, 20, 20]]), 4: np.array([[14.0, 12, 22, 20]])}  # xywh, IoU 0.52: a pair
    np.testing.assert_allclose(interpolate_frame(kept, 1), [[11.0, 10.5, 20.5, 20]])  # a quarter of the way
    np.testing.assert_allclose(interpolate_frame(kept, 6), kept[4])  # after the last: the last
    unmatched = {0: np.array([[0.0, 0, 5, 5]]), 4: np.array([[40.0, 40, 5, 5], [50, 50, 5, 5]])}
    np.testing.assert_allclose(interpolate_frame(unmatched, 1), unmatched[0])  # no pairing: the nearer frame
    np.testing.assert_allclose(interpolate_frame(unmatched, 3), unmatched[4])
    assert interpolate_frame({}, 2).shape == (0, 4)


def test_split_labels_holds_out_a_seeded_share_of_each_video():
    labels = {"a": {k: np.zeros((1, 4)) for k in range(20)}, "b": {k: np.zeros((0, 4)) for k in range(10)}}
    kept, held = split_labels(labels, share=0.9, seed=3)
    assert [len(held["a"]), len(kept["a"]), len(held["b"])] == [18, 2, 9]
    assert set(kept["a"]) | set(held["a"]) == set(range(20)) and not set(kept["a"]) & set(held["a"])
    assert split_labels(labels, share=0.9, seed=3)[1]["a"].keys() == held["a"].keys()


def test_every_frame_gets_a_label_with_its_source(tmp_path):
    written = make_dataset(tmp_path / "data", num_frames=10, events_per_video=500)
    report = label_dataset(written.root, tmp_path / "out", hide=0.5, steps=2, seed=1)
    labels = read_labels(tmp_path / "out")
    sources = json.loads((tmp_path / "out" / "label_sources.json").read_text())
    for video in written.frames:
        assert sorted(labels[video]) == list(range(10))  # every frame has an entry
    kept, _ = split_labels(read_labels(written.root), share=0.5, seed=1)
    for video, frames in kept.items():
        for k, boxes in frames.items():  # kept labels are written as given
            np.testing.assert_allclose(labels[video][k], boxes, atol=1e-3)
            assert sources[f"{video}_frame_{k}"] == ["given"] * len(boxes)
    assert {s for values in sources.values() for s in values} <= {"given", "predicted"}
    assert report["predicted"]["frames"] == report["interpolated"]["frames"] > 0
    assert 0 < report["threshold"] < 1
    assert json.loads((tmp_path / "out" / "label_quality.json").read_text()) == json.loads(json.dumps(report))
    assert (written.root / "bounding_boxes.json").read_text() != (tmp_path / "out" / "bounding_boxes.json").read_text()


@pytest.mark.parametrize("args, expected", [
    (["--hide", "1.5"], r"--hide: expected a share of the labelled frames in \(0, 1\), got 1.5"),
    (["--hide", "0", "--hold-out", "0"], r"--hide: expected a share .* got 0"),
    (["--hold-out", "0"], r"--hold-out: expected a share .* got 0"),
    (["--hold-out", "0.01"], r"--hold-out 0.01: of the \d+ labelled frames of .* none is held out"),
    (["--minutes", "0"], r"--minutes: expected a positive training budget in minutes, got 0"),
    (["--steps", "0"], r"--steps: expected a positive number of steps, got 0"),
])
def test_bad_options_are_refused_by_name_before_any_work(tmp_path, capsys, args, expected):
    written = make_dataset(tmp_path / "data", num_frames=10, events_per_video=500)
    with pytest.raises(SystemExit):
        main([str(written.root), "--out", str(tmp_path / "out"), *args])
    assert re.match(f"error: {expected}", capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_best_threshold_is_the_score_with_the_best_f1_worked_by_hand():
    from dagr_lite.apps.label import best_threshold

    held = {"v": {0: np.array([[0.0, 0, 10, 10]]), 1: np.array([[20.0, 20, 10, 10]])}}
    predicted = {"v": {0: (np.array([[0.0, 0, 10, 10], [50, 50, 10, 10]]), np.array([0.9, 0.3])),
                       1: (np.array([[20.0, 20, 10, 10], [60, 0, 10, 10]]), np.array([0.6, 0.25]))}}
    # t=0.2: tp 2, fp 2, fn 0 -> F1 4/6; t=0.5: tp 2 -> F1 1; t=0.7: tp 1, fn 1 -> F1 2/3.
    assert best_threshold(predicted, held, thresholds=[0.2, 0.5, 0.7]) == (0.5, 1.0)
    assert best_threshold(predicted, held, thresholds=[0.7, 0.2]) == (0.7, 2 / 3)  # a tie keeps the first
    # A box at IoU 1/3 with the truth is no match: at t=0.5, frame 0 has fp 1 and fn 1.
    shifted = {"v": {0: (np.array([[5.0, 0, 10, 10]]), np.array([0.9])), 1: predicted["v"][1]}}
    assert best_threshold(shifted, held, thresholds=[0.5]) == (0.5, 2 * 1 / (2 * 1 + 1 + 1))


def test_quality_is_coco_map_worked_by_hand():
    from dagr_lite.apps.label import quality

    held = {"v": {0: np.array([[0.0, 0, 10, 10]]), 1: np.array([[20.0, 20, 10, 10]])}}
    exact = {"v": {0: (held["v"][0], np.array([0.9])), 1: (held["v"][1], np.array([0.8]))}}
    assert quality(held, exact, 100, 100) == {"frames": 2, "mAP": 1.0, "AP50": 1.0, "AP75": 1.0}
    # IoU 0.62 on both frames: a match at the thresholds 0.50, 0.55 and 0.60 of the ten, none above.
    short = {"v": {k: (box * [1, 1, 1, 0.62], np.array([0.9])) for k, box in ((0, held["v"][0]), (1, held["v"][1]))}}
    got = quality(held, short, 100, 100)
    assert got["frames"] == 2 and got["AP50"] == 1.0 and got["AP75"] == 0.0 and abs(got["mAP"] - 0.3) < 1e-12
