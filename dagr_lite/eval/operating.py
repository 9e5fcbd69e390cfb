"""The operating point of a deployed detector: the score threshold and NMS IoU it answers with.

COCO evaluation scores every candidate box (score >= 0.001, NMS IoU 0.65) because mAP rewards
recall at any precision. A detector that is deployed answers with a few boxes, one per hand: the
pair (score threshold, NMS IoU) with the best F1 at IoU >= 0.5 on the validation split, chosen at
each validation of a training run and stored in its checkpoints (:class:`OperatingPoint`).

The NMS IoUs tried (:data:`NMS_IOUS`) are all below 0.5, so no two boxes an answer holds overlap
with IoU >= 0.5: two answers on one hand are what a user of the detector must never see.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from dagr_lite.errors import UserError
from dagr_lite.nn.head import box_iou

NMS_IOUS = (0.3, 0.35, 0.4, 0.45)                     # the NMS IoUs an operating point is chosen from
SCORE_THRESHOLDS = tuple(np.round(np.arange(0.05, 0.96, 0.05), 2).tolist())  # and the score thresholds
CANDIDATE_SCORE = min(SCORE_THRESHOLDS)               # the lowest score an operating point can keep
MATCH_IOU = 0.5                                       # a box finds its hand at this IoU or more


@dataclass(frozen=True)
class OperatingPoint:
    """What a deployed detector answers with: boxes of ``score`` or more after NMS at ``nms_iou``.

    ``f1``, ``precision``, ``recall``: measured on ``chosen_on`` (e.g. ``valid, ages 1 and 10``),
    or None for a point given by hand."""

    score: float
    nms_iou: float
    f1: float | None = None
    precision: float | None = None
    recall: float | None = None
    chosen_on: str | None = None

    def __post_init__(self):
        if not 0.0 <= self.score <= 1.0:
            raise UserError(f"operating point: score must be in [0, 1], got {self.score!r}")
        if not 0.0 < self.nms_iou <= 1.0:
            raise UserError(f"operating point: nms_iou must be in (0, 1], got {self.nms_iou!r}")

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "OperatingPoint":
        return cls(**values)

    def with_overrides(self, score: float | None = None, nms_iou: float | None = None) -> "OperatingPoint":
        """This point with the values given by name (None: kept); a changed point has no measured F1."""
        if (score is None or score == self.score) and (nms_iou is None or nms_iou == self.nms_iou):
            return self
        return OperatingPoint(score=self.score if score is None else float(score),
                              nms_iou=self.nms_iou if nms_iou is None else float(nms_iou))

    def describe(self) -> str:
        measured = "" if self.f1 is None else (f" (F1 {self.f1:.3f}, precision {self.precision:.3f}, recall "
                                               f"{self.recall:.3f} on {self.chosen_on})")
        return f"score >= {self.score:g}, NMS IoU {self.nms_iou:g}{measured}"


# What a checkpoint without a chosen point answers with (it was trained before points were chosen).
UNMEASURED = OperatingPoint(score=0.3, nms_iou=0.45)


def matched(truth: np.ndarray, boxes: np.ndarray, min_iou: float = MATCH_IOU) -> int:
    """How many boxes (xyxy) find a hand of ``truth`` (xyxy), one to one, at IoU >= ``min_iou``:
    the assignment of largest total IoU (Hungarian), then the pairs that overlap enough."""
    if not len(truth) or not len(boxes):
        return 0
    iou = box_iou(torch.as_tensor(np.asarray(boxes, np.float64)), torch.as_tensor(np.asarray(truth, np.float64)))
    iou = iou.numpy()
    rows, cols = linear_sum_assignment(-iou)
    return int((iou[rows, cols] >= min_iou).sum())


def f1_at(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], score: float) -> tuple[float, float, float]:
    """``(f1, precision, recall)`` of the boxes of ``score`` or more over ``frames`` of
    ``(true boxes, boxes, scores)`` (xyxy); an empty answer on an empty frame counts nothing."""
    tp = fp = fn = 0
    for truth, boxes, scores in frames:
        kept = np.asarray(boxes)[np.asarray(scores) >= score]
        hits = matched(truth, kept)
        tp, fp, fn = tp + hits, fp + len(kept) - hits, fn + len(truth) - hits
    return 2 * tp / max(1, 2 * tp + fp + fn), tp / max(1, tp + fp), tp / max(1, tp + fn)


def best_score(frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
               scores: Iterable[float] = SCORE_THRESHOLDS) -> tuple[float, tuple[float, float, float]]:
    """The score threshold of the best F1 over ``frames`` (the first of a tie), and its
    ``(f1, precision, recall)``."""
    best = None
    for score in scores:
        measured = f1_at(frames, score)
        if best is None or measured[0] > best[1][0]:
            best = (float(score), measured)
    if best is None:
        raise UserError("no score threshold to choose from")
    return best


def choose_operating_point(by_nms: dict[float, list[tuple]], chosen_on: str) -> OperatingPoint:
    """The (score, NMS IoU) pair of the best F1: ``by_nms`` maps each NMS IoU to the entries of
    :func:`~dagr_lite.eval.score.detections_of` made with it (``(name, height, width, true boxes,
    boxes, scores)``, boxes of :data:`CANDIDATE_SCORE` or more). Ties keep the lower NMS IoU."""
    best = None
    for nms_iou in sorted(by_nms):
        frames = [(truth, boxes, scores) for _, _, _, truth, boxes, scores in by_nms[nms_iou]]
        score, (f1, precision, recall) = best_score(frames)
        if best is None or f1 > best.f1:
            best = OperatingPoint(score=score, nms_iou=float(nms_iou), f1=f1, precision=precision, recall=recall,
                                  chosen_on=chosen_on)
    if best is None:
        raise UserError("no NMS IoU to choose from")
    return best
