"""The training entry: ``train(cfg)`` is what ``python train.py`` runs and what tests call."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from dagr_lite.config import ConfigError, build_dataset, build_model, resolve_config
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.engine.common import (EpochSampler, ModelEMA, load_checkpoint, make_loader, resolve_device,
                                     run_folder, save_checkpoint, seed_everything, warmup_cosine)
from dagr_lite.engine.validate import evaluate_model, render_sample
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics


def describe_dataset(dataset: EventEgoHands) -> str:
    height, width = dataset.image_size
    return (f"{dataset.root} [{dataset.split}]: {len(dataset.videos)} videos, {len(dataset)} samples, "
            f"{width}x{height} px, window {dataset.window_us} us, image lag {dataset.image_lag}")


def _graph_options(cfg: DictConfig) -> dict | None:
    if not cfg.model.use_events:
        return None
    return {"radius": cfg.model.radius, "beta": cfg.model.beta, "max_neighbors": cfg.model.max_neighbors}


def _total_steps(cfg: DictConfig, steps_per_epoch: int) -> int:
    trainer = cfg.trainer
    if trainer.max_steps is not None:
        return int(trainer.max_steps)
    if trainer.max_epochs is not None:
        return int(trainer.max_epochs) * steps_per_epoch
    raise ConfigError("set trainer.max_steps or trainer.max_epochs")


def train(cfg: DictConfig) -> dict:
    """Train the configured detector; returns the final validation metrics, the run folder and the
    per-step training losses."""
    cfg = resolve_config(cfg)
    print(OmegaConf.to_yaml(cfg), flush=True)
    run_dir = run_folder(cfg, "train")
    seed_everything(cfg.seed)
    device = resolve_device(cfg.device)
    train_set = build_dataset(cfg, "train", train=True)
    valid_set = build_dataset(cfg, "valid", train=False)
    for dataset in (train_set, valid_set):
        print(describe_dataset(dataset), flush=True)
    graph = _graph_options(cfg)
    batch_size = cfg.loader.batch_size
    sampler = EpochSampler(len(train_set), seed=cfg.seed)
    train_loader = make_loader(train_set, batch_size=batch_size, num_workers=cfg.loader.num_workers,
                               sampler=sampler, graph=graph, drop_last=len(train_set) >= batch_size)
    valid_loader = make_loader(valid_set, batch_size=batch_size, num_workers=cfg.loader.num_workers, graph=graph)
    steps_per_epoch = len(train_loader)
    if steps_per_epoch == 0:
        raise ConfigError(f"the train split has {len(train_set)} samples: no batch of {batch_size} can be made")
    total_steps = _total_steps(cfg, steps_per_epoch)

    height, width = train_set.image_size
    model = build_model(cfg, height=height, width=width).to(device)
    ema = ModelEMA(model, cfg.trainer.ema_decay, cfg.trainer.ema_tau)
    optim = cfg.optim
    optimizer = torch.optim.AdamW(model.parameters(), lr=optim.lr, weight_decay=optim.weight_decay,
                                  betas=tuple(optim.betas))
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: warmup_cosine(step, warmup=cfg.trainer.warmup_steps, total=total_steps,
                                              min_ratio=cfg.trainer.min_lr_ratio))
    use_amp = bool(cfg.trainer.amp) and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp)
    step, best = 0, -math.inf
    if cfg.resume:
        state = load_checkpoint(cfg.resume)
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["scheduler"])
        if state["scaler"]:  # empty when the saved run did not use mixed precision
            scaler.load_state_dict(state["scaler"])
        step, best = int(state["step"]), float(state["best_metric"])
        print(f"resumed from {cfg.resume} at step {step}", flush=True)

    config_container = OmegaConf.to_container(cfg, resolve=True)
    writer = SummaryWriter(str(run_dir / "tensorboard"))
    checkpoints = run_dir / "checkpoints"
    val_every = cfg.trainer.val_every or steps_per_epoch

    def checkpoint_state() -> dict:
        return {"model": model.state_dict(), "ema": ema.state_dict(), "optimizer": optimizer.state_dict(),
                "scheduler": schedule.state_dict(), "scaler": scaler.state_dict(), "step": step,
                "best_metric": best, "config": config_container}

    def validate() -> dict:
        nonlocal best
        metrics, _ = evaluate_model(ema.module, valid_loader, device, backend=cfg.eval.backend,
                                    conf_threshold=cfg.eval.conf_threshold, nms_threshold=cfg.eval.nms_threshold,
                                    desc=f"validating at step {step}")
        for key in ("mAP", "AP50", "AP75"):
            writer.add_scalar(f"val/{key}", metrics[key], step)
        improved = metrics["mAP"] > best
        if improved:
            best = metrics["mAP"]
        save_checkpoint(checkpoints / "last.pt", checkpoint_state())
        if improved:
            save_checkpoint(checkpoints / "best.pt", checkpoint_state())
        print(f"step {step}: val mAP {metrics['mAP']:.4f}  AP50 {metrics['AP50']:.4f}  AP75 {metrics['AP75']:.4f}",
              flush=True)
        return metrics

    try:
        losses: list[float] = []
        metrics: dict | None = None
        started = time.monotonic()
        out_of_time = False
        bar = tqdm(total=total_steps, initial=step, desc="training", unit="step")
        model.train()
        while step < total_steps and not out_of_time:
            epoch, start = divmod(step, steps_per_epoch)
            sampler.set_epoch(epoch, start * batch_size)
            train_set.set_epoch(epoch)
            for batch in train_loader:
                batch = batch.to(device, non_blocking=True)
                with torch.autocast(device.type, enabled=use_amp):
                    out = model(batch)
                loss = out["loss"]
                if not torch.isfinite(loss):
                    parts = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in out.items())
                    raise FloatingPointError(f"non-finite loss {float(loss.detach())} at step {step} ({parts})")
                optimizer.zero_grad(set_to_none=True)
                scaler.scale(loss).backward()
                scaler.unscale_(optimizer)
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.trainer.grad_clip)
                scaler.step(optimizer)
                scaler.update()
                schedule.step()
                ema.update(model)
                step += 1
                losses.append(float(loss.detach()))
                lr = optimizer.param_groups[0]["lr"]
                bar.update(1)
                bar.set_postfix(loss=f"{losses[-1]:.3f}", lr=f"{lr:.2e}")
                if step % cfg.trainer.log_every == 0 or step == total_steps:
                    for key, value in out.items():
                        writer.add_scalar(f"train/{key}", float(value.detach()), step)
                    writer.add_scalar("train/lr", lr, step)
                if cfg.trainer.image_every and step % cfg.trainer.image_every == 0:
                    ema.module.eval()
                    with torch.no_grad():
                        detections = ema.module(batch)
                    writer.add_image("train/sample", render_sample(batch, 0, detections[0]), step, dataformats="HWC")
                if cfg.trainer.max_minutes is not None and time.monotonic() - started > 60 * cfg.trainer.max_minutes:
                    print(f"trainer.max_minutes={cfg.trainer.max_minutes} reached at step {step}", flush=True)
                    out_of_time = True
                if step % val_every == 0 or step == total_steps or out_of_time:
                    metrics = validate()
                    model.train()
                if step >= total_steps or out_of_time:
                    break
        bar.close()
        if metrics is None:  # resumed at the end, or nothing left to train
            metrics = validate()
    finally:
        writer.close()
    result = {**{key: metrics[key] for key in METRIC_KEYS}, "split": "valid", "num_images": len(valid_set),
              "step": step}
    (run_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    print(f"validation metrics after {step} steps ({run_dir}):\n{format_metrics(metrics)}", flush=True)
    return {"metrics": result, "run_dir": Path(run_dir), "losses": losses, "step": step}
