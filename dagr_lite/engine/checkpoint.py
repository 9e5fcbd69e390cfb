"""Checkpoints: saving and loading them, the model a checkpoint describes, what one of its samples
is, and a description of a run's data. The engine, the streaming detector, the sweep and
labelling all read checkpoints through here."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, ListConfig

from dagr_lite.errors import UserError
from dagr_lite.config import ConfigError
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.data.spec import SampleSpec
from dagr_lite.data.writer import temporary_name
from dagr_lite.engine.state import STATE_KEYS
from dagr_lite.eval.operating import UNMEASURED, OperatingPoint
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.detector import Detector, DetectorConfig

CHECKPOINT_FORMAT = 2


def save_checkpoint(path: Path, state: dict) -> None:
    """``torch.save`` to a temporary name, then rename: a checkpoint on disk is always whole. A
    write that fails (disk full, file size limit) raises :class:`OSError` naming ``path`` and
    the cause, removes the temporary file and leaves an earlier checkpoint at ``path`` as it was."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError) as err:  # torch reports a failed write as a RuntimeError
        tmp.unlink(missing_ok=True)
        kept = f"; the earlier {path.name} is kept as it was" if path.exists() else ""
        raise OSError(f"{path}: the checkpoint could not be written ({err}){kept}") from err


def load_failure(err: Exception) -> str:
    """What ``torch.load(weights_only=True)`` found wrong, without its advice to load the file unsafely
    (``weights_only=False``) and to file an issue: the reason its safe unpickler gives, else its first line."""
    text = str(err)
    if "Weights only load failed" in text:
        reason = text.split("WeightsUnpickler error:", 1)[1] if "WeightsUnpickler error:" in text else ""
        reason = next((line.strip() for line in reason.splitlines() if line.strip()), "")
        reason = reason.split(". Please use", 1)[0]  # torch's advice to allow a class it refused
        return f"not a file of tensors and plain values, as train.py writes{': ' + reason if reason else ''}"
    return text.strip().splitlines()[0] if text.strip() else type(err).__name__


