import itertools

import numpy as np
import pytest

from dagr_lite.eval.operating import (NMS_IOUS, SCORE_THRESHOLDS, OperatingPoint, choose_operating_point, f1_at,
                                      matched)


def box(x, y, w=10.0, h=10.0):
    return [x, y, x + w, y + h]


def iou(a, b):
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def brute_matched(truth, boxes, min_iou=0.5):
    """The most one-to-one pairs of IoU >= min_iou, by trying every assignment."""
    truth, boxes = list(truth), list(boxes)
    if len(boxes) > len(truth):
        truth, boxes = boxes, truth
    best = 0
    for chosen in itertools.permutations(range(len(truth)), len(boxes)):
        best = max(best, sum(iou(boxes[i], truth[j]) >= min_iou for i, j in enumerate(chosen)))
    return best


def greedy_nms(boxes, scores, threshold):
    order = np.argsort(-scores, kind="stable")
    kept = []
    for i in order:
        if all(iou(boxes[i], boxes[j]) <= threshold for j in kept):
            kept.append(i)
    return np.array(kept, dtype=int)


def test_f1_of_a_case_worked_by_hand():
    truth = np.array([box(0, 0), box(50, 50)])
    boxes = np.array([box(1, 0), box(50, 51), box(100, 100), box(0, 1)])  # two hits, a miss, a second box on hand 1
    scores = np.array([0.9, 0.6, 0.8, 0.4])
    # score >= 0.5: boxes 0, 1, 2: tp 2, fp 1, fn 0 -> F1 4/5; >= 0.7: boxes 0, 2: tp 1, fp 1, fn 1 -> 1/2
    assert f1_at([(truth, boxes, scores)], 0.5) == pytest.approx((4 / 5, 2 / 3, 1.0))
    assert f1_at([(truth, boxes, scores)], 0.7) == pytest.approx((1 / 2, 1 / 2, 1 / 2))
    # every box: the second box on hand 1 is a false positive: tp 2, fp 2 -> 4/6
    assert f1_at([(truth, boxes, scores)], 0.0)[0] == pytest.approx(4 / 6)
    assert f1_at([(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0))], 0.5) == (0.0, 0.0, 0.0)


def test_matching_is_the_largest_one_to_one_assignment_found_by_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(200):
        truth = [box(*rng.uniform(0, 30, 2)) for _ in range(rng.integers(0, 4))]
        boxes = [box(*rng.uniform(0, 30, 2)) for _ in range(rng.integers(0, 5))]
        found = matched(np.array(truth).reshape(-1, 4), np.array(boxes).reshape(-1, 4))
        assert found == brute_matched(truth, boxes)


def test_the_chosen_point_is_the_best_f1_over_every_pair_by_brute_force():
    rng = np.random.default_rng(7)
    frames = []
    for _ in range(12):
        truth = np.array([box(*rng.uniform(0, 60, 2), *rng.uniform(8, 20, 2)) for _ in range(rng.integers(0, 3))])
        truth = truth.reshape(-1, 4)
        near = [t + rng.normal(0, 2, 4) for t in truth for _ in range(rng.integers(1, 4))]  # several per hand
        far = [np.array(box(*rng.uniform(0, 60, 2))) for _ in range(rng.integers(0, 3))]
        boxes = np.array(near + far).reshape(-1, 4)
        frames.append((truth, boxes, rng.uniform(0.05, 1.0, len(boxes))))
    by_nms = {}
    for threshold in NMS_IOUS:
        entries = []
        for k, (truth, boxes, scores) in enumerate(frames):
            kept = greedy_nms(boxes, scores, threshold)
            entries.append((f"v_frame_{k}", 100, 100, truth, boxes[kept], scores[kept]))
        by_nms[threshold] = entries
    point = choose_operating_point(by_nms, chosen_on="a test")

    def brute_f1(threshold, score):
        tp = fp = fn = 0
        for _, _, _, truth, boxes, scores in by_nms[threshold]:
            kept = boxes[scores >= score]
            hits = brute_matched(truth, kept)
            tp, fp, fn = tp + hits, fp + len(kept) - hits, fn + len(truth) - hits
        return 2 * tp / max(1, 2 * tp + fp + fn)

    table = {(t, s): brute_f1(t, s) for t in NMS_IOUS for s in SCORE_THRESHOLDS}
    assert point.f1 == pytest.approx(max(table.values()))
    assert table[(point.nms_iou, point.score)] == pytest.approx(point.f1)
    assert point.chosen_on == "a test" and 0 < point.f1 < 1


def test_every_nms_iou_tried_keeps_two_boxes_of_one_hand_apart():
    assert max(NMS_IOUS) < 0.5  # no two boxes of an answer overlap with IoU >= 0.5


def test_an_operating_point_checks_its_values_and_takes_overrides_by_name():
    point = OperatingPoint(score=0.4, nms_iou=0.35, f1=0.8, precision=0.9, recall=0.7, chosen_on="valid")
    assert OperatingPoint.from_dict(point.as_dict()) == point
    assert point.with_overrides() is point and point.with_overrides(score=0.4) is point
    assert point.with_overrides(score=0.6) == OperatingPoint(score=0.6, nms_iou=0.35)  # no longer measured
    assert "F1 0.800" in point.describe() and "F1" not in point.with_overrides(nms_iou=0.5).describe()
    with pytest.raises(ValueError, match="score must be in \\[0, 1\\], got 1.5"):
        OperatingPoint(score=1.5, nms_iou=0.4)
    with pytest.raises(ValueError, match="nms_iou must be in \\(0, 1\\], got 0"):
        OperatingPoint(score=0.5, nms_iou=0)
