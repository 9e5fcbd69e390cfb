"""The vectorised COCO statistics equal pycocotools' on random and edge cases."""
import numpy as np
import pytest

from dagr_lite.eval.coco import METRIC_KEYS, CocoEvaluator
from dagr_lite.eval.fast_coco import box_iou_xywh


def scored(images, backend):
    evaluator = CocoEvaluator(backend=backend)
    for i, (gt, dt, scores) in enumerate(images):
        evaluator.add(f"img_{i}", 400, 400, gt, dt, scores)
    return evaluator.compute()


def random_images(rng, count, *, max_gt=5, max_dt=15, score_digits=3):
    """xyxy ground truth and detections near it (some far), scores rounded so that ties happen."""
    images = []
    for _ in range(count):
        m, d = int(rng.integers(0, max_gt + 1)), int(rng.integers(0, max_dt + 1))
        xy = rng.uniform(0, 300, (m, 2))
        gt = np.concatenate([xy, xy + rng.uniform(4, 120, (m, 2))], axis=1)
        base = gt[rng.integers(0, m, d)] if m else np.tile([10.0, 10, 50, 50], (d, 1))
        dt = base + rng.normal(0, float(rng.choice([1, 4, 15])), (d, 4))
        dt[:, 2:] = np.maximum(dt[:, 2:], dt[:, :2] + 1)
        images.append((gt, dt, np.round(rng.uniform(0, 1, d), score_digits)))
    return images


def assert_same(images):
    ours, reference = scored(images, "numpy"), scored(images, "pycocotools")
    for key in METRIC_KEYS:
        assert ours[key] == pytest.approx(reference[key], abs=1e-9), key


@pytest.mark.parametrize("seed", range(6))
def test_equals_pycocotools_on_random_images(seed):
    rng = np.random.default_rng(seed)
    assert_same(random_images(rng, int(rng.integers(1, 40)), score_digits=int(rng.choice([1, 2, 6]))))


def test_equals_pycocotools_with_more_than_100_detections_per_image():
    assert_same(random_images(np.random.default_rng(7), 4, max_dt=180))


def test_edge_cases_equal_pycocotools():
    rng = np.random.default_rng(8)
    no_dt = [(gt, np.zeros((0, 4)), np.zeros(0)) for gt, _, _ in random_images(rng, 5)]
    no_gt = [(np.zeros((0, 4)), dt, s) for _, dt, s in random_images(rng, 5)]
    box = np.array([[10.0, 10, 60, 60]])
    ties = [(box, np.repeat(box, 3, axis=0) + [[0, 0, 0, 0], [1, 1, 1, 1], [0, 0, 0, 0]], np.array([0.5, 0.5, 0.5])),
            (np.concatenate([box, box + 2]), np.repeat(box, 2, axis=0), np.array([0.9, 0.9]))]
    for images in (no_dt, no_gt, ties, no_dt + no_gt, ties + random_images(rng, 3)):
        assert_same(images)
    assert all(value == -1 for value in scored([], "numpy").values())
    assert scored(no_dt, "numpy")["mAP"] == 0.0 and scored(no_gt, "numpy")["mAP"] == -1.0


def test_box_iou_by_hand():
    # 10x10 boxes overlapping in a 5x10 strip: 50 / (100 + 100 - 50); touching boxes do not overlap.
    iou = box_iou_xywh(np.array([[0.0, 0, 10, 10]]), np.array([[5.0, 0, 10, 10], [10.0, 0, 10, 10]]))
    assert iou.tolist() == [[50 / 150, 0.0]]
