"""COCO box evaluation of hand detections (single class "hand"), through pycocotools.

Each sample is one COCO image named ``<video>_frame_<k>``; boxes are xyxy pixels in and COCO
xywh inside. Metrics: AP@[.5:.95] (``mAP``, as the paper calls it), ``AP50``, ``AP75``, ``APs``,
``APm``, ``APl`` and ``AR100``. As in COCO, a metric with nothing to measure (no ground-truth
boxes at all, or none of that size) is ``-1``; with ground truth but no detections it is 0.

The default ``backend="numpy"`` computes pycocotools' statistics vectorised over all images
(:mod:`dagr_lite.eval.fast_coco`; tested equal to pycocotools), which matters on the 21,600
test images; ``pycocotools`` and ``faster`` (faster-coco-eval, optional: ``pip install
faster-coco-eval``) run those libraries.
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass, field

import numpy as np
import torch

from dagr_lite.data import format as fmt
from dagr_lite.eval.fast_coco import coco_stats

METRIC_KEYS = ("mAP", "AP50", "AP75", "APs", "APm", "APl", "AR100")
_STAT_INDEX = {"mAP": 0, "AP50": 1, "AP75": 2, "APs": 3, "APm": 4, "APl": 5, "AR100": 8}
CATEGORY_ID = 1
BACKENDS = ("numpy", "pycocotools", "faster")


def _backend_classes(backend: str):
    if backend == "pycocotools":
        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval
        return COCO, COCOeval
    if backend == "faster":
        try:
            from faster_coco_eval import COCO, COCOeval_faster
        except ImportError as err:
            raise ImportError("eval.backend=faster needs faster-coco-eval: pip install faster-coco-eval") from err
        return COCO, COCOeval_faster
    raise ValueError(f"eval backend must be one of {BACKENDS}, got {backend!r}")


def _as_array(x, shape_tail: tuple[int, ...]) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().float().cpu().numpy()
    return np.asarray(x, dtype=np.float64).reshape(-1, *shape_tail)


@dataclass
class CocoEvaluator:
    """Collects ground truth and detections image by image, then scores them with COCO.

    Boxes are kept as arrays per image (xywh; detections rounded to 1e-3 px as in a COCO results
    file); the per-box dicts pycocotools needs are made only for it.

    Args:
        backend: ``numpy`` (:mod:`dagr_lite.eval.fast_coco`, the same statistics as pycocotools,
            vectorised), ``pycocotools`` or ``faster`` (faster-coco-eval).
    """

    backend: str = "numpy"
    images: list[dict] = field(default_factory=list)

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"eval backend must be one of {BACKENDS}, got {self.backend!r}")
        self._names: set[str] = set()
        self._gt: list[np.ndarray] = []  # (M, 4) xywh per image
        self._dt: list[np.ndarray] = []  # (D, 4) xywh per image, rounded
        self._scores: list[np.ndarray] = []  # (D,)

    def add(self, name: str, height: int, width: int, gt_boxes, pred_boxes, pred_scores) -> None:
        """One image: ground truth ``(M, 4)`` and detections ``(D, 4)`` xyxy with scores ``(D,)``."""
        if name in self._names:
            raise ValueError(f"image {name!r} was added twice")
        boxes, scores = fmt.xyxy_to_xywh(_as_array(pred_boxes, (4,))), _as_array(pred_scores, ()).reshape(-1)
        if len(boxes) != len(scores):
            raise ValueError(f"image {name!r}: {len(boxes)} boxes but {len(scores)} scores")
        self._names.add(name)
        self.images.append({"id": len(self.images) + 1, "file_name": name, "height": int(height), "width": int(width)})
        self._gt.append(fmt.xyxy_to_xywh(_as_array(gt_boxes, (4,))))
        self._dt.append(np.round(boxes, 3))
        self._scores.append(scores)

    @property
    def annotations(self) -> list[dict]:
        """The ground truth as COCO annotation dicts."""
        out = []
        for image, boxes in zip(self.images, self._gt):
            for x, y, w, h in boxes.tolist():
                out.append({"id": len(out) + 1, "image_id": image["id"], "category_id": CATEGORY_ID,
                            "bbox": [x, y, w, h], "area": w * h, "iscrowd": 0})
        return out

    @property
    def detections(self) -> list[dict]:
        """The detections as COCO result dicts."""
        return [{"image_id": image["id"], "category_id": CATEGORY_ID, "bbox": box, "score": score}
                for image, boxes, scores in zip(self.images, self._dt, self._scores)
                for box, score in zip(boxes.tolist(), scores.tolist())]

    def results_json(self) -> list[dict]:
        """Detections in the COCO results format, with ``file_name`` naming each image."""
        names = {image["id"]: image["file_name"] for image in self.images}
        return [{**d, "file_name": names[d["image_id"]]} for d in self.detections]

    def compute(self) -> dict[str, float]:
        """The metrics of everything added (``-1`` where undefined)."""
        if self.backend == "numpy":
            stats = coco_stats(self._gt, self._dt, self._scores) if self.images else -np.ones(12)
            return {key: float(stats[i]) for key, i in _STAT_INDEX.items()}
        coco_cls, eval_cls = _backend_classes(self.backend)
        categories = [{"id": CATEGORY_ID, "name": "hand"}]
        gt = coco_cls()
        gt.dataset = {"images": self.images, "annotations": self.annotations, "categories": categories}
        dt = coco_cls()
        dets = [{**d, "id": i + 1, "area": d["bbox"][2] * d["bbox"][3], "iscrowd": 0}
                for i, d in enumerate(self.detections)]
        dt.dataset = {"images": self.images, "annotations": dets, "categories": categories}
        with contextlib.redirect_stdout(io.StringIO()):
            gt.createIndex()
            dt.createIndex()
            if not self.images:
                return {key: -1.0 for key in METRIC_KEYS}
            evaluator = eval_cls(gt, dt, "bbox")
            evaluator.evaluate()
            evaluator.accumulate()
            evaluator.summarize()
        stats = np.asarray(evaluator.stats, dtype=np.float64)
        return {key: float(stats[i]) for key, i in _STAT_INDEX.items()}


def format_metrics(metrics: dict[str, float]) -> str:
    """A one-table summary of the metrics; a metric with nothing to measure (COCO's -1) reads ``n/a``,
    and a line under the table says why."""
    head = " ".join(f"{key:>7s}" for key in METRIC_KEYS)
    values = " ".join(f"{'n/a':>7s}" if metrics[key] == -1 else f"{metrics[key]:7.4f}" for key in METRIC_KEYS)
    unmeasured = [key for key in METRIC_KEYS if metrics[key] == -1]
    if not unmeasured:
        return f"{head}\n{values}"
    sizes = {"APs": "small (area under 32x32 pixels)", "APm": "medium (area 32x32 to 96x96)",
             "APl": "large (area over 96x96)"}
    if set(unmeasured) <= set(sizes):
        why = "no ground-truth box is " + " or ".join(sizes[key] for key in unmeasured)
    else:
        why = "no ground-truth box at all"
    return f"{head}\n{values}\nn/a: {', '.join(unmeasured)}: {why} (-1 in metrics.json, as in COCO)"
