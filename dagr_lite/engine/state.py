"""What training holds between steps, one optimiser step, and one validation pass.

:class:`TrainState` gathers the model, its EMA, the optimiser, the learning-rate schedule, the
gradient scaler, the step and the best validation metric, and saves and restores them as one
``state_dict``. :func:`train_step` and :func:`validate` are what the training loop calls, and
what tests call directly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn
from torch.utils.data import DataLoader

from dagr_lite.data.collate import Batch
from dagr_lite.engine.schedule import ModelEMA, warmup_cosine
from dagr_lite.eval.operating import CANDIDATE_SCORE, NMS_IOUS
from dagr_lite.eval.score import detection_sets, score_entries
from dagr_lite.nn.detector import Detector, DetectorConfig

STATE_KEYS = ("model", "ema", "optimizer", "scheduler", "scaler", "step", "best_metric")


@dataclass
class TrainState:
    """Everything a training run carries from one step to the next.

    Attributes:
        model: the detector being trained; ema: its moving average (validated and saved).
        optimizer, scheduler, scaler: the optimiser, its learning-rate schedule, the AMP scaler.
        grad_clip: the gradient-norm bound of each step.
        step: optimiser steps taken; best_metric: the best validation mAP so far.
        frame_cfg: when the model trains on crops of the frame (``data.augment.crop``), the same
            detector at the frame's size: validation runs it (:meth:`frame_ema`) and checkpoints
            record it (the weights do not depend on the size); None: the model's own.
    """

    model: Detector
    ema: ModelEMA
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    scaler: torch.amp.GradScaler
    grad_clip: float
    step: int = 0
    best_metric: float = -math.inf
    forward: nn.Module | None = None  # what a training step calls instead of ``model`` (its DDP wrapper)
    amp_dtype: torch.dtype | None = None  # mixed precision: float16 (with the scaler) or bfloat16; None: off
    frame_cfg: DetectorConfig | None = None

    @classmethod
    def create(cls, model: Detector, optimizer: torch.optim.Optimizer, *, total_steps: int, warmup_steps: int,
               min_lr_ratio: float, ema_decay: float, ema_tau: float, grad_clip: float,
               amp: bool | torch.dtype, progress: Callable[[], float] | None = None,
               frame_cfg: DetectorConfig | None = None) -> "TrainState":
        """A fresh state: warm-up cosine schedule over ``total_steps`` (or, after the warm-up, over
        what ``progress()`` says is spent of a time budget), EMA, and mixed precision when ``amp``
        is a dtype (``True``: float16): float16 runs with a gradient scaler, bfloat16 without."""
        schedule = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: warmup_cosine(step, warmup=warmup_steps, total=total_steps, min_ratio=min_lr_ratio,
                                                  progress=progress() if progress is not None else None))
        device = next(model.parameters()).device
        amp_dtype = torch.float16 if amp is True else (amp or None)
        if amp_dtype not in (None, torch.float16, torch.bfloat16):
            raise ValueError(f"mixed precision runs in float16 or bfloat16, got {amp_dtype}")
        return cls(model=model, ema=ModelEMA(model, ema_decay, ema_tau), optimizer=optimizer, scheduler=schedule,
                   scaler=torch.amp.GradScaler(device.type, enabled=amp_dtype == torch.float16), grad_clip=grad_clip,
                   amp_dtype=amp_dtype, frame_cfg=None if frame_cfg == model.cfg else frame_cfg)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def detector_cfg(self) -> DetectorConfig:
        """The detector a checkpoint records: at the frame's size (:attr:`frame_cfg`, when training on
        crops), else the model's."""
        return self.frame_cfg or self.model.cfg

    def frame_ema(self) -> Detector:
        """The EMA weights in the detector of :attr:`detector_cfg`: the EMA itself, or a copy of it
        at the frame's size when the model trains on crops."""
        if self.frame_cfg is None:
            return self.ema.module
        module = Detector(self.frame_cfg).to(self.device)
        module.load_state_dict(self.ema.module.state_dict())
        return module.eval()

    @property
    def amp(self) -> bool:
        return self.amp_dtype is not None

    @property
    def lr(self) -> float:
        return self.optimizer.param_groups[0]["lr"]

    def refresh_lr(self) -> None:
        """Set each group's rate again from the schedule at its current step (for a schedule that
        also reads a clock: the rate of the next step from the latest reading)."""
        scheduler = self.scheduler
        for group, base, factor in zip(self.optimizer.param_groups, scheduler.base_lrs, scheduler.lr_lambdas):
            group["lr"] = base * factor(scheduler.last_epoch)

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "ema": self.ema.state_dict(),
                "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                "scaler": self.scaler.state_dict(), "step": self.step, "best_metric": self.best_metric}

    def load_state_dict(self, state: dict) -> None:
        """Restore everything :meth:`state_dict` saved (a scaler state is optional: a run without
        mixed precision saves an empty one)."""
        missing = [key for key in STATE_KEYS if key not in state]
        if missing:
            raise KeyError(f"training state lacks {missing}")
        self.model.load_state_dict(state["model"])
        self.ema.load_state_dict(state["ema"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if state["scaler"]:
            self.scaler.load_state_dict(state["scaler"])
        self.step, self.best_metric = int(state["step"]), float(state["best_metric"])


def train_step(state: TrainState, batch: Batch, *, image: bool = True, events: bool = True,
               graph: bool = True) -> dict[str, torch.Tensor]:
    """One optimiser step on ``batch`` (already on the model's device); returns the detached losses.
    ``image=False``: a hybrid's image features are zero and its image branch is not run;
    ``events=False``: its event and recency maps are zero and its event branch is not run;
    ``graph=False``: its event branch's maps are zero and the branch is not run, so the batch
    needs no graph (:meth:`Detector.forward`).

    A non-finite loss raises :class:`FloatingPointError` naming the step and every loss term,
    before any weight changes.
    """
    model = state.model
    model.train()
    with torch.autocast(state.device.type, dtype=state.amp_dtype, enabled=state.amp):
        out = (state.forward or model)(batch, **({} if image else {"image": False}),
                                       **({} if events else {"events": False}), **({} if graph else {"graph": False}))
    loss = out["loss"]
    if not torch.isfinite(loss):
        parts = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in out.items())
        raise FloatingPointError(f"non-finite loss {float(loss.detach())} at step {state.step} ({parts})")
    state.optimizer.zero_grad(set_to_none=True)
    state.scaler.scale(loss).backward()
    state.scaler.unscale_(state.optimizer)
    torch.nn.utils.clip_grad_norm_(model.parameters(), state.grad_clip)
    state.scaler.step(state.optimizer)
    state.scaler.update()
    state.scheduler.step()
    state.ema.update(model)
    state.step += 1
    return {key: value.detach() for key, value in out.items()}


def validate(state: TrainState, loader: DataLoader, *, backend: str, conf_threshold: float,
             nms_threshold: float, progress: bool = True,
             gather: Callable[[list], list] | None = None) -> dict[str, float]:
    """COCO metrics of the EMA weights over every sample of ``loader``.

    ``gather``: with several processes, each ``loader`` holds one shard; ``gather`` turns this
    rank's detections into those of every shard in the dataset's order, so every rank scores the
    whole split exactly as one process would.
    """
    return validation_pass(state, loader, backend=backend, conf_threshold=conf_threshold, nms_threshold=nms_threshold,
                           progress=progress, gather=gather)[0]


def validation_pass(state: TrainState, loader: DataLoader, *, backend: str, conf_threshold: float,
                    nms_threshold: float, progress: bool = True,
                    gather: Callable[[list], list] | None = None) -> tuple[dict[str, float], dict[float, list]]:
    """:func:`validate`'s metrics, and from the same forward passes the candidates of an operating
    point: ``{NMS IoU: entries}`` for each IoU of :data:`~dagr_lite.eval.operating.NMS_IOUS`, boxes
    of :data:`~dagr_lite.eval.operating.CANDIDATE_SCORE` or more."""
    settings = {"coco": (conf_threshold, nms_threshold), **{iou: (CANDIDATE_SCORE, iou) for iou in NMS_IOUS}}
    sets = detection_sets(state.frame_ema(), loader, state.device, settings, progress=progress,
                          desc=f"validating at step {state.step}")
    if gather is not None:
        sets = {key: gather(entries) for key, entries in sets.items()}
    metrics, _ = score_entries(sets.pop("coco"), backend=backend)
    return metrics, sets
