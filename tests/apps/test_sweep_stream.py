"""The sweep measures what runs: the streaming detector, fed as a camera feeds it, answers what
the sweep's batch evaluation scores, on the same frames and image ages."""
from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.optimize import linear_sum_assignment

from dagr_lite.config import build_dataset, compose_config
from dagr_lite.engine.loading import make_loader
from dagr_lite.engine.checkpoint import load_checkpoint, load_model
from dagr_lite.eval.score import detections_of
from dagr_lite.nn.head import postprocess
from dagr_lite.apps.sweep import SweepSamples, streamed_detections, sweep_frames

AGES = (1, 3, 10)
MAX_DETECTIONS = inspect.signature(postprocess).parameters["max_detections"].default  # an image's detections' cut


def pair_detections(boxes: np.ndarray, scores: np.ndarray, other_boxes: np.ndarray, other_scores: np.ndarray,
                    leave: float) -> tuple[np.ndarray, np.ndarray]:
    """Detections ``(boxes[i], scores[i])`` paired one to one with the other list's, by the largest
    difference of any coordinate or of the score times 1000, each free to stay unpaired at a cost of
    ``leave``: ``(rows, cols)`` of the pairs."""
    n, m = len(boxes), len(other_boxes)
    cost = np.empty((n + m, m + n))  # every block set below
    cost[:n, :m] = np.maximum(np.abs(boxes[:, None] - other_boxes[None]).max(axis=2),
                              1000 * np.abs(scores[:, None] - other_scores[None]))
    cost[:n, m:] = np.where(np.eye(n, dtype=bool), leave, np.inf)  # detection i left unpaired
    cost[n:, :m] = np.where(np.eye(m, dtype=bool), leave, np.inf)  # the other's j left unpaired
    cost[n:, m:] = 0.0
    rows, cols = linear_sum_assignment(cost)
    real = (rows < n) & (cols < m)
    return rows[real], cols[real]


def assert_only_the_cut_differs(scores: np.ndarray, paired: np.ndarray, cut: int, atol: float) -> None:
    """The detections left unpaired are at most a few, each scored as the list's last one to within
    ``atol``, and only where the list was cut at ``cut`` detections: scores equal to float32 rounding
    may fall on either side of the cut."""
    unpaired = np.setdiff1d(np.arange(len(scores)), paired)
    if len(unpaired):
        assert len(scores) == cut and len(unpaired) <= 3, (len(scores), unpaired)
        np.testing.assert_allclose(scores[unpaired], scores.min(), rtol=0, atol=atol)


@pytest.mark.parametrize("variant,refractory_us,support_us", [("hybrid", 0, 0), ("events_only", 0, 0),
                                                              ("hybrid", 2_000, 0), ("events_only", 500, 5_000)])
def test_the_streaming_detector_answers_what_the_sweep_scores(trained_checkpoints, variant, refractory_us, support_us,
                                                              tmp_path):
    checkpoints = trained_checkpoints
    checkpoint = load_checkpoint(checkpoints[variant])
    detector = checkpoint.detector
    data = {**checkpoint.sample_settings, "refractory_us": refractory_us, "support_us": support_us}
    cfg = OmegaConf.merge(compose_config("sweep", [f"ckpt=[{checkpoints[variant]}]", f"out={tmp_path}",
                                                   "split=valid", "loader.num_workers=0"]), {"data": data})
    dataset = build_dataset(cfg, "valid", train=False, with_image=detector.use_image, image_age=max(AGES),
                            first_frame=max(AGES))
    model = load_model(checkpoint, detector, dataset.image_size)
    assert next(model.parameters()).dtype == torch.float32
    frames = sweep_frames(dataset, max(AGES), between=0)
    frames = [frames[i] for i in (0, 41, len(frames) - 1)]  # both videos, early and late frames
    assert dataset.refractory_us == refractory_us and dataset.support_us == support_us
    # A model a few steps old scores near its prior (objectness 0.01 x class 0.01): a threshold below
    # it compares many boxes, where the sweep's 0.001 would compare none.
    thresholds = {"conf_threshold": 1e-6, "nms_threshold": cfg.eval.nms_threshold}
    compared = 0
    for age in AGES:
        loader = make_loader(SweepSamples(dataset, frames, age, 0.0, cfg.seed), batch_size=2, num_workers=0,
                             graph=model.graph_spec)
        batch = detections_of(model, loader, torch.device("cpu"), progress=False, **thresholds)
        streamed = streamed_detections(model, dataset, frames, age, 0.0, progress=False, **thresholds)
        assert len(batch) == len(streamed) == len(frames)
        for (name, height, width, truth, boxes, scores), (s_name, s_height, s_width, s_truth, s_boxes, s_scores) \
                in zip(batch, streamed):
            assert (s_name, s_height, s_width) == (name, height, width)
            np.testing.assert_array_equal(s_truth, truth)
            assert len(boxes) > 0 and s_boxes.shape == boxes.shape, name
            # The same detections: paired one to one (boxes of scores equal to float32 rounding may come
            # in either order), every pair equal to 1e-5; at the cut of MAX_DETECTIONS a box of a score
            # equal to the last one's to rounding may be kept by one and not the other. A pair further
            # apart than twice the tolerance is left unpaired, so two such boxes kept at the cut by one
            # list each are not taken for one box moved.
            rows, cols = pair_detections(boxes, scores, s_boxes, s_scores, leave=4e-5 * max(height, width))
            assert_only_the_cut_differs(scores, rows, MAX_DETECTIONS, atol=1e-6)
            assert_only_the_cut_differs(s_scores, cols, MAX_DETECTIONS, atol=1e-6)
            np.testing.assert_allclose(s_scores[cols], scores[rows], rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(s_boxes[cols], boxes[rows], rtol=1e-5, atol=1e-5 * max(height, width))
            compared += len(rows)
    assert compared > 40
