"""Run folders and what starts a run: devices, seeds, the folder a run writes into and its files."""
from __future__ import annotations

import os
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from dagr_lite.errors import UserError
from dagr_lite.data.writer import write_text_atomically


# What marks a folder as holding a run: none of these is ever overwritten by a new run.
RUN_FILES = ("checkpoints", "metrics.json", "config.yaml", ".hydra")


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when present, else CPU; anything else as given (``cpu``, ``cuda:1``)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"device={name} was asked for, but CUDA is not available here")
    return device


def seed_everything(seed: int) -> None:
    """Seed torch's global generator (weight initialisation); every other draw has its own
    ``np.random.default_rng([seed, ...])``."""
    torch.manual_seed(seed)


def run_folder(cfg: DictConfig, kind: str, *, make: bool = True) -> Path:
    """The run's own folder: ``cfg.run_dir``, else Hydra's, else a new ``runs/<kind>/<time>``.

    An existing folder holding a run (checkpoints, metrics or its config) is never reused: the
    check comes before anything is written. The folder is then made, with the resolved config
    and the command-line overrides in it (:func:`write_run_files`); ``make=False`` checks only,
    for a caller that checks more before it writes anything.
    """
    if cfg.get("run_dir"):
        path = Path(cfg.run_dir)
    else:
        try:
            from hydra.core.hydra_config import HydraConfig
            path = Path(HydraConfig.get().runtime.output_dir)
        except (ImportError, ValueError):
            path = Path("runs") / kind / time.strftime("%Y-%m-%d/%H-%M-%S") / f"{os.getpid()}"
    for name in RUN_FILES:
        if (path / name).exists():
            raise FileExistsError(f"{path}: holds an earlier run ({name}); choose a new run_dir")
    if make:
        write_run_files(path, cfg)
    return path


def record_resume(path: Path, step: int, resumed_from: str) -> None:
    """Append to ``path/resumes.yaml`` the step a resume went on from, its checkpoint and the command
    line's overrides (``config.yaml`` and ``overrides.yaml`` stay the first command's)."""
    overrides: list[str] = []
    try:
        from hydra.core.hydra_config import HydraConfig
        overrides = list(HydraConfig.get().overrides.task)
    except (ImportError, ValueError):
        pass
    log = path / "resumes.yaml"
    records = OmegaConf.to_container(OmegaConf.load(log)) if log.is_file() else []
    records.append({"step": int(step), "resume": str(resumed_from), "overrides": overrides})
    write_text_atomically(log, OmegaConf.to_yaml(OmegaConf.create(records)))


def write_run_files(path: Path, cfg: DictConfig) -> None:
    """Make the run folder ``path`` and write ``config.yaml`` (resolved) and ``overrides.yaml``
    (the command line's overrides) into it."""
    overrides: list[str] = []
    try:
        from hydra.core.hydra_config import HydraConfig
        overrides = list(HydraConfig.get().overrides.task)
    except (ImportError, ValueError):
        pass
    path.mkdir(parents=True, exist_ok=True)
    write_text_atomically(path / "config.yaml", OmegaConf.to_yaml(cfg))
    write_text_atomically(path / "overrides.yaml", OmegaConf.to_yaml(OmegaConf.create(overrides)))
