"""COCO box statistics computed with numpy over all images at once, equal to pycocotools'.

For one category, no crowd boxes, the standard parameters (IoU thresholds .50:.05:.95, 101
recall points, area ranges all / small / medium / large, at most 1, 10, 100 detections per
image). pycocotools matches detections image by image in Python; here the greedy matching runs
as one loop over detection ranks, each step deciding that rank's detection in every image,
every IoU threshold and every area range at once, with pycocotools' rules:

- an image's detections are taken by score (a stable sort, so equal scores keep their order),
  at most 100;
- a detection takes, among the ground truths it overlaps by at least the threshold and not yet
  taken, the one of largest IoU, the last of equal ones, ground truths of the area range before
  the others ("ignored" ones: outside the range);
- a detection matched to an ignored ground truth, or unmatched and itself outside the range,
  is ignored;
- precision is made monotone, read at the 101 recall points (``searchsorted``, left), and the
  summary averages the entries that are not -1.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

IOU_THRESHOLDS = np.linspace(0.5, 0.95, int(np.round((0.95 - 0.5) / 0.05)) + 1)
RECALL_POINTS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1)
AREA_RANGES = ((0.0, 1e5 ** 2), (0.0, 32.0 ** 2), (32.0 ** 2, 96.0 ** 2), (96.0 ** 2, 1e5 ** 2))  # all, s, m, l
MAX_DETECTIONS = (1, 10, 100)


def box_iou_xywh(dt: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(..., D, G)`` IoU of ``dt (..., D, 4)`` and ``gt (..., G, 4)`` xywh boxes, computed as
    pycocotools' ``bbIou`` computes it (no crowd)."""
    d, g = dt[..., :, None, :], gt[..., None, :, :]
    w = np.minimum(d[..., 0] + d[..., 2], g[..., 0] + g[..., 2]) - np.maximum(d[..., 0], g[..., 0])
    h = np.minimum(d[..., 1] + d[..., 3], g[..., 1] + g[..., 3]) - np.maximum(d[..., 1], g[..., 1])
    inter = np.where((w > 0) & (h > 0), w * h, 0.0)
    union = d[..., 2] * d[..., 3] + g[..., 2] * g[..., 3] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / union, 0.0)


