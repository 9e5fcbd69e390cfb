"""Pieces shared by training and evaluation: devices, seeds, run folders, checkpoints, EMA, loaders."""
from __future__ import annotations

import copy
import math
import os
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torch.utils.data import DataLoader, Sampler

from dagr_lite.data.collate import GraphCollate, collate
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.data.writer import temporary_name, write_text_atomically
from dagr_lite.graph.spec import EventGraphSpec

CHECKPOINT_FORMAT = 2
# What marks a folder as holding a run: none of these is ever overwritten by a new run.
RUN_FILES = ("checkpoints", "metrics.json", "config.yaml", ".hydra")


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when present, else CPU; anything else as given (``cpu``, ``cuda:1``)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name} was asked for, but CUDA is not available here")
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


def load_checkpoint(path: Path | str) -> dict:
    """Load a checkpoint safely (``weights_only``); a missing or foreign file gives a clear error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint file is missing")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling errors come in many types
        raise ValueError(f"{path}: cannot read as a dagr_lite checkpoint ({err})") from err
    if not isinstance(state, dict) or "model" not in state:
        raise ValueError(f"{path}: not a dagr_lite checkpoint (expected keys format, model, ema, detector, config, ...)")
    if state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: a checkpoint of format {state.get('format')}, but this dagr_lite reads format "
                         f"{CHECKPOINT_FORMAT} (it records the model's architecture and event graph); "
                         "train the model again with this version")
    return state


class ModelEMA:
    """Exponential moving average of a model's weights (and buffers), used for validation.

    ``decay`` ramps up as ``decay * (1 - exp(-updates / tau))`` so early averages follow the model.
    """

    def __init__(self, model: nn.Module, decay: float = 0.9998, tau: float = 2000.0):
        self.module = copy.deepcopy(model).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        model_state = model.state_dict()
        for name, value in self.module.state_dict().items():
            if value.dtype.is_floating_point:
                value.mul_(d).add_(model_state[name].detach(), alpha=1 - d)
            else:
                value.copy_(model_state[name])

    def state_dict(self) -> dict:
        return {"module": self.module.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.module.load_state_dict(state["module"])
        self.updates = int(state["updates"])


def warmup_cosine(step: int, *, warmup: int, total: int, min_ratio: float, progress: float | None = None) -> float:
    """Learning-rate factor: linear warm-up over ``warmup`` steps, then cosine down to ``min_ratio``.

    The cosine's progress is ``(step - warmup) / (total - warmup)``; ``progress``, when given, is a
    second measure (e.g. the fraction of a time budget spent since the warm-up), and the cosine
    follows whichever of the two is further along."""
    if step < warmup:
        return (step + 1) / warmup
    by_steps = (step - warmup) / max(1, total - warmup)
    progress = min(1.0, max(by_steps, progress if progress is not None else 0.0))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


class EpochSampler(Sampler[int]):
    """Shuffled indices, a fixed permutation per (seed, epoch), optionally starting part-way.

    ``start`` counts samples of the epoch's order: resuming skips them without loading them.
    With ``world_size`` > 1 the order is cut into global batches of ``batch_size * world_size``
    samples and rank ``rank`` takes its slice of each, so the ranks together see exactly the
    batches one process would with the global batch size (an incomplete last global batch is dropped).
    """

    def __init__(self, size: int, *, seed: int, shuffle: bool = True, rank: int = 0, world_size: int = 1,
                 batch_size: int = 1):
        self.size, self.seed, self.shuffle = size, seed, shuffle
        self.rank, self.world_size, self.batch_size = rank, world_size, batch_size
        self.epoch, self.start = 0, 0

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        self.epoch, self.start = epoch, start

    def order(self) -> list[int]:
        if not self.shuffle:
            return list(range(self.size))
        return np.random.default_rng([self.seed, self.epoch]).permutation(self.size).tolist()

    def __iter__(self):
        order = self.order()[self.start:]
        if self.world_size == 1:
            return iter(order)
        step, b = self.batch_size * self.world_size, self.batch_size
        return iter([i for g in range(0, len(order) - step + 1, step)
                     for i in order[g + self.rank * b: g + (self.rank + 1) * b]])

    def __len__(self) -> int:
        remaining = self.size - self.start
        if self.world_size == 1:
            return remaining
        return remaining // (self.batch_size * self.world_size) * self.batch_size


class RunSampler(Sampler[tuple[int, int]]):
    """``(epoch, index)`` pairs for a whole run: the orders of an :class:`EpochSampler`, epoch
    after epoch, from a position on, without end.

    One loader iterator (and its workers) then serves every epoch: nothing restarts at an
    epoch's end and the workers prepare the next epoch's first batches while the last ones
    train. Each epoch gives whole batches of ``batch_size`` only, so no batch mixes two
    epochs, and the dataset reads each sample's epoch from its pair (its image age, thinning
    and augmentation), not from a shared ``set_epoch``.
    """

    def __init__(self, epochs: EpochSampler, batch_size: int):
        self.epochs, self.batch_size = epochs, batch_size
        self.first, self.start = 0, 0

    def start_at(self, epoch: int, start: int = 0) -> None:
        """Begin at ``epoch``, ``start`` samples into its global order (a resumed run's position)."""
        self.first, self.start = int(epoch), int(start)

    def __iter__(self):
        epoch, start = self.first, self.start
        while True:
            self.epochs.set_epoch(epoch, start)
            order = list(self.epochs)
            for index in order[:len(order) // self.batch_size * self.batch_size]:
                yield epoch, index
            epoch, start = epoch + 1, 0


class ShardSampler(Sampler[int]):
    """Indices ``rank, rank + world_size, ...`` of ``size``, in order: one evaluation shard per rank."""

    def __init__(self, size: int, *, rank: int, world_size: int):
        self.size, self.rank, self.world_size = size, rank, world_size

    def __iter__(self):
        return iter(range(self.rank, self.size, self.world_size))

    def __len__(self) -> int:
        return len(range(self.rank, self.size, self.world_size))


def make_loader(dataset: EventEgoHands, *, batch_size: int, num_workers: int, sampler: Sampler | None = None,
                graph: EventGraphSpec | None = None, drop_last: bool = False, worker_nice: int = 0) -> DataLoader:
    """A loader with :func:`collate`; with ``graph`` (the model's own spec) its workers also build
    the event graph. Training passes a :class:`RunSampler`, whose ``(epoch, index)`` pairs carry
    each sample's epoch to the workers. The workers run one thread each, at ``worker_nice``
    lower CPU priority (see :func:`prepare_worker`)."""
    collate_fn = GraphCollate(graph) if graph is not None else collate
    return DataLoader(dataset, batch_size=batch_size, sampler=sampler, shuffle=False, num_workers=num_workers,
                      collate_fn=collate_fn, drop_last=drop_last, pin_memory=torch.cuda.is_available(),
                      worker_init_fn=partial(prepare_worker, nice=worker_nice) if num_workers else None)


def prepare_worker(_worker_id: int, nice: int = 0) -> None:
    """A loader worker shares the machine with the step: one thread, and ``nice`` lower priority.

    On few cores the step's threads wait for each other at every parallel region, so a worker
    holding a core slows the whole step; at a lower priority (Unix ``nice``) the workers take the
    cores while the step leaves them idle, and still get them all while it waits for data.
    """
    torch.set_num_threads(1)
    if nice and hasattr(os, "nice"):  # not on Windows
        os.nice(nice)
