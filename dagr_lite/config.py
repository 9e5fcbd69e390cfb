"""Config handling: resolution and validation at start, and the builders from config to objects.

The YAML files under ``conf/`` are composed by Hydra; :func:`resolve_config` resolves every
interpolation at once (a missing value or a typo fails before any work), and the ``build_*``
functions are the only places that read config objects: everything else takes typed arguments.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.augment import TrainAugment, crop_size
from dagr_lite.data.dataset import RGB_CHANNELS, EventEgoHands, carry_channels
from dagr_lite.data.spec import increasing_positive_integers, is_integer
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.detector import IMAGE_STEMS, Detector, DetectorConfig

ROOT_ENV = "EVENTEGOHANDS_ROOT"
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


class ConfigError(UserError):
    """The configuration is incomplete or inconsistent; the message names the key."""


def _eventegohands_root(version: str) -> str:
    base = os.environ.get(ROOT_ENV)
    if not base:
        raise ConfigError(f"dataset.root of {version} is not set: export {ROOT_ENV}=/path/to/eventegohands "
                          f"(the folder holding {version}/) or pass dataset.root=/path/to/{version}")
    return str(Path(base) / version)


OmegaConf.register_new_resolver("eventegohands_root", _eventegohands_root, replace=True)
# data.carry_picture: whether the model has a carry branch (model.carry_width > 0), unless set.
OmegaConf.register_new_resolver("has_carry", lambda width: isinstance(width, int) and width > 0, replace=True)
# hydra.run.dir: the run's own run_dir when one is given, else a new dated folder.
OmegaConf.register_new_resolver("run_folder", lambda run_dir, default: run_dir if run_dir is not None
                                else torchrun_folder(default), replace=True)


def torchrun_folder(default: str) -> str:
    """Hydra's run folder: under torchrun, one name every process (and every restart of the group)
    agrees on, ``<runs/kind>/torchrun-<rendezvous id>``, instead of each process's own clock."""
    run_id = os.environ.get("TORCHELASTIC_RUN_ID", "")
    if int(os.environ.get("WORLD_SIZE", "1") or 1) <= 1 or not run_id:
        return default
    if run_id == "none":  # a static rendezvous: name it by its address
        run_id = f"{os.environ.get('MASTER_ADDR', 'local')}-{os.environ.get('MASTER_PORT', '0')}"
    return str(Path(*Path(default).parts[:2]) / f"torchrun-{run_id}")


def compose_config(name: str = "train", overrides: Sequence[str] = (), *, hydra: bool = False) -> DictConfig:
    """``conf/<name>.yaml`` composed with ``overrides``, as the command line would (for scripts and tests);
    ``hydra``: with Hydra's own node (``hydra.runtime.choices``: the option each group took)."""
    from hydra import compose, initialize_config_dir
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose(config_name=name, overrides=list(overrides), return_hydra_config=hydra)


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


def _integers(v, count: int, least: int) -> bool:
    return isinstance(v, (ListConfig, list, tuple)) and len(v) == count and all(is_integer(a) and a >= least for a in v)


