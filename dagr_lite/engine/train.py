"""The training entry: ``train(cfg)`` is what ``python train.py`` runs and what tests call."""
from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader

from dagr_lite.config import build_dataset, resolve_config
from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import EventEgoHands


def describe_dataset(dataset: EventEgoHands) -> str:
    height, width = dataset.image_size
    return (f"{dataset.root} [{dataset.split}]: {len(dataset.videos)} videos, {len(dataset)} samples, "
            f"{width}x{height} px, window {dataset.window_us} us, image lag {dataset.image_lag}")


def build_loader(dataset: EventEgoHands, *, batch_size: int, num_workers: int, shuffle: bool,
                 seed: int = 0) -> DataLoader:
    """A loader over ``dataset`` with :func:`collate`.

    Workers are started per epoch (not persistent), so ``dataset.set_epoch`` reaches them.
    """
    generator = torch.Generator().manual_seed(seed)
    return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, num_workers=num_workers,
                      collate_fn=collate, drop_last=False, generator=generator,
                      pin_memory=torch.cuda.is_available())


def train(cfg: DictConfig) -> dict:
    """Validate and print the config, build the train and valid data, and read one batch.

    Returns a summary: the resolved config and, per split, the dataset and the first batch.
    """
    cfg = resolve_config(cfg)
    print(OmegaConf.to_yaml(cfg), flush=True)
    datasets = {"train": build_dataset(cfg, "train", train=True), "valid": build_dataset(cfg, "valid", train=False)}
    for dataset in datasets.values():
        print(describe_dataset(dataset), flush=True)
    loader = build_loader(datasets["train"], batch_size=cfg.loader.batch_size, num_workers=cfg.loader.num_workers,
                          shuffle=True, seed=cfg.seed)
    batch = next(iter(loader))
    print(f"first training batch: {len(batch)} samples, {len(batch.events)} events, "
          f"{sum(len(b) for b in batch.boxes)} boxes, images {tuple(batch.images.shape)}", flush=True)
    return {"config": cfg, "datasets": datasets, "batch": batch}
