"""The evaluation entry: ``evaluate(cfg)`` is what ``python evaluate.py`` runs and what tests call.

The checkpoint defines the model (its architecture and event graph) and what one sample is
(image age, event window and context, event cap). A value given in ``data.*`` or ``graph.*`` overrides the
checkpoint's: it is printed as an override and recorded in ``metrics.json``, beside the data and
graph settings the evaluation actually used.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dagr_lite.config import ConfigError, build_dataset, check_values, resolve_config
from dagr_lite.engine.common import load_checkpoint, make_loader, resolve_device, run_folder
from dagr_lite.engine.train import describe_dataset
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics
from dagr_lite.eval.score import save_pictures, score_model
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.detector import Detector, DetectorConfig

# The data settings that define a model's input: taken from the checkpoint unless overridden.
SAMPLE_KEYS = ("image_age", "window_us", "context_us", "refractory_us", "max_events")
# Sample keys newer than some checkpoints, with the value that gives those checkpoints' samples.
SAMPLE_ADDED_LATER = {"refractory_us": 0}


def trained_sample(state: dict) -> dict:
    """The sample settings a checkpoint was trained with (keys added later at their old value)."""
    return {**SAMPLE_ADDED_LATER, **{key: state["config"]["data"][key] for key in SAMPLE_KEYS
                                     if key in state["config"]["data"]}}


def _override(section: str, key: str, trained, given, overrides: dict):
    """``given`` when set (recorded in ``overrides`` when it differs), else ``trained``."""
    if given is None:
        return trained
    if given != trained:
        overrides[f"{section}.{key}"] = {"checkpoint": trained, "used": given}
    return given


def settings(cfg: DictConfig, state: dict) -> tuple[dict, DetectorConfig, dict]:
    """The data settings, the detector and the overrides of an evaluation of checkpoint ``state``."""
    trained_data = trained_sample(state)
    detector = DetectorConfig.from_dict(state["detector"])
    overrides: dict = {}
    data = {key: _override("data", key, trained_data[key], cfg.data[key], overrides) for key in SAMPLE_KEYS}
    given_graph = {key: value for key, value in cfg.graph.items() if value is not None}
    if given_graph and detector.graph is None:
        raise ConfigError(f"{cfg.ckpt}: graph.{next(iter(given_graph))}={next(iter(given_graph.values()))!r} "
                          "was given, but the checkpoint's model has no event branch (use_events false)")
    graph = detector.graph
    if graph is not None:
        values = {key: _override("graph", key, trained, cfg.graph[key], overrides)
                  for key, trained in graph.as_dict().items()}
        try:
            graph = EventGraphSpec(**values)
        except ValueError as err:
            raise ConfigError(str(err)) from err
    return data, dataclasses.replace(detector, graph=graph), overrides


def load_model(state: dict, detector: DetectorConfig, image_size: tuple[int, int], ckpt: str) -> Detector:
    """The checkpoint's EMA weights in the detector it describes; frames of another size are refused."""
    if (detector.height, detector.width) != tuple(image_size):
        raise ConfigError(f"{ckpt}: the model was trained on {detector.width}x{detector.height} frames, but the "
                          f"dataset's frames are {image_size[1]}x{image_size[0]}; evaluate it on data of its size, "
                          "or give model_size=data to run its weights at the data's size")
    model = Detector(detector)
    try:
        model.load_state_dict(state["ema"]["module"])
    except RuntimeError as err:
        raise ValueError(f"{ckpt}: its weights do not fit the model its config describes ({err})") from err
    return model


MODEL_SIZES = ("checkpoint", "data")


def at_model_size(model_size: str, detector: DetectorConfig, image_size: tuple[int, int],
                  overrides: dict) -> DetectorConfig:
    """The detector at the size it was trained at (``checkpoint``) or at the dataset's frame size
    (``data``: the weights do not depend on the input size; what ``detect``'s
    ``sensor.model_size=sensor`` runs), the change recorded in ``overrides``."""
    height, width = image_size
    if model_size == "checkpoint" or (detector.height, detector.width) == (height, width):
        return detector
    overrides["model_size"] = {"checkpoint": [detector.width, detector.height], "used": [width, height]}
    return dataclasses.replace(detector, width=int(width), height=int(height))


def evaluate(cfg: DictConfig) -> dict:
    """Score a checkpoint's EMA weights on ``cfg.split``; writes ``metrics.json`` and ``detections.json``."""
    cfg = resolve_config(cfg)
    state = load_checkpoint(cfg.ckpt)
    data, detector, overrides = settings(cfg, state)
    cfg = OmegaConf.merge(cfg, {"data": data})
    check_values(cfg)
    if cfg.model_size not in MODEL_SIZES:
        raise ConfigError(f"model_size={cfg.model_size!r}: expected one of {MODEL_SIZES}")
    print(OmegaConf.to_yaml(cfg), flush=True)
    for key, change in overrides.items():
        print(f"override: {key}={change['used']!r} (the checkpoint was trained with {change['checkpoint']!r})")
    run_dir = run_folder(cfg, "evaluate")
    device = resolve_device(cfg.device)
    dataset = build_dataset(cfg, cfg.split, train=False, with_image=detector.use_image)
    print(describe_dataset(dataset), flush=True)
    detector = at_model_size(cfg.model_size, detector, dataset.image_size, overrides)
    model = load_model(state, detector, dataset.image_size, cfg.ckpt).to(device)
    loader = make_loader(dataset, batch_size=cfg.loader.batch_size, num_workers=cfg.loader.num_workers,
                         graph=model.graph_spec, worker_nice=cfg.loader.worker_nice)
    metrics, evaluator = score_model(model, loader, device, backend=cfg.eval.backend,
                                     conf_threshold=cfg.eval.conf_threshold, nms_threshold=cfg.eval.nms_threshold)
    result = {**{key: metrics[key] for key in METRIC_KEYS}, "split": cfg.split, "num_images": len(evaluator.images),
              "checkpoint": str(cfg.ckpt), "data": data,
              "graph": None if detector.graph is None else detector.graph.as_dict(), "overrides": overrides}
    (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    (run_dir / "detections.json").write_text(json.dumps(evaluator.results_json()))
    if cfg.save_images:
        save_pictures(model, loader, device, run_dir / "images", cfg.save_images)
    print(f"{cfg.split} split, {len(evaluator.images)} images ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir)}
