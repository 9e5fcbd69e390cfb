"""Evaluation: COCO metrics of detections, and scoring a detector over a data loader."""
from dagr_lite.eval.coco import METRIC_KEYS, CocoEvaluator, format_metrics
from dagr_lite.eval.score import render_sample, save_pictures, score_model

__all__ = ["METRIC_KEYS", "CocoEvaluator", "format_metrics", "render_sample", "save_pictures", "score_model"]