def spans_of(data: DictConfig) -> tuple[int, ...]:
    """``data.carry_spans_us`` as a tuple (missing: none)."""
    return tuple(int(v) for v in (data.get("carry_spans_us") or ()))


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# key: (what it must be, test). Keys a config does not have are skipped.
_RULES = {
    "seed": ("an integer", is_integer),
    "data.image_age": ("an integer >= 0 (frames)", lambda v: is_integer(v) and v >= 0),
    "data.train_image_age": ("a range [low, high] of frames, 0 <= low <= high",
                             lambda v: isinstance(v, ListConfig) and len(v) == 2 and all(is_integer(a) for a in v)
                             and 0 <= v[0] <= v[1]),
    "data.train_image_age_power": ("a number >= 0 (0: ages drawn uniformly)", lambda v: _number(v) and v >= 0),
    "data.train_image_age_ramp": ("an integer >= 0 (frames an epoch; 0: the whole range from the start)",
                                  lambda v: is_integer(v) and v >= 0),
    "data.context_us": ("an integer >= 0 (microseconds)", lambda v: is_integer(v) and v >= 0),
    "data.augment.crop": ("a number in (0, 1] (a fraction of each side of the frame; 1: the whole frame)",
                          lambda v: _number(v) and 0 < v <= 1),
    "data.augment.crop_boxes": ("a number in [0, 1] (a probability)", lambda v: _number(v) and 0 <= v <= 1),
    "model.event_head_weight": ("a number >= 0 (0: no event head)", lambda v: _number(v) and v >= 0),
    "model.event_answers": ("true or false", lambda v: isinstance(v, bool)),
    "model.late_query": ("true or false", lambda v: isinstance(v, bool)),
    "model.carry_width": ("an integer >= 0 (0: no carry branch)", lambda v: is_integer(v) and v >= 0),
    "model.carry_frame": ("true or false", lambda v: isinstance(v, bool)),
    "model.event_dense": ("an integer >= 0 (pixels: the first stride, or that halved; 0: GCN pooled stages)",
                          lambda v: is_integer(v) and v >= 0),
    "model.carry_attend": ("an integer >= 0 (cells each way at stride 16; 0: none)", lambda v: is_integer(v) and v >= 0),
    "model.image_stem": (f"one of {', '.join(IMAGE_STEMS)}", lambda v: v in IMAGE_STEMS),
    "model.time_scale_us": ("a positive number (microseconds)", lambda v: _number(v) and v > 0),
    "data.window_us": ("a positive integer (microseconds)", lambda v: is_integer(v) and v > 0),
    "data.refractory_us": ("an integer >= 0 (microseconds; 0: every event)", lambda v: is_integer(v) and v >= 0),
    "data.support_us": ("an integer >= 0 (microseconds; 0: no background-activity filter)",
                        lambda v: is_integer(v) and v >= 0),
    "data.graph_context_us": ("an integer >= 0 (microseconds; 0: none)", lambda v: is_integer(v) and v >= 0),
    "data.event_picture": ("true or false", lambda v: isinstance(v, bool)),
    "data.carry_picture": ("true or false", lambda v: isinstance(v, bool)),
    "data.carry_recent_us": ("an integer >= 0 (microseconds; 0: no recent channel)", lambda v: is_integer(v) and v >= 0),
    "data.carry_confirm_us": ("an integer >= 0 (microseconds; 0: no confirmed channels)",
                              lambda v: is_integer(v) and v >= 0),
    "data.carry_align_us": ("an integer >= 0 (microseconds; 0: no moved frame)", lambda v: is_integer(v) and v >= 0),
    "data.carry_spans_us": ("a list of increasing positive integers (microseconds since the image; []: no spans)",
                            increasing_positive_integers),
    "data.carry_onset": ("true or false", lambda v: isinstance(v, bool)),
    "data.max_events": ("a positive integer or null", lambda v: v is None or (is_integer(v) and v > 0)),
    "loader.batch_size": ("a positive integer", lambda v: is_integer(v) and v > 0),
    "loader.num_workers": ("an integer >= 0", lambda v: is_integer(v) and v >= 0),
    "loader.worker_nice": ("an integer from 0 to 19 (a Unix nice increment)", lambda v: is_integer(v) and 0 <= v <= 19),
    "optim.lr": ("a positive number", lambda v: _number(v) and v > 0),
    "trainer.max_steps": ("a positive integer or null", lambda v: v is None or (is_integer(v) and v > 0)),
    "trainer.max_epochs": ("a positive integer or null", lambda v: v is None or (is_integer(v) and v > 0)),
    "trainer.max_minutes": ("a positive number or null", lambda v: v is None or (_number(v) and v > 0)),
    "trainer.schedule_by": ("steps or time", lambda v: v in ("steps", "time")),
    "trainer.events_first": ("a number in [0, 1) (a fraction of the schedule)", lambda v: _number(v) and 0 <= v < 1),
    "trainer.image_first": ("a number in [0, 1) (a fraction of the schedule)", lambda v: _number(v) and 0 <= v < 1),
    "trainer.dense_first": ("a number in [0, 1) (a fraction of the schedule)", lambda v: _number(v) and 0 <= v < 1),
    "trainer.val_every": ("an integer >= 0 (0: every epoch)", lambda v: is_integer(v) and v >= 0),
    "trainer.val_samples": ("a positive integer or null (every sample)", lambda v: v is None or (is_integer(v) and v > 0)),
    "trainer.log_every": ("a positive integer", lambda v: is_integer(v) and v > 0),
    "trainer.image_every": ("an integer >= 0 (0: never)", lambda v: is_integer(v) and v >= 0),
    "trainer.amp_dtype": ("one of auto, float16, bfloat16", lambda v: v in ("auto", "float16", "bfloat16")),
    "trainer.channels_last": ("auto, true or false", lambda v: v in ("auto", True, False)),
    "trainer.checkpoint_every": ("an integer >= 0 (0: only at validation)", lambda v: is_integer(v) and v >= 0),
    "trainer.checkpoint_minutes": ("a positive number or null", lambda v: v is None or (_number(v) and v > 0)),
    "trainer.warmup_steps": ("an integer >= 0", lambda v: is_integer(v) and v >= 0),
    "trainer.min_lr_ratio": ("a number in [0, 1]", lambda v: _number(v) and 0 <= v <= 1),
    "trainer.grad_clip": ("a positive number", lambda v: _number(v) and v > 0),
    "trainer.ema_decay": ("a number in [0, 1)", lambda v: _number(v) and 0 <= v < 1),
    "trainer.ema_tau": ("a positive number", lambda v: _number(v) and v > 0),
    "eval.conf_threshold": ("a number in [0, 1]", lambda v: _number(v) and 0 <= v <= 1),
    "eval.nms_threshold": ("a number in (0, 1]", lambda v: _number(v) and 0 < v <= 1),
    "save_images": ("an integer >= 0", lambda v: is_integer(v) and v >= 0),
    # detect and the demo
    "rate_hz": ("a positive number (answers per second of recording)", lambda v: _number(v) and v > 0),
    "seconds": ("a positive number of seconds or null (all of it)", lambda v: v is None or (_number(v) and v > 0)),
    "overwrite": ("true or false", lambda v: isinstance(v, bool)),
    "order": ("sort or refuse", lambda v: v in ("sort", "refuse")),
    "order_window_us": ("an integer >= 0 (microseconds)", lambda v: is_integer(v) and v >= 0),
    "operating.score": ("a number in [0, 1], or null (the checkpoint's)", lambda v: v is None or (_number(v) and 0 <= v <= 1)),
    "operating.nms_iou": ("a number in (0, 1], or null (the checkpoint's)", lambda v: v is None or (_number(v) and 0 < v <= 1)),
    "sensor.size": ("[width, height], two positive integers, or null", lambda v: v is None or _integers(v, 2, 1)),
    "sensor.crop": ("[x0, y0, width, height], four integers (x0, y0 >= 0; width, height > 0), or null",
                    lambda v: v is None or (_integers(v, 4, 0) and v[2] > 0 and v[3] > 0)),
    "sensor.rotate": ("one of 0, 90, 180, 270 (degrees clockwise)", lambda v: is_integer(v) and v in (0, 90, 180, 270)),
    "sensor.flip_x": ("true or false", lambda v: isinstance(v, bool)),
    "sensor.flip_y": ("true or false", lambda v: isinstance(v, bool)),
    "sensor.scale": ("a positive integer (pixels binned scale x scale)", lambda v: is_integer(v) and v > 0),
    "udp.max_backlog_mb": ("a positive number (megabytes)", lambda v: _number(v) and v > 0),
    "udp.idle_s": ("a positive number (seconds)", lambda v: _number(v) and v > 0),
    "udp.wait_first_s": ("a positive number (seconds)", lambda v: _number(v) and v > 0),
}
_ABSENT = object()


