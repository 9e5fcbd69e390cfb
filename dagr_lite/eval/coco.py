"""COCO box evaluation of hand detections (single class "hand"), through pycocotools.

Each sample is one COCO image named ``<video>_frame_<k>``; boxes are xyxy pixels in and COCO
xywh inside. Metrics: AP@[.5:.95] (``mAP``, as the paper calls it), ``AP50``, ``AP75``, ``APs``,
``APm``, ``APl`` and ``AR100``. As in COCO, a metric with nothing to measure (no ground-truth
boxes at all, or none of that size) is ``-1``; with ground truth but no detections it is 0.

``backend="faster"`` computes the same statistics with faster-coco-eval (an optional
package: ``pip install faster-coco-eval``), which matters on the 21,600 test images.
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass, field

import numpy as np
import torch

from dagr_lite.data import format as fmt

METRIC_KEYS = ("mAP", "AP50", "AP75", "APs", "APm", "APl", "AR100")
_STAT_INDEX = {"mAP": 0, "AP50": 1, "AP75": 2, "APs": 3, "APm": 4, "APl": 5, "AR100": 8}
CATEGORY_ID = 1
BACKENDS = ("pycocotools", "faster")


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

    Args:
        backend: ``pycocotools`` or ``faster``.
    """

    backend: str = "pycocotools"
    images: list[dict] = field(default_factory=list)
    annotations: list[dict] = field(default_factory=list)
    detections: list[dict] = field(default_factory=list)

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"eval backend must be one of {BACKENDS}, got {self.backend!r}")
        self._names: set[str] = set()

    def add(self, name: str, height: int, width: int, gt_boxes, pred_boxes, pred_scores) -> None:
        """One image: ground truth ``(M, 4)`` and detections ``(D, 4)`` xyxy with scores ``(D,)``."""
        if name in self._names:
            raise ValueError(f"image {name!r} was added twice")
        self._names.add(name)
        image_id = len(self.images) + 1
        self.images.append({"id": image_id, "file_name": name, "height": int(height), "width": int(width)})
        for x, y, w, h in fmt.xyxy_to_xywh(_as_array(gt_boxes, (4,))):
            self.annotations.append({"id": len(self.annotations) + 1, "image_id": image_id,
                                     "category_id": CATEGORY_ID, "bbox": [x, y, w, h], "area": w * h,
                                     "iscrowd": 0})
        boxes, scores = fmt.xyxy_to_xywh(_as_array(pred_boxes, (4,))), _as_array(pred_scores, ()).reshape(-1)
        if len(boxes) != len(scores):
            raise ValueError(f"image {name!r}: {len(boxes)} boxes but {len(scores)} scores")
        for (x, y, w, h), score in zip(boxes, scores):
            self.detections.append({"image_id": image_id, "category_id": CATEGORY_ID,
                                    "bbox": [round(float(v), 3) for v in (x, y, w, h)], "score": float(score)})

    def results_json(self) -> list[dict]:
        """Detections in the COCO results format, with ``file_name`` naming each image."""
        names = {image["id"]: image["file_name"] for image in self.images}
        return [{**d, "file_name": names[d["image_id"]]} for d in self.detections]

    def compute(self) -> dict[str, float]:
        """The metrics of everything added (``-1`` where undefined)."""
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
    """A one-table summary of the metrics."""
    head = " ".join(f"{key:>7s}" for key in METRIC_KEYS)
    values = " ".join(f"{metrics[key]:7.4f}" for key in METRIC_KEYS)
    return f"{head}\n{values}"
