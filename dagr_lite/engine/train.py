"""The training entry: ``train(cfg)`` is what ``python train.py`` runs and what tests call.

It builds the datasets, the model (which owns the event-graph spec the loaders build graphs
with), the :class:`~dagr_lite.engine.state.TrainState`, then loops over epochs calling
:func:`~dagr_lite.engine.state.train_step`, saving ``last.pt`` and validating every
``trainer.val_every`` steps.
"""
from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from dagr_lite.config import build_dataset, build_model, build_optimizer, check_values, resolve_config
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.engine.common import (EpochSampler, load_checkpoint, make_loader, resolve_device, run_folder,
                                     save_checkpoint, seed_everything)
from dagr_lite.engine.state import TrainState, train_step, validate
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics
from dagr_lite.eval.score import render_sample


class ResumeError(ValueError):
    """A checkpoint given as ``resume=`` does not fit this run; the message names both sides."""


def describe_dataset(dataset: EventEgoHands) -> str:
    height, width = dataset.image_size
    return (f"{dataset.root} [{dataset.split}]: {len(dataset.videos)} videos, {len(dataset)} samples, "
            f"{width}x{height} px, image age {describe_age(dataset.age_range)} frames, events "
            f"{'since the image' if dataset.event_span == 'since_image' else f'of {dataset.window_us} us'}")


def describe_age(ages: tuple[int, int]) -> str:
    return str(ages[0]) if ages[0] == ages[1] else f"{ages[0]}-{ages[1]}"


@dataclass
class TrainData:
    """The datasets and loaders of a run; the loaders build graphs with the model's spec.
    Validation runs at each image age of ``valid_loaders`` (``data.image_age``, and for a model
    with an image also the largest training age)."""

    train_set: EventEgoHands
    sampler: EpochSampler
    train_loader: DataLoader
    valid_loaders: dict[int, DataLoader]
    batch_size: int


def validation_ages(cfg: DictConfig) -> list[int]:
    """``data.image_age``, and for a model with an image the largest training age too."""
    ages = {cfg.data.image_age}
    if cfg.model.use_image:
        ages.add(cfg.data.train_image_age[1])
    return sorted(ages)


def make_data(cfg: DictConfig, train_set: EventEgoHands, model) -> TrainData:
    """The training loader, and one validation loader per validation age."""
    with_image = cfg.model.use_image
    valid_sets = {age: build_dataset(cfg, "valid", train=False, with_image=with_image, image_age=age)
                  for age in validation_ages(cfg)}
    for dataset in (train_set, *valid_sets.values()):
        print(describe_dataset(dataset), flush=True)
    batch_size, workers = cfg.loader.batch_size, cfg.loader.num_workers
    if len(train_set) < batch_size:
        raise ValueError(f"loader.batch_size={batch_size}, but the train split has {len(train_set)} samples: "
                         "no batch can be made")
    sampler = EpochSampler(len(train_set), seed=cfg.seed)
    train_loader = make_loader(train_set, batch_size=batch_size, num_workers=workers, sampler=sampler,
                               graph=model.graph_spec, drop_last=True)
    valid_loaders = {age: make_loader(dataset, batch_size=batch_size, num_workers=workers, graph=model.graph_spec)
                     for age, dataset in valid_sets.items()}
    return TrainData(train_set, sampler, train_loader, valid_loaders, batch_size)


def make_state(cfg: DictConfig, model, steps_per_epoch: int, device: torch.device) -> TrainState:
    trainer = cfg.trainer
    return TrainState.create(model, build_optimizer(cfg, model.parameters()),
                             total_steps=make_total(cfg, steps_per_epoch),
                             warmup_steps=trainer.warmup_steps, min_lr_ratio=trainer.min_lr_ratio,
                             ema_decay=trainer.ema_decay, ema_tau=trainer.ema_tau, grad_clip=trainer.grad_clip,
                             amp=bool(trainer.amp) and device.type == "cuda")


def resume(state: TrainState, path: str | Path, checkpoints: Path) -> None:
    """Continue from checkpoint ``path``; its run's ``best.pt`` is carried into ``checkpoints``, so
    the new run holds its best weights even when it never beats them."""
    saved = load_checkpoint(path)
    ours = state.model.cfg.as_dict()
    if saved["detector"] != ours:
        differ = ", ".join(f"{key}: {saved['detector'].get(key)!r} in the checkpoint, {ours[key]!r} here"
                           for key in ours if saved["detector"].get(key) != ours[key])
        raise ResumeError(f"resume={path}: the checkpoint's model does not fit this run's ({differ})")
    state.load_state_dict(saved)
    best = Path(path).parent / "best.pt"
    if best.is_file():
        checkpoints.mkdir(parents=True, exist_ok=True)
        shutil.copy2(best, checkpoints / "best.pt")
    else:
        state.best_metric = -math.inf  # nothing to carry: the first validation writes best.pt
    print(f"resumed from {path} at step {state.step}", flush=True)


