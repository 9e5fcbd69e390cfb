"""The training entry: ``train(cfg)`` is what ``python train.py`` runs and what tests call.

It builds the datasets and loaders (:mod:`~dagr_lite.engine.loop`), the model (which owns the
event-graph spec the loaders build graphs with) and the :class:`~dagr_lite.engine.state.TrainState`,
starts it where the run starts (:mod:`~dagr_lite.engine.starting`), and runs the
:class:`~dagr_lite.engine.loop.TrainLoop`.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch.nn.parallel import DistributedDataParallel
from torch.utils.tensorboard import SummaryWriter

from dagr_lite.config import (PHASE_STEP, TrainerSettings, build_dataset, build_model, build_optimizer, check_values,
                              detector_config, resolve_config, trainer_settings, training_size)
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.engine.clock import TrainingClock, make_clock
from dagr_lite.engine.distributed import (Distributed, broadcast_object, cleanup, global_normaliser, setup,
                                          synchronise_batch_norm)
from dagr_lite.engine.loading import batch_maker
from dagr_lite.engine.loop import NullWriter, TrainLoop, epoch_steps, make_data, resumed_done
from dagr_lite.engine.precision import PrecisionTrial, amp_dtype, memory_format, prefers_trial, time_precisions
from dagr_lite.engine.runs import record_resume, resolve_device, seed_everything, write_run_files
from dagr_lite.engine.starting import resume, resumed_config, shared_run_folder, start_from, start_weights
from dagr_lite.engine.state import TrainState
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics
from dagr_lite.nn.detector import DetectorConfig


def make_state(trainer: TrainerSettings, model, optimizer: torch.optim.Optimizer, steps_per_epoch: int,
               amp: torch.dtype | None, clock: TrainingClock, frame_cfg: DetectorConfig | None = None) -> TrainState:
    return TrainState.create(model, optimizer, total_steps=trainer.total_steps(steps_per_epoch),
                             warmup_steps=trainer.warmup_steps, min_lr_ratio=trainer.min_lr_ratio,
                             ema_decay=trainer.ema_decay, ema_tau=trainer.ema_tau, grad_clip=trainer.grad_clip,
                             amp=amp,
                             progress=clock.progress if clock.by_time else None, frame_cfg=frame_cfg)


def train(cfg: DictConfig) -> dict:
    """Train the configured detector; returns the final validation metrics, the run folder and the
    per-step training losses. Launched by ``torchrun``, every process runs this together."""
    cfg = resolve_config(resumed_config(cfg))
    check_values(cfg)
    for key in ("init_from", "resume"):  # before the datasets are opened and the run folder is made
        if cfg.get(key) is not None and not Path(cfg[key]).is_file():
            raise FileNotFoundError(f"{key}={cfg[key]}: checkpoint file is missing")
    place = Distributed.from_environment()
    device = setup(place, resolve_device(cfg.device))
    try:
        return _train(cfg, place, device)
    finally:
        cleanup(place)


# What a first phase's steps leave out, as the precision trial's line says it.
PHASE_WORDS = {"events_first": "without the image", "image_first": "without the events", "dense_first": "without the graph"}


def schedule_trial(model: torch.nn.Module, batch, trainer: TrainerSettings, done: float = 0.0) -> PrecisionTrial:
    """The precision trial of a run: a step timed in each precision (:func:`time_precisions`), and
    with a first phase (``trainer.dense_first`` and the like, whose steps leave a part out and cost
    differently) that phase's step too, the two weighed by their shares of the schedule left
    (:meth:`PrecisionTrial.of_schedule`); ``done``: the part a resumed run has trained
    (:func:`~dagr_lite.engine.loop.resumed_done`), past the phase none of it is left."""
    whole, key = time_precisions(model, batch), trainer.first_phase
    share = (max(0.0, float(getattr(trainer, key)) - done) / (1.0 - done)) if key is not None and done < 1 else 0.0
    if not share:
        return whole
    return PrecisionTrial.of_schedule(time_precisions(model, batch, **PHASE_STEP[key]), share, whole,
                                      by_time=trainer.by_time)


def first_phase_words(trainer: TrainerSettings) -> str:
    key = trainer.first_phase
    return f"{PHASE_WORDS[key]} (trainer.{key})" if key else ""


def _train(cfg: DictConfig, place: Distributed, device: torch.device) -> dict:
    if place.is_main:
        print(OmegaConf.to_yaml(cfg), flush=True)
    run_dir, resume_from = shared_run_folder(cfg, place)
    seed_everything(cfg.seed)
    train_set = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
    height, width = training_size(cfg, train_set.image_size)  # a crop's with data.augment.crop < 1
    model = build_model(cfg, height=height, width=width).to(device)
    init_from = start_weights(cfg, resume_from)
    if init_from is not None:
        start_from(model, init_from, verbose=place.is_main)
    trainer = trainer_settings(cfg)
    model = model.to(memory_format=memory_format(trainer, device))
    if trainer.events_first and resume_from is None:  # the image's weights start at zero (see TrainLoop)
        model.zero_image_weights()
    if trainer.image_first and resume_from is None:  # the events' weights start at zero (see TrainLoop)
        model.zero_event_weights()
    if trainer.dense_first and resume_from is None:  # the event graph's weights start at zero (see TrainLoop)
        model.zero_graph_weights()
    amp, trial = amp_dtype(trainer, device), None
    if prefers_trial(trainer, device):  # a CPU with native bfloat16: bfloat16 if clearly faster on a first batch,
        if place.is_main:               # timed before the processes share batch norm and the loss normaliser
            first = [train_set[(0, index)] for index in range(min(cfg.loader.batch_size, len(train_set)))]
            done = (resumed_done(trainer, load_checkpoint(resume_from).training,
                                 epoch_steps(len(train_set), cfg.loader.batch_size * place.world_size))
                    if resume_from is not None and trainer.first_phase else 0.0)
            trial = schedule_trial(model, batch_maker(model.graph_spec)(first), trainer, done)
        trial = broadcast_object(trial, place)
        amp = trial.dtype
    if place.enabled:
        model = synchronise_batch_norm(model, device)
        model.loss_normaliser = global_normaliser(place)
    data = make_data(cfg, train_set, model, place)
    clock = make_clock(trainer)
    frame_cfg = detector_config(cfg, height=train_set.image_size[0], width=train_set.image_size[1])
    state = make_state(trainer, model, build_optimizer(cfg, model.parameters()), data.steps_per_epoch, amp, clock,
                       frame_cfg)
    if place.is_main:
        precision = "float32" if state.amp_dtype is None else f"mixed precision {str(state.amp_dtype).split('.')[-1]}"
        other = "trainer.amp_dtype=bfloat16 keeps bfloat16" if amp is None else "trainer.amp=false keeps float32"
        why = f" ({trial.describe(first_phase_words(trainer))}; {other})" if trial else ""
        print(f"training on {device} in {precision}{why}", flush=True)
    saved = resume(state, resume_from, run_dir / "checkpoints", place) if resume_from else None
    if place.is_main and not (run_dir / "config.yaml").exists():  # all checked: the run folder is made now
        write_run_files(run_dir, cfg)
    elif place.is_main and saved is not None:  # a run going on in its own folder: its resumes are logged
        record_resume(run_dir, state.step, resume_from)
    if place.enabled:
        state.forward = DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None,
                                                find_unused_parameters=bool(trainer.events_first or trainer.image_first
                                                                           or trainer.dense_first))  # a branch idle in a first phase
    writer = SummaryWriter(str(run_dir / "tensorboard")) if place.is_main else NullWriter()
    try:
        loop = TrainLoop(trainer, OmegaConf.to_container(cfg, resolve=True), state, data, run_dir, writer, clock,
                         position=saved.training.get("position") if saved else None)
        metrics = loop.run()
    finally:
        if place.is_main:
            writer.close()
    extra = {key: value for key, value in metrics.items() if "_age" in key or key == "mAP_mean"}
    result = {**{key: metrics[key] for key in METRIC_KEYS}, **extra, "split": "valid", "image_age": cfg.data.image_age,
              "num_images": len(data.valid_loaders[cfg.data.image_age].dataset), "step": state.step,
              "world_size": place.world_size, "global_batch_size": data.global_batch_size}
    if place.is_main:
        (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
        print(f"validation metrics after {state.step} steps ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir), "losses": loop.losses, "step": state.step}
