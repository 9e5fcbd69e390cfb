"""The training entry: ``train(cfg)`` is what ``python train.py`` runs and what tests call.

It builds the datasets, the model (which owns the event-graph spec the loaders build graphs
with), the :class:`~dagr_lite.engine.state.TrainState`, then loops over epochs calling
:func:`~dagr_lite.engine.state.train_step`, saving ``last.pt`` and validating every
``trainer.val_every`` steps.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from dagr_lite.config import (TrainerSettings, build_dataset, build_model, build_optimizer, check_values,
                              resolve_config, trainer_settings)
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.engine.checkpoint import describe_dataset, load_checkpoint, save_checkpoint
from dagr_lite.engine.loading import EpochSampler, RunSampler, ShardSampler, make_loader
from dagr_lite.engine.runs import resolve_device, run_folder, seed_everything, write_run_files
from dagr_lite.engine.distributed import (Distributed, broadcast_object, cleanup, gather_objects, global_normaliser,
                                          mean_over_ranks, setup, synchronise_batch_norm)
from dagr_lite.engine.state import TrainState, train_step, validation_pass
from dagr_lite.eval.coco import METRIC_KEYS, format_metrics
from dagr_lite.eval.operating import NMS_IOUS, OperatingPoint, choose_operating_point
from dagr_lite.eval.score import render_sample
from dagr_lite.nn.warm_start import warm_start


class ResumeError(ValueError):
    """A checkpoint given as ``resume=`` does not fit this run; the message names both sides."""


@dataclass
class TrainData:
    """The datasets and loaders of a run; the loaders build graphs with the model's spec.
    Validation runs at each image age of ``valid_loaders`` (``data.image_age``, and for a model
    with an image also the largest training age)."""

    train_set: EventEgoHands
    sampler: RunSampler
    train_loader: DataLoader  # one iterator serves the whole run (see RunSampler)
    valid_loaders: dict[int, DataLoader]
    batch_size: int  # per process
    place: Distributed

    @property
    def global_batch_size(self) -> int:
        return self.batch_size * self.place.world_size

    @property
    def steps_per_epoch(self) -> int:
        """Whole global batches per epoch (an incomplete last one is dropped)."""
        return len(self.train_set) // self.global_batch_size


def validation_ages(cfg: DictConfig) -> list[int]:
    """``data.image_age``, and for a model with an image the largest training age too."""
    ages = {cfg.data.image_age}
    if cfg.model.use_image:
        ages.add(cfg.data.train_image_age[1])
    return sorted(ages)


def make_data(cfg: DictConfig, train_set: EventEgoHands, model, place: Distributed) -> TrainData:
    """The training loader (this rank's slice of each global batch), and one validation loader
    per validation age (this rank's shard)."""
    with_image = cfg.model.use_image
    valid_sets = {age: build_dataset(cfg, "valid", train=False, with_image=with_image, image_age=age)
                  for age in validation_ages(cfg)}
    if place.is_main:
        for dataset in (train_set, *valid_sets.values()):
            print(describe_dataset(dataset), flush=True)
    batch_size, workers = cfg.loader.batch_size, cfg.loader.num_workers
    global_batch = batch_size * place.world_size
    if len(train_set) < global_batch:
        raise ValueError(f"loader.batch_size={batch_size} x {place.world_size} processes, but the train split has "
                         f"{len(train_set)} samples: no batch can be made")
    sampler = RunSampler(EpochSampler(len(train_set), seed=cfg.seed, rank=place.rank, world_size=place.world_size,
                                      batch_size=batch_size), batch_size)
    nice = cfg.loader.worker_nice
    train_loader = make_loader(train_set, batch_size=batch_size, num_workers=workers, sampler=sampler,
                               graph=model.graph_spec, worker_nice=nice)
    valid_loaders = {age: make_loader(dataset, batch_size=batch_size, num_workers=workers, graph=model.graph_spec,
                                      sampler=ShardSampler(len(dataset), rank=place.rank, world_size=place.world_size)
                                      if place.enabled else None, worker_nice=nice)
                     for age, dataset in valid_sets.items()}
    return TrainData(train_set, sampler, train_loader, valid_loaders, batch_size, place)


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


def make_state(trainer: TrainerSettings, model, optimizer: torch.optim.Optimizer, steps_per_epoch: int,
               device: torch.device, clock: TrainingClock) -> TrainState:
    return TrainState.create(model, optimizer, total_steps=trainer.total_steps(steps_per_epoch),
                             warmup_steps=trainer.warmup_steps, min_lr_ratio=trainer.min_lr_ratio,
                             ema_decay=trainer.ema_decay, ema_tau=trainer.ema_tau, grad_clip=trainer.grad_clip,
                             amp=amp_dtype(trainer, device),
                             progress=clock.progress if clock.by_time else None)


def cpu_has_bfloat16() -> bool:
    """Whether this CPU computes in bfloat16 natively (AVX512-BF16 or AMX), so that bfloat16
    convolutions are faster than float32 ones; elsewhere they are emulated and slower."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)


def amp_dtype(trainer: TrainerSettings, device: torch.device) -> torch.dtype | None:
    """The mixed precision of a training step when ``trainer.amp`` (None: float32).

    CUDA: ``trainer.amp_dtype`` (``auto``: bfloat16 where the GPU supports it, else float16 with
    the gradient scaler). CPU: bfloat16 where the CPU has it natively (``auto`` or ``bfloat16``;
    float16 is not offered there), else float32. The sparse graph products and the losses run in
    float32 either way.
    """
    if not trainer.amp or device.type not in ("cuda", "cpu"):
        return None
    if device.type == "cpu":
        return torch.bfloat16 if trainer.amp_dtype in ("auto", "bfloat16") and cpu_has_bfloat16() else None
    if trainer.amp_dtype == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"float16": torch.float16, "bfloat16": torch.bfloat16}[trainer.amp_dtype]


def resume(state: TrainState, path: str | Path, checkpoints: Path, place: Distributed) -> dict:
    """Continue from checkpoint ``path``; its run's ``best.pt`` is carried into ``checkpoints`` (by
    rank 0), so the new run holds its best weights even when it never beats them. Returns the
    checkpoint (its ``position`` says where in the data it stopped)."""
    saved = load_checkpoint(path)
    ours, theirs = state.model.cfg.as_dict(), saved.detector.as_dict()
    if theirs != ours:
        differ = ", ".join(f"{key}: {theirs[key]!r} in the checkpoint, {ours[key]!r} here"
                           for key in ours if theirs[key] != ours[key])
        raise ResumeError(f"resume={path}: the checkpoint's model does not fit this run's ({differ})")
    state.load_state_dict(saved.training)
    best = Path(path).parent / "best.pt"
    if best.is_file():
        if place.is_main and best.resolve() != (checkpoints / "best.pt").resolve():
            checkpoints.mkdir(parents=True, exist_ok=True)
            shutil.copy2(best, checkpoints / "best.pt")
    else:
        state.best_metric = -math.inf  # nothing to carry: the first validation writes best.pt
    if place.is_main:
        print(f"resumed from {path} at step {state.step} (it ran on {saved.training.get('world_size', 1)} processes)",
              flush=True)
    return saved


class NullWriter:
    """What ranks other than 0 log to: nothing."""

    def add_scalar(self, *args, **kwargs) -> None:
        pass

    def add_image(self, *args, **kwargs) -> None:
        pass


class TrainLoop:
    """The epochs of one run: steps, logging, pictures, checkpoints and validation.

    Where it is in the data is ``(epoch, offset)``, the offset counting samples of the epoch's
    global order, so a run resumed on another number of processes goes on from the same sample.

    ``trainer.events_first`` = f > 0 (a hybrid): for the first fraction f of the schedule the
    hybrid learns from its events alone. Its weights that read image features start at zero
    (``Detector.zero_image_weights``) and the steps run with every image feature zero and the
    image branch idle (``train_step(image=False)``), so those weights stay zero and the hybrid
    is an events-only model inside the hybrid's layers, validated and saved as the hybrid it is.
    Then the image joins: the image branch and those weights learn from zero, as after
    ``init_from`` an events-only checkpoint, in one run.
    """

    def __init__(self, trainer: TrainerSettings, config: dict, state: TrainState, data: TrainData, run_dir: Path,
                 writer, clock: TrainingClock, position: dict | None = None):
        """``config``: the run's resolved config, recorded in every checkpoint; ``clock`` must be the
        one ``state``'s schedule reads (:func:`make_clock`, :func:`make_state`)."""
        self.trainer, self.config, self.state, self.data, self.writer = trainer, config, state, data, writer
        self.clock, self.resumed_position = clock, position
        self.place = data.place
        self.checkpoints = run_dir / "checkpoints"
        self.steps_per_epoch = data.steps_per_epoch
        self.epoch_samples = self.steps_per_epoch * data.global_batch_size  # of the global order, per epoch
        self.total = trainer.total_steps(self.steps_per_epoch)
        self.val_every = self.trainer.val_every or self.steps_per_epoch
        self.losses: list[float] = []
        self.metrics: dict | None = None
        self.operating: OperatingPoint | None = None  # chosen at each validation, saved with the weights
        if position is None:  # a fresh run, or a checkpoint from before positions were saved
            epoch, start = divmod(state.step, self.steps_per_epoch)
            position = {"epoch": epoch, "offset": start * data.global_batch_size}
        self.epoch, self.offset = int(position["epoch"]), int(position["offset"])
        if self.offset >= self.epoch_samples:  # saved after an epoch's last batch
            self.epoch, self.offset = self.epoch + 1, 0
        self.saved_at = time.monotonic()
        self.terminated = False  # set by SIGTERM (see run)
        self.events_first = trainer.events_first
        self.in_phase = self.events_phase()

    def events_phase(self) -> bool:
        """Whether the next step is in the ``trainer.events_first`` phase: how far along the schedule
        is, by steps (and by the time budget with ``schedule_by=time``, whichever is further)."""
        if not self.events_first:
            return False
        done = self.state.step / max(1, self.total)
        if self.clock.by_time:
            done = max(done, self.clock.progress())
        return done < self.events_first

    def run(self) -> dict:
        """Train to the end of the schedule (or ``trainer.max_minutes``); a SIGTERM (a cluster's
        notice of preemption, ``kill``'s default) ends it after the step under way, with
        ``last.pt`` saved, by raising :class:`Terminated`."""
        if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
            return self._run()

        def note(signum, frame):
            self.terminated = True

        previous = signal.signal(signal.SIGTERM, note)
        try:
            return self._run()
        finally:
            signal.signal(signal.SIGTERM, previous)

    def _run(self) -> dict:
        state = self.state
        self.clock.start(self.resumed_position, state.step)
        by_time = self.clock.by_time  # then the bar counts steps and shows the time left
        bar = tqdm(total=None if by_time else self.total, initial=state.step, desc="training", unit="step",
                   disable=not self.place.is_main)
        if state.step >= self.total or self.clock.spent():  # resumed at the end
            bar.close()
            return self.metrics if self.metrics is not None else self.save_and_validate()
        self.data.sampler.start_at(self.epoch, self.offset)
        for batch in self.data.train_loader:  # every epoch from here on, one iterator
            batch = batch.to(state.device, non_blocking=True)
            out = mean_over_ranks(train_step(state, batch, image=not self.events_phase()), self.place)
            self.offset += self.data.global_batch_size
            if self.offset >= self.epoch_samples:
                self.epoch, self.offset = self.epoch + 1, 0
            self.losses.append(float(out["loss"]))
            if self.events_first and self.place.is_main and not self.events_phase() and self.in_phase:
                print(f"step {state.step}: the image joins (trainer.events_first={self.events_first})", flush=True)
            self.in_phase = self.events_phase()
            bar.update(1)
            bar.set_postfix(loss=f"{self.losses[-1]:.3f}", lr=f"{state.lr:.2e}",
                            **({"left": f"{self.clock.left_s():.0f}s"} if by_time else {}))
            self.log(out, batch)
            if broadcast_object(self.terminated, self.place):
                self.stop_on_signal(bar)
            out_of_time = self.out_of_time()
            if state.step % self.val_every == 0 or state.step == self.total or out_of_time:
                self.save_and_validate()
            elif self.checkpoint_due():
                self.save("last.pt")
            if state.step >= self.total or out_of_time:
                break
        bar.close()
        return self.metrics

    def stop_on_signal(self, bar) -> None:
        self.save("last.pt")
        bar.close()
        path = self.checkpoints / "last.pt"
        if self.place.is_main:
            print(f"SIGTERM: stopped after step {self.state.step} and saved {path}; continue with resume={path}",
                  flush=True)
        raise Terminated(f"stopped by SIGTERM after step {self.state.step} ({path} saved)")

    def out_of_time(self) -> bool:
        """Whether ``trainer.max_minutes`` is spent: by this process (``schedule_by=steps``), or by the
        whole run, the time before a resume included (``schedule_by=time``). Every rank reads the
        same clock, so every rank stops at the same step."""
        elapsed = self.clock.tick(self.state.step, self.place)
        if self.clock.by_time:
            self.state.refresh_lr()  # the next step's rate from this reading, not the one before the step
        minutes = self.trainer.max_minutes
        spent = elapsed if self.clock.by_time else elapsed - self.clock.before_s
        over = minutes is not None and spent > 60 * minutes
        if over and self.place.is_main:
            print(f"trainer.max_minutes={minutes} reached at step {self.state.step}", flush=True)
        return over

    def checkpoint_due(self) -> bool:
        """``last.pt`` is due every ``trainer.checkpoint_every`` steps or ``trainer.checkpoint_minutes``."""
        every, minutes = self.trainer.checkpoint_every, self.trainer.checkpoint_minutes
        due = bool(every) and self.state.step % every == 0
        if minutes:
            due = due or bool(broadcast_object(time.monotonic() - self.saved_at > 60 * minutes, self.place))
        return due

    def log(self, out: dict, batch) -> None:
        step = self.state.step
        if step % self.trainer.log_every == 0 or step == self.total:
            for key, value in out.items():
                self.writer.add_scalar(f"train/{key}", float(value), step)
            self.writer.add_scalar("train/lr", self.state.lr, step)
        if self.place.is_main and self.trainer.image_every and step % self.trainer.image_every == 0:
            ema = self.state.ema.module.eval()
            with torch.no_grad():
                detections = ema(batch, conf_threshold=self.trainer.conf_threshold,
                                 nms_threshold=self.trainer.nms_threshold)
            self.writer.add_image("train/sample", render_sample(batch, 0, detections[0]), step, dataformats="HWC")

    def checkpoint(self) -> dict:
        return {**self.state.state_dict(), "detector": self.state.model.cfg.as_dict(), "config": self.config,
                "operating": None if self.operating is None else self.operating.as_dict(),
                "world_size": self.place.world_size, "global_batch_size": self.data.global_batch_size,
                "position": {"epoch": self.epoch, "offset": self.offset, **self.clock.position()}}

    def save(self, name: str) -> None:
        """Rank 0 writes ``checkpoints/<name>`` (all ranks hold the same weights)."""
        if self.place.is_main:
            save_checkpoint(self.checkpoints / name, self.checkpoint())
        self.saved_at = time.monotonic()

    def save_and_validate(self) -> dict:
        """Validate at each validation age, choose the operating point, then save ``last.pt`` (with
        both) and ``best.pt`` when the mean mAP over the ages improves. A validation that fails
        saves ``last.pt`` before the error goes on: no training is lost.

        The returned metrics are those of the first age (``data.image_age``), with ``mAP_age<a>``,
        ``AP50_age<a>`` for every age and their ``mAP_mean``.
        """
        state = self.state
        try:
            per_age, self.operating = self.validate_ages()
        except BaseException:
            self.save("last.pt")
            raise
        metrics = dict(per_age[self.trainer.image_age])
        for age, values in per_age.items():
            metrics.update({f"mAP_age{age}": values["mAP"], f"AP50_age{age}": values["AP50"]})
        metrics["mAP_mean"] = sum(values["mAP"] for values in per_age.values()) / len(per_age)
        for key in ("mAP", "AP50", "AP75", "mAP_mean", *(f"{m}_age{a}" for a in per_age for m in ("mAP", "AP50"))):
            self.writer.add_scalar(f"val/{key}", metrics[key], state.step)
        improved = metrics["mAP_mean"] > state.best_metric or not (self.checkpoints / "best.pt").exists()
        state.best_metric = max(state.best_metric, metrics["mAP_mean"])
        self.save("last.pt")
        if improved:
            self.save("best.pt")
        if self.place.is_main:
            ages = "  ".join(f"age {a}: mAP {v['mAP']:.4f} AP50 {v['AP50']:.4f}" for a, v in per_age.items())
            print(f"step {state.step}: val {ages}; operating point {self.operating.describe()}", flush=True)
        self.metrics = metrics
        return metrics

    def validate_ages(self) -> tuple[dict[int, dict], OperatingPoint]:
        """The EMA's COCO metrics at each validation age, and the operating point chosen over all of them."""
        trainer = self.trainer
        gather = self.gather_shards if self.place.enabled else None
        per_age, candidates = {}, {iou: [] for iou in NMS_IOUS}
        for age, loader in self.data.valid_loaders.items():
            per_age[age], by_nms = validation_pass(
                self.state, loader, backend=trainer.eval_backend, conf_threshold=trainer.conf_threshold,
                nms_threshold=trainer.nms_threshold, progress=self.place.is_main, gather=gather)
            for iou, entries in by_nms.items():
                candidates[iou].extend(entries)
        chosen_on = f"valid, image age {' and '.join(map(str, per_age))}"
        return per_age, choose_operating_point(candidates, chosen_on=chosen_on)

    def gather_shards(self, entries: list) -> list:
        """Every rank's validation entries, back in the dataset's order (rank ``r`` holds samples
        ``r, r + N, ...``)."""
        shards = gather_objects(entries, self.place)
        return [shard[i] for i in range(max(len(x) for x in shards)) for shard in shards if i < len(shard)]


def budget_overrides(minutes: float, steps: int | None = None) -> list[str]:
    """Config overrides that train for ``minutes`` of wall time, or ``steps`` steps if given
    (still capped by the minutes): what the tools that train to a time budget pass. The learning
    rate's cosine follows whichever of the two budgets is further along, so it ends decayed."""
    length = [f"trainer.max_steps={steps}"] if steps else ["trainer.max_steps=null", "trainer.max_epochs=100000"]
    return [f"trainer.max_minutes={minutes}", "trainer.schedule_by=time", *length]


class Terminated(SystemExit):
    """Training stopped by SIGTERM with ``last.pt`` saved; exits with status 143 (128 + SIGTERM)."""

    def __init__(self, message: str):
        super().__init__(143)
        self.message = message

    def __str__(self) -> str:
        return self.message


def train(cfg: DictConfig) -> dict:
    """Train the configured detector; returns the final validation metrics, the run folder and the
    per-step training losses. Launched by ``torchrun``, every process runs this together."""
    cfg = resolve_config(cfg)
    check_values(cfg)
    if cfg.get("init_from") is not None and not Path(cfg.init_from).is_file():  # before the run folder is made
        raise FileNotFoundError(f"init_from={cfg.init_from}: checkpoint file is missing")
    place = Distributed.from_environment()
    device = setup(place, resolve_device(cfg.device))
    try:
        return _train(cfg, place, device)
    finally:
        cleanup(place)


def shared_run_folder(cfg: DictConfig, place: Distributed) -> tuple[Path, Path | None]:
    """The run folder, checked by rank 0 and shared with every rank (nothing is written yet:
    :func:`_train` makes it once the data, model and state are built), and the checkpoint to
    resume from: ``resume=``, or, when torchrun restarts a failed group, the run's own ``last.pt``."""
    restarted = int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0") or 0) > 0
    outcome = None
    if place.is_main:
        try:
            own = own_last_checkpoint(cfg) if restarted else None
            outcome = ("ok", str(own.parent.parent if own else run_folder(cfg, "train", make=False)), own and str(own))
        except Exception as err:  # rank 0 refuses the run: every rank must stop, not wait
            outcome = ("error", f"{type(err).__name__}: {err}", None)
            broadcast_object(outcome, place)
            raise
    outcome = broadcast_object(outcome, place)
    if outcome[0] == "error":
        raise RuntimeError(f"rank 0 refused the run: {outcome[1]}")
    resume_from = outcome[2] or cfg.resume
    return Path(outcome[1]), Path(resume_from) if resume_from else None


def own_last_checkpoint(cfg: DictConfig) -> Path | None:
    """This run's ``checkpoints/last.pt`` when its folder already holds one (a restarted group)."""
    if cfg.get("run_dir"):
        folder = Path(cfg.run_dir)
    else:
        from hydra.core.hydra_config import HydraConfig
        folder = Path(HydraConfig.get().runtime.output_dir)
    last = folder / "checkpoints" / "last.pt"
    return last if last.is_file() else None


def start_weights(cfg: DictConfig, resume_from: Path | None) -> str | None:
    """The checkpoint ``init_from`` names, when this run starts from it: not when it resumes (a
    run restarted in its own folder continues from its own ``last.pt``, which holds what training
    made of those weights; ``check_values`` refuses ``init_from`` beside ``resume``)."""
    path = cfg.get("init_from")
    return None if path is None or resume_from is not None else str(path)


def start_from(model, path: str | Path, *, verbose: bool = True) -> dict:
    """Start ``model`` from the weights of checkpoint ``path`` (its EMA weights, the ones it was
    validated with) that fit, :func:`~dagr_lite.nn.warm_start.warm_start`."""
    saved = load_checkpoint(path)
    report = warm_start(model, saved.weights)
    if not report["copied"] and not report["widened"]:
        raise ValueError(f"init_from={path}: no weight of that checkpoint ({saved.model_name}) fits this model; "
                         "nothing to start from")
    if verbose:
        print(f"init_from {path}: {len(report['copied'])} tensors copied, {len(report['widened'])} widened "
              f"with zeros, {len(report['kept'])} at their own initialisation", flush=True)
    return report


def _train(cfg: DictConfig, place: Distributed, device: torch.device) -> dict:
    if place.is_main:
        print(OmegaConf.to_yaml(cfg), flush=True)
    run_dir, resume_from = shared_run_folder(cfg, place)
    seed_everything(cfg.seed)
    train_set = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
    model = build_model(cfg, height=train_set.image_size[0], width=train_set.image_size[1]).to(device)
    init_from = start_weights(cfg, resume_from)
    if init_from is not None:
        start_from(model, init_from, verbose=place.is_main)
    trainer = trainer_settings(cfg)
    if trainer.events_first and resume_from is None:  # the image's weights start at zero (see TrainLoop)
        model.zero_image_weights()
    if place.enabled:
        model = synchronise_batch_norm(model, device)
        model.loss_normaliser = global_normaliser(place)
    data = make_data(cfg, train_set, model, place)
    clock = make_clock(trainer)
    state = make_state(trainer, model, build_optimizer(cfg, model.parameters()), data.steps_per_epoch, device, clock)
    if place.is_main:
        precision = "float32" if state.amp_dtype is None else f"mixed precision {str(state.amp_dtype).split('.')[-1]}"
        print(f"training on {device} in {precision}", flush=True)
    saved = resume(state, resume_from, run_dir / "checkpoints", place) if resume_from else None
    if place.is_main and not (run_dir / "config.yaml").exists():  # all checked: the run folder is made now
        write_run_files(run_dir, cfg)
    if place.enabled:
        state.forward = DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None,
                                                find_unused_parameters=bool(trainer.events_first))  # the image branch
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
