"""The run's training clock: the time a run has trained, read the same on every rank, which a
time-budgeted schedule follows and ``trainer.max_minutes`` stops."""
from __future__ import annotations

import time

from dagr_lite.config import TrainerSettings
from dagr_lite.engine.distributed import Distributed, broadcast_object


class TrainingClock:
    """The run's training time in seconds: the time before a resume (saved in the checkpoint's
    ``position``) plus this process's since its loop started, as rank 0 reads it (broadcast, so
    every rank holds the same value).

    With ``trainer.schedule_by=time`` the learning rate's cosine also follows it: after the
    ``warmup`` steps, :meth:`progress` is the fraction of the ``budget_s`` left at the warm-up's end
    that is spent since, and the run stops when the whole budget is spent, the time before a
    resume included.
    """

    now = staticmethod(time.monotonic)  # the reading (tests replace it)

    def __init__(self, budget_s: float | None = None, warmup: int = 0):
        self.budget_s, self.warmup = budget_s, warmup
        self.before_s = self.elapsed_s = 0.0
        self.warmup_end_s: float | None = None
        self.started = self.now()

    @property
    def by_time(self) -> bool:
        return self.budget_s is not None

    def start(self, position: dict | None, step: int) -> None:
        """Begin this process's count at ``step``, after the time a resumed run had spent (``position``)."""
        position = position or {}
        self.before_s = self.elapsed_s = float(position.get("elapsed_s", 0.0))
        warmup_end = position.get("warmup_end_s")
        self.warmup_end_s = None if warmup_end is None else float(warmup_end)
        if self.warmup_end_s is None and step >= self.warmup:  # no warm-up (or one finished before)
            self.warmup_end_s = self.elapsed_s
        self.started = self.now()

    def tick(self, step: int, place: Distributed) -> float:
        """Read the clock after step ``step`` (on every rank at once); returns the training time."""
        self.elapsed_s = self.before_s + float(broadcast_object(self.now() - self.started, place))
        if self.warmup_end_s is None and step >= self.warmup:
            self.warmup_end_s = self.elapsed_s
        return self.elapsed_s

    def progress(self) -> float:
        """Fraction of the time budget spent since the warm-up ended (0 without a budget or before)."""
        if self.budget_s is None or self.warmup_end_s is None:
            return 0.0
        left = self.budget_s - self.warmup_end_s
        return 1.0 if left <= 0 else (self.elapsed_s - self.warmup_end_s) / left

    def spent(self) -> bool:
        """Whether the time budget is spent (never without one)."""
        return self.budget_s is not None and self.elapsed_s > self.budget_s

    def left_s(self) -> float:
        """Seconds of the budget left at the last reading (0 without a budget)."""
        return max(0.0, self.budget_s - self.elapsed_s) if self.budget_s is not None else 0.0

    def position(self) -> dict:
        return {"elapsed_s": self.elapsed_s, "warmup_end_s": self.warmup_end_s}


def make_clock(trainer: TrainerSettings) -> TrainingClock:
    """The run's clock; with ``trainer.schedule_by=time`` it carries the ``trainer.max_minutes`` budget."""
    budget = 60.0 * trainer.max_minutes if trainer.by_time else None
    return TrainingClock(budget, warmup=trainer.warmup_steps)