def load_checkpoint(path: Path | str) -> "Checkpoint":
    """Read a checkpoint safely (``weights_only``): the one place a checkpoint's raw contents are
    read, and where an older one is upgraded (:func:`upgrade`). A missing, foreign or unreadable
    file is an error naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint file is missing")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling errors come in many types
        raise UserError(f"{path}: cannot read as a dagr_lite checkpoint ({load_failure(err)})") from err
    if not isinstance(state, dict) or "model" not in state:
        raise UserError(f"{path}: not a dagr_lite checkpoint (expected keys format, model, ema, detector, config, ...)")
    if state.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: a checkpoint of format {state.get('format')}, but this dagr_lite reads format "
                         f"{CHECKPOINT_FORMAT} (it records the model's architecture and event graph); "
                         "train the model again with this version")
    state = upgrade(state)
    try:
        detector = DetectorConfig.from_dict(state["detector"])
        data = state["config"]["data"]
        sample, image_age = SampleSpec.from_dict(data), int(data["image_age"])
        operating = OperatingPoint.from_dict(state["operating"])
        weights = state["ema"]["module"] if state.get("ema") else state["model"]
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(f"{path}: its model, sample or operating point cannot be read ({err})") from err
    training = {key: state[key] for key in (*STATE_KEYS, "position", "world_size", "global_batch_size") if key in state}
    return Checkpoint(path=path, detector=detector, sample=sample, image_age=image_age, operating=operating,
                      config=state["config"], weights=weights, training=training)


# Keys newer than some checkpoints of this format, with the values that give those checkpoints'
# models and samples: an older checkpoint is read as what it was trained as.
DETECTOR_ADDED_LATER = {"event_head_weight": 0.0, "event_answers": False, "image_stem": "conv", "late_query": False,
                        "geometry": False, "directional": False, "image_channels": 3,
                        "carry_width": 0, "carry_channels": 3,
                        "carry_frame": False, "carry_attend": 0, "event_dense": 0}
SAMPLE_ADDED_LATER = {"refractory_us": 0, "event_picture": False, "graph_context_us": 0, "carry_picture": False,
                      "carry_recent_us": 0, "support_us": 0, "carry_confirm_us": 0,
                      "carry_align_us": 0, "carry_spans_us": [], "carry_onset": False}


def upgrade(state: dict) -> dict:
    """A raw checkpoint of this format with every key added since filled in: the detector's and
    the sample's at the values it was trained with, an operating point (:data:`UNMEASURED`) when
    it was trained before points were chosen."""
    state = dict(state)
    if isinstance(state.get("detector"), dict):
        state["detector"] = upgraded_detector(state["detector"])
    config = state.get("config")
    if isinstance(config, dict) and isinstance(config.get("data"), dict):
        state["config"] = {**config, "data": {**SAMPLE_ADDED_LATER, **config["data"]}}
    if state.get("operating") is None:
        state["operating"] = UNMEASURED.as_dict()
    return state


def upgraded_detector(values: dict) -> dict:
    """A saved detector config with the keys added since at the values that rebuild its model."""
    return {**DETECTOR_ADDED_LATER, **values}


@dataclass(frozen=True)
class Checkpoint:
    """A training checkpoint, read (:func:`load_checkpoint`).

    Attributes:
        path: the file it was read from.
        detector: the model's architecture and event graph; ``sample``: what one sample's events
            are; ``image_age``: the image age it was validated at first (evaluation's default).
        operating: the score threshold and NMS IoU a deployed detector answers with.
        config: the training run's resolved config (read-only: the model's name, the recipe).
        weights: the EMA weights, the ones validated and deployed.
        training: what resuming needs: the training state (:class:`~dagr_lite.engine.state.TrainState`),
            ``position`` in the data, ``world_size`` and ``global_batch_size``.
    """

    path: Path
    detector: DetectorConfig
    sample: SampleSpec
    image_age: int
    operating: OperatingPoint
    config: dict
    weights: dict
    training: dict

    @property
    def model_name(self) -> str:
        return str((self.config.get("model") or {}).get("name", "a model"))

    @property
    def sample_settings(self) -> dict:
        """The data settings of its sample: ``image_age`` and every :class:`SampleSpec` key."""
        return {"image_age": self.image_age, **self.sample.as_dict()}

    def model(self, detector: DetectorConfig | None = None) -> Detector:
        """Its detector (or ``detector``, e.g. at another input size) with its EMA weights."""
        model = Detector(detector or self.detector)
        try:
            model.load_state_dict(self.weights)
        except RuntimeError as err:
            raise UserError(f"{self.path}: its weights do not fit the model its config describes ({err})") from err
        return model


def override(section: str, key: str, trained, given, overrides: dict):
    """``given`` when set (recorded in ``overrides`` when it differs), else ``trained``."""
    if given is None:
        return trained
    given = as_plain(given)
    if given != as_plain(trained):
        overrides[f"{section}.{key}"] = {"checkpoint": as_plain(trained), "used": given}
    return given


# The keys that say which channels a model's input picture has (a picture in place of the frame, a
# carry picture, and each of the carry picture's optional windows): an evaluation may change a
# window's length, never whether the model's input holds it.
PICTURE_KEYS = ("event_picture", "carry_picture")
CARRY_WINDOW_KEYS = ("carry_recent_us", "carry_confirm_us", "carry_align_us")
CARRY_FIXED_KEYS = ("carry_spans_us", "carry_onset")  # the carry picture's spans and onset: as trained, or refused


def check_picture_layout(path, trained: dict, used: dict) -> None:
    """Refuse (:class:`~dagr_lite.errors.ConfigError`) data settings ``used`` (values already
    checked) whose pictures hold other channels than those the checkpoint at ``path`` was
    ``trained`` with: the weights read each channel as what it was in training, and two layouts of
    one count (a carry picture's confirmed channels or its moved frame) would pass a check of the
    count alone."""
    for key in PICTURE_KEYS:
        if bool(used[key]) != bool(trained[key]):
            raise ConfigError(f"{path}: data.{key}={used[key]} changes the model's input (it was trained with "
                              f"data.{key}={trained[key]}); leave it null (the checkpoint's)")
    if not trained["carry_picture"]:
        return
    for key in CARRY_WINDOW_KEYS:
        if (used[key] > 0) != (trained[key] > 0):
            raise ConfigError(f"{path}: data.{key}={used[key]} {'adds' if used[key] > 0 else 'removes'} carry "
                              f"picture channels the model was not trained with (data.{key}={trained[key]}): an "
                              "evaluation may change a window's length, not whether the picture holds it")
    for key in CARRY_FIXED_KEYS:
        if as_plain(used[key]) != as_plain(trained[key]):
            raise ConfigError(f"{path}: data.{key}={as_plain(used[key])} changes what the carry picture's channels "
                              f"hold (the model was trained with data.{key}={as_plain(trained[key])}); leave it null "
                              "(the checkpoint's)")


def as_plain(value):
    """A setting as a plain value to compare and print: a list, tuple or list config as a list."""
    return list(value) if isinstance(value, (list, tuple, ListConfig)) else value


def settings(cfg: DictConfig, checkpoint: "Checkpoint") -> tuple[dict, DetectorConfig, dict]:
    """The data settings, the detector and the overrides of an evaluation of ``checkpoint``."""
    detector = checkpoint.detector
    overrides: dict = {}
    data = {key: override("data", key, trained, cfg.data[key], overrides)
            for key, trained in checkpoint.sample_settings.items()}
    given_graph = {key: value for key, value in cfg.graph.items() if value is not None}
    if given_graph and detector.graph is None:
        raise ConfigError(f"{cfg.ckpt}: graph.{next(iter(given_graph))}={next(iter(given_graph.values()))!r} "
                          "was given, but the checkpoint's model has no event branch (use_events false)")
    graph = detector.graph
    if graph is not None:
        values = {key: override("graph", key, trained, cfg.graph[key], overrides)
                  for key, trained in graph.as_dict().items()}
        try:
            graph = EventGraphSpec(**values)
        except ValueError as err:
            raise ConfigError(str(err)) from err
    return data, dataclasses.replace(detector, graph=graph), overrides


def load_model(checkpoint: Checkpoint, detector: DetectorConfig, image_size: tuple[int, int]) -> Detector:
    """The checkpoint's EMA weights in ``detector``; frames of another size are refused."""
    if (detector.height, detector.width) != tuple(image_size):
        raise ConfigError(f"{checkpoint.path}: the model was trained on {detector.width}x{detector.height} frames, "
                          f"but the dataset's frames are {image_size[1]}x{image_size[0]}; evaluate it on data of its "
                          "size, or give model_size=data to run its weights at the data's size")
    return checkpoint.model(detector)


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


def describe_dataset(dataset: EventEgoHands, *, image: bool = True, events: bool = True) -> str:
    """One line on what a split holds and what a model reads of it: with an ``image``, the image's age
    (or, for a picture of the events, its horizon); with ``events``, the horizon (and, beside an
    image, how far before it the events may start); with a carry picture, that it is read."""
    height, width = dataset.image_size
    line = f"{dataset.root} [{dataset.split}]: {len(dataset.videos)} videos, {len(dataset)} samples, {width}x{height} px"
    if image and dataset.event_picture:  # the dense peer: its image is a picture of the horizon's events
        line += f", the image a picture of the events of the last {dataset.window_us} us"
    elif image:
        line += f", image age {describe_age(dataset.age_range, dataset.age_power, dataset.age_ramp)} frames"
    if events:
        line += f", events of the last {dataset.window_us} us"
        if image and dataset.event_span == "image":
            line += f" (none from before the image - {dataset.context_us} us)"
    if image and dataset.carry_picture:
        line += ", a picture of every event since the image"
    return line


def describe_age(ages: tuple[int, int], power: float = 0.0, ramp: int = 0) -> str:
    if ages[0] == ages[1]:
        return str(ages[0])
    return (f"{ages[0]}-{ages[1]}" + (f" (weights (a - {ages[0] - 1})^{power:g})" if power else "")
            + (f" (the longest growing {ramp} an epoch)" if ramp else ""))
