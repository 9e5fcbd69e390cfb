"""The evaluation entry: ``evaluate(cfg)`` is what ``python evaluate.py`` runs and what tests call."""
from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from dagr_lite.config import build_dataset, resolve_config
from dagr_lite.engine.train import describe_dataset


def evaluate(cfg: DictConfig) -> dict:
    """Validate and print the config and open the evaluation split (``split=...``)."""
    cfg = resolve_config(cfg)
    print(OmegaConf.to_yaml(cfg), flush=True)
    dataset = build_dataset(cfg, cfg.split, train=False)
    print(describe_dataset(dataset), flush=True)
    return {"config": cfg, "dataset": dataset}