def _pad(arrays: list[np.ndarray], width: int, fill: float) -> tuple[np.ndarray, np.ndarray]:
    """Stack ragged ``(n_i, width)`` arrays into ``(I, max n, width)`` with a ``(I, max n)`` mask."""
    longest = max((len(a) for a in arrays), default=0)
    out = np.full((len(arrays), longest, width), fill, dtype=np.float64)
    mask = np.zeros((len(arrays), longest), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
        mask[i, : len(a)] = True
    return out, mask


def coco_stats(gt_boxes: list[np.ndarray], dt_boxes: list[np.ndarray], dt_scores: list[np.ndarray]) -> np.ndarray:
    """pycocotools' 12 summary statistics of per-image ground truth ``(M_i, 4)`` and detections
    ``(D_i, 4)`` (xywh, as they would be given to it) with scores ``(D_i,)``.

    The areas are ``w * h`` of each box (as the evaluator records them for pycocotools too).
    """
    order = [np.argsort(-s, kind="mergesort")[: MAX_DETECTIONS[-1]] for s in dt_scores]
    dt, dt_valid = _pad([b[o] for b, o in zip(dt_boxes, order)], 4, 0.0)  # (I, D, 4) by score
    score, _ = _pad([s[o][:, None] for s, o in zip(dt_scores, order)], 1, -np.inf)
    gt, gt_valid = _pad(gt_boxes, 4, 0.0)  # (I, G, 4)
    ious = box_iou_xywh(dt, gt)  # (I, D, G)
    gt_area, dt_area = gt[..., 2] * gt[..., 3], dt[..., 2] * dt[..., 3]
    reach = ious.max(axis=2, initial=0.0) >= min(IOU_THRESHOLDS.min(), 1 - 1e-10)  # (I, D)
    num_t, num_r, num_m = len(IOU_THRESHOLDS), len(RECALL_POINTS), len(MAX_DETECTIONS)
    precision = -np.ones((num_t, num_r, len(AREA_RANGES), num_m))
    recall = -np.ones((num_t, len(AREA_RANGES), num_m))
    # Each detection limit's detections of all images, ranked by score as pycocotools ranks them
    # (images in order, each by score, then one stable sort): flat indices into (I, D).
    ranked = []
    for limit in MAX_DETECTIONS:
        keep = np.zeros_like(dt_valid)
        keep[:, :limit] = dt_valid[:, :limit]
        flat = np.flatnonzero(keep)
        ranked.append(flat[np.argsort(-score[..., 0].ravel()[flat], kind="mergesort")])

    def area_range(a: int) -> None:
        low, high = AREA_RANGES[a]
        gt_ignored = (gt_area < low) | (gt_area > high)  # (I, G)
        matched, dt_ignored = _match(ious, gt_valid, gt_ignored, dt_valid, reach)  # (T, I, D) each
        dt_ignored |= ~matched & ((dt_area < low) | (dt_area > high))[None]
        num_gt = int((gt_valid & ~gt_ignored).sum())
        if num_gt == 0:
            return
        matched, dt_ignored = matched.reshape(num_t, -1), dt_ignored.reshape(num_t, -1)
        for m, flat in enumerate(ranked):
            # Detections ignored at every threshold only repeat the curve's previous point, which
            # changes neither the precision read at any recall point nor the final recall.
            ignored = dt_ignored[:, flat]  # (T, N)
            useful = ~ignored.all(axis=0)
            hit, counted = matched[:, flat[useful]], ~ignored[:, useful]
            steps = np.cumsum(np.concatenate([hit & counted, ~hit & counted]), axis=1, dtype=np.int32)
            tp, fp = steps[:num_t].astype(float), steps[num_t:].astype(float)
            for t in range(num_t):
                precision[t, :, a, m], recall[t, a, m] = _pr_curve(tp[t], fp[t], num_gt)

    # The area ranges are independent, and numpy releases the interpreter lock on large arrays.
    with ThreadPoolExecutor(max_workers=min(len(AREA_RANGES), os.cpu_count() or 1)) as pool:
        list(pool.map(area_range, range(len(AREA_RANGES))))
    return _summarise(precision, recall)


def _match(ious: np.ndarray, gt_valid: np.ndarray, gt_ignored: np.ndarray, dt_valid: np.ndarray,
           reach: np.ndarray):
    """Greedy matching in rank order for every threshold: ``(matched, ignored)`` ``(T, I, D)``.
    ``reach (I, D)``: the detections overlapping some ground truth by the lowest threshold, the
    only ones that can match."""
    images, ranks, _ = ious.shape
    thresholds = np.minimum(IOU_THRESHOLDS, 1 - 1e-10)[:, None, None]  # (T, 1, 1)
    # Ground truth in pycocotools' order: those of the area range first (stable).
    gt_order = np.argsort(gt_ignored | ~gt_valid, axis=1, kind="mergesort")  # (I, G)
    ious = np.take_along_axis(ious, gt_order[:, None, :], axis=2)
    valid = np.take_along_axis(gt_valid, gt_order, axis=1)
    ignored = np.take_along_axis(gt_ignored, gt_order, axis=1)
    columns = np.arange(ious.shape[2])
    taken = np.zeros((len(thresholds), images, ious.shape[2]), dtype=bool)  # (T, I, G)
    matched = np.zeros((len(thresholds), images, ranks), dtype=bool)
    dt_ignored = np.zeros_like(matched)
    if ious.shape[2] == 0:  # no ground truth in any image
        return matched, dt_ignored
    reach = reach & dt_valid  # (I, D)
    for d in range(ranks):
        rows = np.flatnonzero(reach[:, d])
        if not len(rows):
            continue
        iou = ious[rows, d][None]  # (1, R, G)
        free = valid[rows][None] & ~taken[:, rows] & (iou >= thresholds)  # (T, R, G)
        pick = np.full(free.shape[:2], -1)
        ignored_here = ignored[rows]
        for group in (~ignored_here, ignored_here):  # the area range's own ground truth first
            if group is ignored_here and not ignored_here.any():
                break
            candidates = free & group[None]
            best = np.where(candidates, iou, -np.inf).max(axis=2, keepdims=True)  # (T, R, 1)
            last = np.where(candidates & (iou == best), columns, -1).max(axis=2)  # the last of equal IoUs
            pick = np.where(pick >= 0, pick, last)
        t_index, r_index = np.nonzero(pick >= 0)
        image, gt_index = rows[r_index], pick[t_index, r_index]
        taken[t_index, image, gt_index] = True
        matched[t_index, image, d] = True
        dt_ignored[t_index, image, d] = ignored[image, gt_index]
    return matched, dt_ignored


def _pr_curve(tp: np.ndarray, fp: np.ndarray, num_gt: int) -> tuple[np.ndarray, float]:
    """Precision at the recall points and the final recall of one cumulative tp / fp curve."""
    q = np.zeros(len(RECALL_POINTS))
    if len(tp) == 0:
        return q, 0.0
    rc = tp / num_gt
    pr = tp / (fp + tp + np.spacing(1))
    pr = np.maximum.accumulate(pr[::-1])[::-1]  # monotone from the end
    inds = np.searchsorted(rc, RECALL_POINTS, side="left")  # non-decreasing: those inside are a prefix
    inside = inds < len(pr)
    q[inside] = pr[inds[inside]]
    return q, float(rc[-1])


def _summarise(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """pycocotools' ``summarize`` for boxes: 12 numbers, -1 where nothing was measured."""

    def mean(values: np.ndarray) -> float:
        values = values[values > -1]
        return float(np.mean(values)) if values.size else -1.0

    t50, t75 = int(np.argmin(np.abs(IOU_THRESHOLDS - 0.5))), int(np.argmin(np.abs(IOU_THRESHOLDS - 0.75)))
    stats = [mean(precision[:, :, 0, 2]), mean(precision[t50, :, 0, 2]), mean(precision[t75, :, 0, 2]),
             mean(precision[:, :, 1, 2]), mean(precision[:, :, 2, 2]), mean(precision[:, :, 3, 2]),
             mean(recall[:, 0, 0]), mean(recall[:, 0, 1]), mean(recall[:, 0, 2]),
             mean(recall[:, 1, 2]), mean(recall[:, 2, 2]), mean(recall[:, 3, 2])]
    return np.asarray(stats, dtype=np.float64)
