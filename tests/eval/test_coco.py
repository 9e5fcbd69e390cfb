import contextlib
import io

import numpy as np
import pytest
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from dagr_lite.eval.coco import METRIC_KEYS, CocoEvaluator, format_metrics


def test_a_perfect_detector_scores_one():
    ev = CocoEvaluator()
    ev.add("v_frame_0", 100, 200, [[10, 10, 60, 50], [100, 20, 180, 90]], [[100, 20, 180, 90], [10, 10, 60, 50]],
           [0.9, 0.8])
    ev.add("v_frame_1", 100, 200, [[5, 5, 40, 40]], [[5, 5, 40, 40]], [0.7])
    metrics = ev.compute()
    assert metrics["mAP"] == pytest.approx(1.0) and metrics["AP50"] == pytest.approx(1.0)
    assert metrics["AR100"] == pytest.approx(1.0)


def test_a_shifted_box_is_cut_at_its_iou():
    # IoU of [0, 0, 40, 40] and [4, 0, 44, 40] is 36 / 44 = 0.818: it matches at thresholds
    # 0.50 .. 0.80 (7 of 10) and not at 0.85 .. 0.95.
    ev = CocoEvaluator()
    ev.add("v_frame_0", 100, 100, [[0, 0, 40, 40]], [[4, 0, 44, 40]], [0.9])
    metrics = ev.compute()
    assert metrics["AP50"] == pytest.approx(1.0) and metrics["AP75"] == pytest.approx(1.0)
    assert metrics["mAP"] == pytest.approx(0.7)
    assert metrics["APm"] == pytest.approx(0.7) and metrics["APs"] == -1.0  # a 40x40 box is "medium"


def test_no_detections_and_no_ground_truth_are_defined():
    ev = CocoEvaluator()
    ev.add("v_frame_0", 50, 50, [[0, 0, 10, 10]], np.zeros((0, 4)), [])
    assert all(v == 0.0 for k, v in ev.compute().items() if k in ("mAP", "AP50", "AP75", "AR100"))
    empty = CocoEvaluator()
    empty.add("v_frame_0", 50, 50, np.zeros((0, 4)), [[0, 0, 10, 10]], [0.5])
    assert all(v == -1.0 for v in empty.compute().values())
    assert all(v == -1.0 for v in CocoEvaluator().compute().values())


def test_the_printed_table_says_which_metrics_had_nothing_to_measure_and_why():
    ev = CocoEvaluator()
    ev.add("v_frame_0", 100, 100, [[0, 0, 40, 40]], [[4, 0, 44, 40]], [0.9])  # one medium box
    lines = format_metrics(ev.compute()).splitlines()
    assert lines[0].split() == list(METRIC_KEYS)
    values = dict(zip(METRIC_KEYS, lines[1].split()))
    assert values["APs"] == values["APl"] == "n/a" and values["APm"] == "0.7000"
    assert lines[2] == ("n/a: APs, APl: no ground-truth box is small (area under 32x32 pixels) or large "
                        "(area over 96x96) (-1 in metrics.json, as in COCO)")
    empty = CocoEvaluator()
    empty.add("v_frame_0", 50, 50, np.zeros((0, 4)), [[0, 0, 10, 10]], [0.5])
    assert format_metrics(empty.compute()).splitlines()[2].endswith("no ground-truth box at all (-1 in metrics.json, "
                                                                    "as in COCO)")
    whole = {key: 0.5 for key in METRIC_KEYS}
    assert len(format_metrics(whole).splitlines()) == 2 and "n/a" not in format_metrics(whole)


def reference_stats(images, gts, dets):
    """pycocotools driven the usual way: loadRes on a results list."""
    gt = COCO()
    gt.dataset = {"images": [{"id": i + 1, "height": 120, "width": 160} for i in range(images)],
                  "annotations": [{"id": j + 1, "image_id": im + 1, "category_id": 1, "bbox": [x1, y1, x2 - x1, y2 - y1],
                                   "area": (x2 - x1) * (y2 - y1), "iscrowd": 0}
                                  for j, (im, (x1, y1, x2, y2)) in enumerate(gts)],
                  "categories": [{"id": 1, "name": "hand"}]}
    with contextlib.redirect_stdout(io.StringIO()):
        gt.createIndex()
        dt = gt.loadRes([{"image_id": im + 1, "category_id": 1, "bbox": [round(v, 3) for v in
                          (x1, y1, x2 - x1, y2 - y1)], "score": s} for im, (x1, y1, x2, y2), s in dets])
        ev = COCOeval(gt, dt, "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats


def random_case(rng, images=30):
    gts, dets = [], []
    for im in range(images):
        for _ in range(int(rng.integers(0, 4))):
            x1, y1 = rng.uniform(0, 120), rng.uniform(0, 80)
            w, h = rng.uniform(4, 40), rng.uniform(4, 40)
            box = (x1, y1, x1 + w, y1 + h)
            gts.append((im, box))
            if rng.random() < 0.8:  # a noisy detection of it
                jitter = rng.normal(0, 3, 4)
                dets.append((im, tuple(np.array(box) + jitter), float(rng.random())))
        for _ in range(int(rng.integers(0, 3))):  # false positives
            x1, y1 = rng.uniform(0, 120), rng.uniform(0, 80)
            dets.append((im, (x1, y1, x1 + rng.uniform(4, 30), y1 + rng.uniform(4, 30)), float(rng.random())))
    return gts, dets


def fill(ev, images, gts, dets):
    for im in range(images):
        ev.add(f"v_frame_{im}", 120, 160, [b for i, b in gts if i == im] or np.zeros((0, 4)),
               [b for i, b, _ in dets if i == im] or np.zeros((0, 4)), [s for i, _, s in dets if i == im])
    return ev.compute()


def test_equals_pycocotools_on_random_cases():
    rng = np.random.default_rng(0)
    for _ in range(5):
        gts, dets = random_case(rng)
        ours = fill(CocoEvaluator(), 30, gts, dets)
        stats = reference_stats(30, gts, dets)
        expected = dict(zip(METRIC_KEYS, [stats[i] for i in (0, 1, 2, 3, 4, 5, 8)]))
        assert ours == pytest.approx(expected, abs=1e-12)


def test_faster_backend_gives_identical_stats():
    pytest.importorskip("faster_coco_eval")
    rng = np.random.default_rng(1)
    for _ in range(3):
        gts, dets = random_case(rng, images=40)
        assert fill(CocoEvaluator(backend="faster"), 40, gts, dets) == pytest.approx(
            fill(CocoEvaluator(), 40, gts, dets), abs=1e-9)


def test_results_json_and_bad_input():
    ev = CocoEvaluator()
    ev.add("clip_frame_3", 10, 10, [[0, 0, 5, 5]], [[1, 1, 4, 5]], [0.5])
    assert ev.results_json() == [{"image_id": 1, "category_id": 1, "bbox": [1.0, 1.0, 3.0, 4.0], "score": 0.5,
                                  "file_name": "clip_frame_3"}]
    with pytest.raises(ValueError, match="added twice"):
        ev.add("clip_frame_3", 10, 10, [], [], [])
    with pytest.raises(ValueError, match="2 boxes but 1 scores"):
        ev.add("clip_frame_4", 10, 10, [], [[0, 0, 1, 1], [0, 0, 2, 2]], [0.1])
    with pytest.raises(ValueError, match="backend"):
        CocoEvaluator(backend="nope")
