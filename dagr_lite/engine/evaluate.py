"""The evaluation entry: ``evaluate(cfg)`` is what ``python evaluate.py`` runs and what tests call."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from dagr_lite.config import build_dataset, build_model, resolve_config
from dagr_lite.engine.common import load_checkpoint, make_loader, resolve_device, run_folder
from dagr_lite.engine.train import _graph_options, describe_dataset
from dagr_lite.engine.validate import evaluate_model, render_sample
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics


def evaluate(cfg: DictConfig) -> dict:
    """Score a checkpoint's EMA weights on ``cfg.split``; writes ``metrics.json`` and ``detections.json``."""
    cfg = resolve_config(cfg)
    print(OmegaConf.to_yaml(cfg), flush=True)
    state = load_checkpoint(cfg.ckpt)
    trained = OmegaConf.create(state["config"])
    if "model" not in trained or "data" not in trained:
        raise ValueError(f"{cfg.ckpt}: the checkpoint's config has no model or data section")
    run_dir = run_folder(cfg, "evaluate")
    device = resolve_device(cfg.device)
    dataset = build_dataset(cfg, cfg.split, train=False)
    print(describe_dataset(dataset), flush=True)
    height, width = dataset.image_size
    model_cfg = OmegaConf.merge(trained, {"data": {"window_us": cfg.data.window_us}})
    model = build_model(model_cfg, height=height, width=width)
    try:
        model.load_state_dict(state["ema"]["module"])
    except RuntimeError as err:
        raise ValueError(f"{cfg.ckpt}: its weights do not fit the model its config describes ({err})") from err
    model.to(device)
    loader = make_loader(dataset, batch_size=cfg.loader.batch_size, num_workers=cfg.loader.num_workers,
                         graph=_graph_options(model_cfg))
    metrics, evaluator = evaluate_model(model, loader, device, backend=cfg.eval.backend,
                                        conf_threshold=cfg.eval.conf_threshold, nms_threshold=cfg.eval.nms_threshold)
    result = {**{key: metrics[key] for key in METRIC_KEYS}, "split": cfg.split, "num_images": len(evaluator.images),
              "checkpoint": str(cfg.ckpt)}
    (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    (run_dir / "detections.json").write_text(json.dumps(evaluator.results_json()))
    if cfg.save_images:
        save_pictures(model, loader, device, run_dir / "images", cfg.save_images)
    print(f"{cfg.split} split, {len(evaluator.images)} images ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir)}


def save_pictures(model, loader, device, folder: Path, count: int) -> None:
    """PNGs of the first ``count`` samples with true (green) and predicted (red) boxes."""
    import torch

    folder.mkdir(parents=True, exist_ok=True)
    model.eval()
    saved = 0
    with torch.no_grad():
        for batch in loader:
            batch = batch.to(device)
            detections = model(batch)
            for b in range(len(batch)):
                if saved >= count:
                    return
                picture = render_sample(batch, b, detections[b])
                Image.fromarray(np.ascontiguousarray(picture)).save(
                    folder / f"{batch.videos[b]}_frame_{int(batch.frames[b])}.png")
                saved += 1
