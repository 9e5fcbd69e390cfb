"""The evaluation entry: ``evaluate(cfg)`` is what ``python evaluate.py`` runs and what tests call.

The checkpoint defines the model (its architecture and event graph) and what one sample is
(image age, event window and context, event cap). A value given in ``data.*`` or ``graph.*`` overrides the
checkpoint's: it is printed as an override and recorded in ``metrics.json``, beside the data and
graph settings the evaluation actually used. One that changes which channels the model's input
picture holds is refused (:func:`~dagr_lite.engine.checkpoint.check_picture_layout`).
"""
from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Subset

from dagr_lite.config import ConfigError, build_dataset, check_values, resolve_config
from dagr_lite.engine.checkpoint import (MODEL_SIZES, at_model_size, check_picture_layout, describe_dataset,
                                         load_checkpoint, load_model, settings)
from dagr_lite.engine.loading import make_loader
from dagr_lite.engine.runs import resolve_device, run_folder
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics
from dagr_lite.eval.score import save_pictures, score_model


TRAINING_ONLY = ("train_image_age", "train_image_age_power", "train_image_age_ramp", "augment")


def used_config(cfg: DictConfig, detector) -> DictConfig:
    """``cfg`` as the evaluation uses it, to print: the event graph the model reads (the
    checkpoint's, or an override's), none for a model without one, and no training-only data keys."""
    shown = OmegaConf.to_container(cfg)
    shown["graph"] = None if detector.graph is None else detector.graph.as_dict()
    for key in TRAINING_ONLY:
        shown["data"].pop(key, None)
    return OmegaConf.create(shown)


def spread_indices(size: int, count: int) -> list[int]:
    """``count`` indices (at most ``size``) spread evenly over ``range(size)``, first and last included."""
    count = min(count, size)
    if count <= 1:
        return list(range(count))
    return sorted({round(i * (size - 1) / (count - 1)) for i in range(count)})


def evaluate(cfg: DictConfig) -> dict:
    """Score a checkpoint's EMA weights on ``cfg.split``; writes ``metrics.json`` and ``detections.json``."""
    cfg = resolve_config(cfg)
    checkpoint = load_checkpoint(cfg.ckpt)
    data, detector, overrides = settings(cfg, checkpoint)
    cfg = OmegaConf.merge(cfg, {"data": data})
    check_values(cfg)
    check_picture_layout(checkpoint.path, checkpoint.sample_settings, data)
    if cfg.model_size not in MODEL_SIZES:
        raise ConfigError(f"model_size={cfg.model_size!r}: expected one of {MODEL_SIZES}")
    print(OmegaConf.to_yaml(used_config(cfg, detector)), flush=True)
    for key, change in overrides.items():
        print(f"override: {key}={change['used']!r} (the checkpoint was trained with {change['checkpoint']!r})")
    device = resolve_device(cfg.device)
    dataset = build_dataset(cfg, cfg.split, train=False, with_image=detector.use_image)
    print(describe_dataset(dataset, image=detector.use_image, events=detector.use_events), flush=True)
    detector = at_model_size(cfg.model_size, detector, dataset.image_size, overrides)
    model = load_model(checkpoint, detector, dataset.image_size).to(device)
    run_dir = run_folder(cfg, "evaluate")  # once everything the evaluation reads is found good
    loader = make_loader(dataset, batch_size=cfg.loader.batch_size, num_workers=cfg.loader.num_workers,
                         graph=model.graph_spec, worker_nice=cfg.loader.worker_nice)
    metrics, evaluator = score_model(model, loader, device, backend=cfg.eval.backend,
                                     conf_threshold=cfg.eval.conf_threshold, nms_threshold=cfg.eval.nms_threshold)
    result = {**{key: metrics[key] for key in METRIC_KEYS}, "split": cfg.split, "num_images": len(evaluator.images),
              "checkpoint": str(cfg.ckpt), "data": data,
              "graph": None if detector.graph is None else detector.graph.as_dict(), "overrides": overrides}
    (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    (run_dir / "detections.json").write_text(json.dumps(evaluator.results_json()))
    if cfg.save_images:  # samples spread over the split, answered at the checkpoint's operating point
        chosen = spread_indices(len(dataset), int(cfg.save_images))
        pictures = make_loader(Subset(dataset, chosen), batch_size=cfg.loader.batch_size, num_workers=0,
                               graph=model.graph_spec)
        point = checkpoint.operating
        save_pictures(model, pictures, device, run_dir / "images", len(chosen), conf_threshold=point.score,
                      nms_threshold=point.nms_iou)
    print(f"{cfg.split} split, {len(evaluator.images)} images ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir)}
