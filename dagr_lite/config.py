"""Config handling: resolution and validation at start, and the builders from config to objects.

The YAML files under ``conf/`` are composed by Hydra; :func:`resolve_config` resolves every
interpolation at once (a missing value or a typo fails before any work), and the ``build_*``
functions are the only places that read config objects: everything else takes typed arguments.
"""
from __future__ import annotations

import os
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dagr_lite.data import format as fmt
from dagr_lite.data.augment import TrainAugment
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.nn.detector import Detector, DetectorConfig

# Model sizes: image CNN width, event branch channels (input stage, then strides 8, 16, 32), head width.
MODEL_SIZES = {
    "s": {"image_width": 16, "event_channels": (16, 32, 48, 64), "head_hidden": 64},
    "m": {"image_width": 24, "event_channels": (24, 48, 72, 96), "head_hidden": 96},
}

ROOT_ENV = "EVENTEGOHANDS_ROOT"


class ConfigError(ValueError):
    """The configuration is incomplete or inconsistent; the message names the key."""


def _eventegohands_root(version: str) -> str:
    base = os.environ.get(ROOT_ENV)
    if not base:
        raise ConfigError(f"dataset.root of {version} is not set: export {ROOT_ENV}=/path/to/eventegohands "
                          f"(the folder holding {version}/) or pass dataset.root=/path/to/{version}")
    return str(Path(base) / version)


OmegaConf.register_new_resolver("eventegohands_root", _eventegohands_root, replace=True)


def resolve_config(cfg: DictConfig) -> DictConfig:
    """Resolve every value of ``cfg`` now; raise :class:`ConfigError` naming what is missing or wrong."""
    try:
        container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except OmegaConfBaseException as err:
        cause = err
        while cause is not None and not isinstance(cause, ConfigError):
            cause = cause.__cause__ or cause.__context__
        raise ConfigError(str(cause) if cause else f"invalid configuration: {err}") from err
    resolved = OmegaConf.create(container)
    OmegaConf.set_struct(resolved, True)
    _check_dataset(resolved.dataset)
    return resolved


def _check_dataset(dataset: DictConfig) -> None:
    for key in ("height", "width"):
        value = dataset.get(key)
        if value is not None and (not isinstance(value, int) or value <= 0):
            raise ConfigError(f"dataset.{key} must be a positive integer or null, got {value!r}")
    if (dataset.get("height") is None) != (dataset.get("width") is None):
        raise ConfigError("dataset.height and dataset.width must be both set or both null, got "
                          f"{dataset.get('height')!r} and {dataset.get('width')!r}")
    if not dataset.get("fps") or dataset.fps <= 0:
        raise ConfigError(f"dataset.fps must be positive, got {dataset.get('fps')!r}")


def dataset_root(dataset: DictConfig) -> Path:
    """The dataset folder: ``dataset.root``, or for the stub dataset the (generated) cache copy."""
    if dataset.root is None:
        if dataset.name != "stub":
            raise ConfigError(f"dataset.root of {dataset.name} is null: pass dataset.root=/path/to/dataset")
        from dagr_lite.synth.stub import stub_root
        return stub_root()
    root = Path(dataset.root).expanduser()
    if not root.is_dir():
        raise ConfigError(f"dataset.root={root} of {dataset.name} is not a folder (expected a dataset holding "
                          f"{', '.join(fmt.SPLITS)} and {fmt.LABELS_FILE})")
    return root


def build_dataset(cfg: DictConfig, split: str, *, train: bool) -> EventEgoHands:
    """The dataset of one split, with augmentation when ``train`` and ``data.augment.enabled``."""
    data, dataset = cfg.data, cfg.dataset
    transform = None
    augment = data.get("augment")
    if train and augment is not None and augment.enabled:
        transform = TrainAugment(flip_prob=augment.flip_prob, zoom=tuple(augment.zoom),
                                 translate=augment.translate, min_box_size=augment.min_box_size)
    image_size = (dataset.height, dataset.width) if dataset.height is not None else None
    return EventEgoHands(dataset_root(dataset), split, image_lag=data.image_lag, window_us=data.window_us,
                         max_events=data.max_events, fps=dataset.fps, image_size=image_size,
                         transform=transform, clip_boxes=data.clip_boxes, seed=cfg.seed)


def build_model(cfg: DictConfig, *, height: int, width: int) -> Detector:
    """The detector of ``cfg.model`` for frames of ``height x width`` pixels."""
    model = cfg.model
    if model.size not in MODEL_SIZES:
        raise ConfigError(f"model.size must be one of {sorted(MODEL_SIZES)}, got {model.size!r}")
    return Detector(DetectorConfig(height=height, width=width, use_events=model.use_events, use_image=model.use_image,
                                   radius=model.radius, beta=model.beta, max_neighbors=model.max_neighbors,
                                   window_us=cfg.data.window_us, **MODEL_SIZES[model.size]))