def check_values(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` naming the first key whose value is of the wrong type or range."""
    for key, (expected, ok) in _RULES.items():
        value = OmegaConf.select(cfg, key, default=_ABSENT)
        if value is not _ABSENT and not ok(value):
            raise ConfigError(f"{key} must be {expected}, got {value!r}")
    if cfg.get("init_from") is not None and cfg.get("resume") is not None:
        raise ConfigError(f"init_from={cfg.init_from} starts a new run from other weights, and resume={cfg.resume} "
                          "continues a run from its own: give one of them")
    trainer = cfg.get("trainer")
    unknown = sorted(set(trainer) - {*TRAINER_KEYS, *FIRST_PHASES}) if trainer is not None else []
    if unknown:
        raise ConfigError(f"trainer.{unknown[0]} is not a training setting; the trainer reads "
                          f"{', '.join(sorted({*TRAINER_KEYS, *FIRST_PHASES}))}")
    if trainer is not None and trainer.max_steps is None and trainer.max_epochs is None:
        raise ConfigError("set trainer.max_steps or trainer.max_epochs (both are null)")
    if trainer is not None and trainer.get("schedule_by") == "time" and trainer.max_minutes is None:
        raise ConfigError("trainer.schedule_by=time needs the time budget trainer.max_minutes (it is null); "
                          "give trainer.schedule_by=steps to train by steps alone")


def dataset_root(dataset: DictConfig) -> Path:
    """The dataset folder: ``dataset.root``, or for a built-in dataset (stub, ego) the (generated) cache copy."""
    if dataset.root is None:
        if dataset.name == "stub":
            from dagr_lite.synth.stub import stub_root
            return stub_root()
        if dataset.name == "ego":
            from dagr_lite.synth.ego import ego_root
            return ego_root()
        raise ConfigError(f"dataset.root of {dataset.name} is null: pass dataset.root=/path/to/dataset")
    root = Path(dataset.root).expanduser()
    if not root.is_dir():
        raise ConfigError(f"dataset.root={root} of {dataset.name} is not a folder (expected a dataset holding "
                          f"{', '.join(fmt.SPLITS)} and {fmt.LABELS_FILE})")
    return root


def build_dataset(cfg: DictConfig, split: str, *, train: bool, with_image: bool,
                  image_age: int | None = None, first_frame: int | None = None) -> EventEgoHands:
    """The dataset of one split for a model with or without an image branch.

    Training draws each sample's image age from ``data.train_image_age`` and augments (when
    ``data.augment.enabled``; images are dropped for grey only in a hybrid); otherwise the age
    is ``image_age`` (default ``data.image_age``).
    Every model reads the events of the last ``data.window_us``; one with an image none from
    before ``image time - data.context_us`` (:func:`~dagr_lite.data.spec.sample_start_us`).
    """
    data, dataset = cfg.data, cfg.dataset
    hybrid = with_image and bool(OmegaConf.select(cfg, "model.use_events", default=False))
    if image_age is None:
        image_age = tuple(data.train_image_age) if train else data.image_age
    transform = None
    augment = data.get("augment")
    if train and augment is not None and augment.enabled:
        transform = TrainAugment(flip_prob=augment.flip_prob, zoom=tuple(augment.zoom),
                                 translate=augment.translate, min_box_size=augment.min_box_size,
                                 image_dropout=augment.image_dropout if hybrid else 0.0,
                                 event_drop=augment.event_drop, crop=training_crop(cfg),
                                 crop_multiple=max(cfg.model.strides), crop_boxes=float(augment.get("crop_boxes", 0.0)))
    image_size = (dataset.height, dataset.width) if dataset.height is not None else None
    picture = bool(data.get("event_picture", False))
    built = EventEgoHands(dataset_root(dataset), split, image_age=image_age,
                          event_span="image" if with_image and not picture else "window", window_us=data.window_us,
                          context_us=data.context_us, refractory_us=data.refractory_us, max_events=data.max_events,
                          support_us=data.support_us,
                          graph_context_us=data.graph_context_us,
                          first_frame=first_frame,
                          fps=dataset.fps, image_size=image_size, transform=transform,
                          clip_boxes=data.clip_boxes, labelled_only=bool(data.get("labelled_only", False)),
                          seed=cfg.seed, age_power=data.train_image_age_power if train else 0.0,
                          age_ramp=int(data.get("train_image_age_ramp", 0)) if train else 0,
                          event_picture=picture, carry_picture=bool(data.get("carry_picture", False)),
                          carry_recent_us=int(data.get("carry_recent_us", 0)),
                          carry_confirm_us=int(data.get("carry_confirm_us", 0)),
                          carry_align_us=int(data.get("carry_align_us", 0)),
                          carry_spans_us=spans_of(data), carry_onset=data.get("carry_onset", False),
                          frames=with_image or not train)  # a frameless model's training skips the frames
    if not len(built) and built.videos and first_frame is None:  # (the sweep says its own)
        lengths = [built.num_frames(v) for v in range(len(built.videos))]
        raise ConfigError(f"{built.root} [{split}]: no sample at image age {image_age}: its videos have "
                          f"{min(lengths)} to {max(lengths)} frames (a sample needs the image age's frames before "
                          "its label frame)")
    return built


def training_crop(cfg: DictConfig) -> float:
    """``data.augment.crop``: the fraction of each side of the frame a training sample is cut to
    (1 when augmentation is off or the key is absent, as in configs saved before it)."""
    augment = cfg.data.get("augment")
    if augment is None or not augment.enabled:
        return 1.0
    return float(augment.get("crop", 1.0))


def training_size(cfg: DictConfig, image_size: tuple[int, int]) -> tuple[int, int]:
    """``(height, width)`` the model trains at on ``image_size`` frames: the frame's, or with
    ``data.augment.crop < 1`` the crop's (a multiple of the head's largest stride,
    :func:`~dagr_lite.data.augment.crop_size`). Validation, evaluation and checkpoints use the frame's."""
    return crop_size(int(image_size[0]), int(image_size[1]), training_crop(cfg), max(cfg.model.strides))


def graph_spec(model: DictConfig) -> EventGraphSpec | None:
    """The event-graph settings of ``model.graph`` (None for a model without an event branch)."""
    if not model.use_events:
        return None
    try:
        return EventGraphSpec(radius=model.graph.radius, beta=model.graph.beta,
                              max_neighbors=model.graph.max_neighbors)
    except ValueError as err:
        raise ConfigError(f"model.{err}") from err


def detector_config(cfg: DictConfig, *, height: int, width: int) -> DetectorConfig:
    """The architecture of ``cfg.model`` (size chosen from ``model.sizes``) for ``height x width`` frames."""
    model = cfg.model
    if model.size not in model.sizes:
        raise ConfigError(f"model.size must be one of {sorted(model.sizes)}, got {model.size!r}")
    size = model.sizes[model.size]
    picture, carry = bool(cfg.data.get("carry_picture", False)), int(model.carry_width)
    channels = carry_channels(int(cfg.data.get("carry_recent_us", 0)) if picture else 0,  # the carry picture's
                              int(cfg.data.get("carry_confirm_us", 0)) if picture else 0,
                              int(cfg.data.get("carry_align_us", 0)) if picture else 0,
                              spans_of(cfg.data) if picture else (),
                              bool(cfg.data.get("carry_onset", False)) if picture else False)
    if carry and not picture:
        raise ConfigError(f"model.carry_width={carry} reads the picture of the events since the image: it needs "
                          "data.carry_picture=true")
    return DetectorConfig(height=height, width=width, use_events=model.use_events, use_image=model.use_image,
                          image_width=size.image_width, event_channels=tuple(size.event_channels),
                          event_blocks=model.event_blocks, fuse_channels=model.fuse_channels,
                          head_hidden=size.head_hidden, num_classes=model.num_classes,
                          strides=tuple(model.strides), graph=graph_spec(model), time_scale_us=model.time_scale_us,
                          recency_us=tuple(model.recency_us), event_head_weight=float(model.event_head_weight),
                          event_answers=(bool(model.get("event_answers", False)) and model.use_image
                                         and model.use_events),
                          image_stem=model.image_stem, late_query=bool(model.late_query),
                          geometry=bool(model.geometry), directional=bool(model.directional),
                          image_channels=RGB_CHANNELS + (channels if picture and not carry else 0),
                          carry_width=carry, carry_channels=channels,
                          carry_frame=bool(model.get("carry_frame", False)) and bool(carry),
                          carry_attend=int(model.get("carry_attend", 0)) if carry else 0,
                          event_dense=int(model.get("event_dense", 0)))


def build_model(cfg: DictConfig, *, height: int, width: int) -> Detector:
    """The detector of ``cfg.model`` for frames of ``height x width`` pixels."""
    try:
        return Detector(detector_config(cfg, height=height, width=width))
    except ValueError as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"model: {err}") from err


def build_optimizer(cfg: DictConfig, parameters) -> torch.optim.Optimizer:
    """The optimiser of ``cfg.optim`` (a ``_target_`` with ``_partial_: true``) over ``parameters``."""
    try:
        return instantiate(cfg.optim, _convert_="all")(parameters)
    except Exception as err:  # instantiation wraps the optimiser's own errors
        raise ConfigError(f"optim: cannot build {cfg.optim.get('_target_')!r}: {err}") from err


@dataclass(frozen=True)
class TrainerSettings:
    """What the training loop reads, built from ``trainer.*``, ``eval.*`` and ``data.image_age`` by
    :func:`trainer_settings` (each field is the config key of the same name, ``conf/train.yaml``)."""
    max_steps: int | None
    max_epochs: int | None
    max_minutes: float | None
    schedule_by: str
    events_first: float  # 0 for a model with one branch and for a run started from init_from
    image_first: float  # likewise
    dense_first: float  # likewise
    val_every: int
    val_samples: int | None
    log_every: int
    image_every: int
    checkpoint_every: int
    checkpoint_minutes: float | None
    warmup_steps: int
    min_lr_ratio: float
    grad_clip: float | None
    ema_decay: float
    ema_tau: float
    amp: bool
    amp_dtype: str
    channels_last: str | bool  # auto (on a CPU), true or false
    image_age: int  # data.image_age: the validation age whose metrics the run reports
    eval_backend: str  # eval.backend, eval.conf_threshold, eval.nms_threshold: how validation scores
    conf_threshold: float
    nms_threshold: float

    @property
    def by_time(self) -> bool:
        return self.schedule_by == "time"

    @property
    def first_phase(self) -> str | None:
        """The first phase the run has (``events_first``, ``image_first`` or ``dense_first``), or None."""
        return next((key for key in FIRST_PHASES if getattr(self, key)), None)

    def total_steps(self, steps_per_epoch: int) -> int:
        """The schedule's length: ``max_steps``, or ``max_epochs`` epochs."""
        return int(self.max_steps) if self.max_steps is not None else int(self.max_epochs) * steps_per_epoch


# The keys of conf/train.yaml's trainer section (the first phases besides): a key given with + that the
# loop does not read is refused rather than ignored.
FIRST_PHASES = ("events_first", "image_first", "dense_first")
# What each first phase leaves out of a training step (``engine.state.train_step``'s flags in the phase).
PHASE_STEP = {"events_first": {"image": False}, "image_first": {"events": False}, "dense_first": {"graph": False}}
TRAINER_KEYS = ("max_steps", "max_epochs", "max_minutes", "schedule_by", "val_every", "val_samples", "log_every", "image_every",
                "checkpoint_every", "checkpoint_minutes", "warmup_steps", "min_lr_ratio", "grad_clip", "ema_decay",
                "ema_tau", "amp", "amp_dtype", "channels_last")


def trainer_settings(cfg: DictConfig) -> TrainerSettings:
    """The training loop's settings from a checked config (:func:`check_values`)."""
    trainer = cfg.trainer
    hybrid = bool(cfg.model.use_events and cfg.model.use_image)
    first = {key: float(trainer.get(key, 0.0) or 0.0) if hybrid and cfg.get("init_from") is None else 0.0
             for key in FIRST_PHASES}
    set_ = [f"trainer.{key}={value}" for key, value in first.items() if value]
    if len(set_) > 1:
        raise ConfigError(f"{' and '.join(set_)}: a run has one first phase, not two; set all but one to 0")
    if first["image_first"] and (cfg.model.late_query or float(cfg.model.event_head_weight) > 0):
        raise ConfigError(f"trainer.image_first={first['image_first']} needs model.late_query=false and "
                          f"model.event_head_weight=0 (got {cfg.model.late_query} and {cfg.model.event_head_weight}): "
                          "the events must reach the output through the fusion alone")
    if first["events_first"] and cfg.data.get("carry_picture", False) and int(cfg.data.get("carry_align_us", 0)):
        raise ConfigError(f"trainer.events_first={first['events_first']} hides the image from the model, but "
                          f"data.carry_align_us={cfg.data.carry_align_us} shows the carry branch the frame moved by "
                          "the camera's motion: set one of them to 0")
    if first["dense_first"] and float(cfg.model.event_head_weight) > 0:
        raise ConfigError(f"trainer.dense_first={first['dense_first']} needs model.event_head_weight=0 (got "
                          f"{cfg.model.event_head_weight}): the event graph must reach the output through the fusion alone")
    return TrainerSettings(**{key: trainer[key] for key in TRAINER_KEYS}, **first,
                           image_age=int(cfg.data.image_age), eval_backend=cfg.eval.backend,
                           conf_threshold=float(cfg.eval.conf_threshold), nms_threshold=float(cfg.eval.nms_threshold))


def budget_overrides(minutes: float, steps: int | None = None) -> list[str]:
    """Config overrides that train for ``minutes`` of wall time, or ``steps`` steps if given
    (still capped by the minutes): what the tools that train to a time budget pass. The learning
    rate's cosine follows whichever of the two budgets is further along, so it ends decayed."""
    length = [f"trainer.max_steps={steps}"] if steps else ["trainer.max_steps=null", "trainer.max_epochs=100000"]
    return [f"trainer.max_minutes={minutes}", "trainer.schedule_by=time", *length]

