"""Loading samples for a run: the samplers (epochs, runs of frames, shards) and the data loader."""
from __future__ import annotations

import os
from functools import partial

import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from dagr_lite.data.collate import GraphCollate, collate
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.graph.spec import EventGraphSpec


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


def batch_maker(graph: EventGraphSpec | None):
    """What makes a batch of samples: :func:`collate`, or with ``graph`` (a model's own spec) a
    :class:`GraphCollate` that also builds the event graph."""
    return GraphCollate(graph) if graph is not None else collate


def make_loader(dataset: EventEgoHands, *, batch_size: int, num_workers: int, sampler: Sampler | None = None,
                graph: EventGraphSpec | None = None, drop_last: bool = False, worker_nice: int = 0) -> DataLoader:
    """A loader with :func:`collate`; with ``graph`` (the model's own spec) its workers also build
    the event graph. Training passes a :class:`RunSampler`, whose ``(epoch, index)`` pairs carry
    each sample's epoch to the workers. The workers run one thread each, at ``worker_nice``
    lower CPU priority (see :func:`prepare_worker`)."""
    collate_fn = batch_maker(graph)
    return DataLoader(dataset, batch_size=batch_size, sampler=sampler, shuffle=False, num_workers=num_workers,
                      collate_fn=collate_fn, drop_last=drop_last, pin_memory=torch.cuda.is_available(),
                      worker_init_fn=partial(prepare_worker, nice=worker_nice) if num_workers else None)


def prepare_worker(_worker_id: int, nice: int = 0) -> None:
    """A loader worker shares the machine with the step: one thread, and ``nice`` lower priority;
    it runs in a process group of its own (below).

    On few cores the step's threads wait for each other at every parallel region, so a worker
    holding a core slows the whole step; at a lower priority (Unix ``nice``) the workers take the
    cores while the step leaves them idle, and still get them all while it waits for data.
    """
    torch.set_num_threads(1)
    if nice and hasattr(os, "nice"):  # not on Windows
        os.nice(nice)
    if hasattr(os, "setpgrp"):  # not on Windows
        # A process group of its own: a signal to the trainer's group (a scheduler's or `timeout`'s
        # SIGTERM) reaches the main process alone, which stops after its step, saves last.pt and
        # shuts the workers down; a worker killed by it first would fail the save. (A terminal's
        # Ctrl-C then reaches the main process alone too, which saves the same way.)
        os.setpgrp()