class TrainLoop:
    """The epochs of one run: steps, logging, pictures, checkpoints and validation."""

    def __init__(self, cfg: DictConfig, state: TrainState, data: TrainData, run_dir: Path, writer: SummaryWriter):
        self.cfg, self.state, self.data, self.writer = cfg, state, data, writer
        self.trainer = cfg.trainer
        self.checkpoints = run_dir / "checkpoints"
        self.steps_per_epoch = len(data.train_loader)
        self.total = make_total(cfg, self.steps_per_epoch)
        self.val_every = self.trainer.val_every or self.steps_per_epoch
        self.config = OmegaConf.to_container(cfg, resolve=True)
        self.losses: list[float] = []
        self.metrics: dict | None = None

    def run(self) -> dict:
        started, state = time.monotonic(), self.state
        bar = tqdm(total=self.total, initial=state.step, desc="training", unit="step")
        while state.step < self.total:
            epoch, start = divmod(state.step, self.steps_per_epoch)
            self.data.sampler.set_epoch(epoch, start * self.data.batch_size)
            self.data.train_set.set_epoch(epoch)
            for batch in self.data.train_loader:
                batch = batch.to(state.device, non_blocking=True)
                out = train_step(state, batch)
                self.losses.append(float(out["loss"]))
                bar.update(1)
                bar.set_postfix(loss=f"{self.losses[-1]:.3f}", lr=f"{state.lr:.2e}")
                self.log(out, batch)
                out_of_time = self.out_of_time(started)
                if state.step % self.val_every == 0 or state.step == self.total or out_of_time:
                    self.save_and_validate()
                if state.step >= self.total or out_of_time:
                    bar.close()
                    return self.metrics
        bar.close()
        return self.metrics if self.metrics is not None else self.save_and_validate()  # resumed at the end

    def out_of_time(self, started: float) -> bool:
        minutes = self.trainer.max_minutes
        if minutes is None or time.monotonic() - started <= 60 * minutes:
            return False
        print(f"trainer.max_minutes={minutes} reached at step {self.state.step}", flush=True)
        return True

    def log(self, out: dict, batch) -> None:
        step = self.state.step
        if step % self.trainer.log_every == 0 or step == self.total:
            for key, value in out.items():
                self.writer.add_scalar(f"train/{key}", float(value), step)
            self.writer.add_scalar("train/lr", self.state.lr, step)
        if self.trainer.image_every and step % self.trainer.image_every == 0:
            ema = self.state.ema.module.eval()
            with torch.no_grad():
                detections = ema(batch)
            self.writer.add_image("train/sample", render_sample(batch, 0, detections[0]), step, dataformats="HWC")

    def checkpoint(self) -> dict:
        return {**self.state.state_dict(), "detector": self.state.model.cfg.as_dict(), "config": self.config}

    def save_and_validate(self) -> dict:
        """Save ``last.pt`` first (a failing validation loses no training), then validate at each
        validation age and keep ``best.pt`` when the mean mAP over those ages improves.

        The returned metrics are those of the first age (``data.image_age``), with ``mAP_age<a>``,
        ``AP50_age<a>`` for every age and their ``mAP_mean``.
        """
        state = self.state
        save_checkpoint(self.checkpoints / "last.pt", self.checkpoint())
        ev = self.cfg.eval
        per_age = {age: validate(state, loader, backend=ev.backend, conf_threshold=ev.conf_threshold,
                                 nms_threshold=ev.nms_threshold) for age, loader in self.data.valid_loaders.items()}
        metrics = dict(per_age[self.cfg.data.image_age])
        for age, values in per_age.items():
            metrics.update({f"mAP_age{age}": values["mAP"], f"AP50_age{age}": values["AP50"]})
        metrics["mAP_mean"] = sum(values["mAP"] for values in per_age.values()) / len(per_age)
        for key in ("mAP", "AP50", "AP75", "mAP_mean", *(f"{m}_age{a}" for a in per_age for m in ("mAP", "AP50"))):
            self.writer.add_scalar(f"val/{key}", metrics[key], state.step)
        if metrics["mAP_mean"] > state.best_metric or not (self.checkpoints / "best.pt").exists():
            state.best_metric = max(state.best_metric, metrics["mAP_mean"])
            save_checkpoint(self.checkpoints / "best.pt", self.checkpoint())
            save_checkpoint(self.checkpoints / "last.pt", self.checkpoint())  # with the new best metric
        ages = "  ".join(f"age {a}: mAP {v['mAP']:.4f} AP50 {v['AP50']:.4f}" for a, v in per_age.items())
        print(f"step {state.step}: val {ages}", flush=True)
        self.metrics = metrics
        return metrics


def make_total(cfg: DictConfig, steps_per_epoch: int) -> int:
    trainer = cfg.trainer
    return int(trainer.max_steps) if trainer.max_steps is not None else int(trainer.max_epochs) * steps_per_epoch


def train(cfg: DictConfig) -> dict:
    """Train the configured detector; returns the final validation metrics, the run folder and the
    per-step training losses."""
    cfg = resolve_config(cfg)
    check_values(cfg)
    print(OmegaConf.to_yaml(cfg), flush=True)
    run_dir = run_folder(cfg, "train")
    seed_everything(cfg.seed)
    device = resolve_device(cfg.device)
    train_set = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
    model = build_model(cfg, height=train_set.image_size[0], width=train_set.image_size[1]).to(device)
    data = make_data(cfg, train_set, model)
    state = make_state(cfg, model, len(data.train_loader), device)
    if cfg.resume:
        resume(state, cfg.resume, run_dir / "checkpoints")
    with SummaryWriter(str(run_dir / "tensorboard")) as writer:
        loop = TrainLoop(cfg, state, data, run_dir, writer)
        metrics = loop.run()
    extra = {key: value for key, value in metrics.items() if "_age" in key or key == "mAP_mean"}
    result = {**{key: metrics[key] for key in METRIC_KEYS}, **extra, "split": "valid", "image_age": cfg.data.image_age,
              "num_images": len(data.valid_loaders[cfg.data.image_age].dataset), "step": state.step}
    (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    print(f"validation metrics after {state.step} steps ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir), "losses": loop.losses, "step": state.step}

