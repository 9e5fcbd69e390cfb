"""The epochs of a run: its data (:class:`TrainData`), and the loop of steps, logging, pictures,
checkpoints, validation and the operating point (:class:`TrainLoop`)."""
from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig
from torch.utils.data import DataLoader, Subset

from dagr_lite.errors import UserError
from dagr_lite.config import PHASE_STEP, ConfigError, TrainerSettings, build_dataset
from dagr_lite.data.collate import GraphCollate
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.engine.checkpoint import describe_dataset, save_checkpoint
from dagr_lite.engine.clock import TrainingClock, make_clock
from dagr_lite.engine.distributed import Distributed, broadcast_object, gather_objects, mean_over_ranks
from dagr_lite.engine.loading import EpochSampler, RunSampler, ShardSampler, make_loader
from dagr_lite.engine.state import TrainState, train_step, validation_pass
from dagr_lite.eval.operating import NMS_IOUS, OperatingPoint, choose_operating_point
from dagr_lite.eval.score import render_sample
from dagr_lite.progress import progress_bar, say


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
        return epoch_steps(len(self.train_set), self.global_batch_size)


def epoch_steps(samples: int, global_batch: int) -> int:
    """Whole global batches per epoch of ``samples`` training samples (an incomplete last one is dropped)."""
    return samples // global_batch


def validation_ages(cfg: DictConfig) -> list[int]:
    """``data.image_age``, and for a model with an image the largest training age too."""
    ages = {cfg.data.image_age}
    if cfg.model.use_image:
        ages.add(cfg.data.train_image_age[1])
    return sorted(ages)


def spread_subset(dataset, count: int):
    """``count`` samples of ``dataset`` spread evenly over it (samples ``i * len // count``), in
    order; the dataset itself when it holds no more."""
    if count >= len(dataset):
        return dataset
    return Subset(dataset, [i * len(dataset) // count for i in range(count)])


def schedule_done(step: int, total: int, clock: TrainingClock) -> float:
    """How far along the schedule a run is at ``step`` of ``total``: by steps, and by the time
    budget with ``schedule_by=time``, whichever is further (a first phase ends by it)."""
    done = step / max(1, total)
    return max(done, clock.progress()) if clock.by_time else done


def resumed_done(trainer: TrainerSettings, training: dict, steps_per_epoch: int) -> float:
    """:func:`schedule_done` where a checkpoint's run stopped (its ``training`` state and position)."""
    step = int(training["step"])
    clock = make_clock(trainer)
    clock.start(training.get("position"), step)
    return schedule_done(step, trainer.total_steps(steps_per_epoch), clock)


def make_data(cfg: DictConfig, train_set: EventEgoHands, model, place: Distributed) -> TrainData:
    """The training loader (this rank's slice of each global batch), and one validation loader
    per validation age (this rank's shard)."""
    with_image = cfg.model.use_image
    valid_sets = {}
    for age in validation_ages(cfg):
        try:
            valid_sets[age] = build_dataset(cfg, "valid", train=False, with_image=with_image, image_age=age)
        except ConfigError as err:  # videos shorter than the largest training age: validate at the first
            if age == cfg.data.image_age:
                raise
            if place.is_main:
                print(f"validation at image age {age} left out: {err}", flush=True)
    if place.is_main:
        for dataset in (train_set, *valid_sets.values()):
            print(describe_dataset(dataset, image=cfg.model.use_image, events=cfg.model.use_events), flush=True)
    limit = cfg.trainer.get("val_samples")
    if limit is not None:
        valid_sets = {age: spread_subset(dataset, int(limit)) for age, dataset in valid_sets.items()}
        if place.is_main:
            print(f"validating on {len(next(iter(valid_sets.values())))} samples at each age (trainer.val_samples)",
                  flush=True)
    batch_size, workers = cfg.loader.batch_size, cfg.loader.num_workers
    global_batch = batch_size * place.world_size
    if len(train_set) < global_batch:
        raise UserError(f"loader.batch_size={batch_size} x {place.world_size} processes, but the train split has "
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


class NullWriter:
    """What ranks other than 0 log to: nothing."""

    def add_scalar(self, *args, **kwargs) -> None:
        pass

    def add_image(self, *args, **kwargs) -> None:
        pass


class Terminated(SystemExit):
    """Training stopped by SIGTERM or Ctrl-C with ``last.pt`` saved; exits with status 128 + the
    signal's number (143, 130)."""

    def __init__(self, message: str, code: int = 128 + signal.SIGTERM):
        super().__init__(code)
        self.message = message

    def __str__(self) -> str:
        return self.message


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
    ``init_from`` an events-only checkpoint, in one run. ``trainer.image_first`` = f is the
    same the other way round: the image learns alone (``Detector.zero_event_weights``,
    ``train_step(events=False)``: event and recency maps zero, the event branch idle), then the
    events join. ``trainer.dense_first`` = f: the hybrid learns without its event graph
    (``Detector.zero_graph_weights``, ``train_step(graph=False)``: the event branch idle and its
    maps zero, the recency maps and a carry branch as always), and the loader's workers build no
    graph in the phase (:attr:`GraphCollate.building`), so a step costs what a dense model's does;
    then the graph joins, every step from there on with its batch's graph (one made before the
    switch gets it built here).
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
        self.terminated: signal.Signals | None = None  # set by SIGTERM or a first Ctrl-C (see run)
        # A first phase: one branch alone, or the dense parts without the graph (at most one, checked with the config).
        self.first_key = trainer.first_phase or "events_first"
        self.first_fraction = getattr(trainer, self.first_key)
        self.alone = PHASE_STEP[self.first_key]  # train_step's flags in the phase
        self.in_phase = False  # whether the next step is in that phase (set as the loop runs)
        collate = data.train_loader.collate_fn
        # dense_first: the loader's graph, switched off in the phase
        self.graphs = collate if trainer.dense_first and isinstance(collate, GraphCollate) else None

    def first_phase(self) -> bool:
        """Whether the next step is in the ``trainer.events_first``, ``image_first`` or ``dense_first`` phase: how far
        along the schedule is, by steps (and by the time budget with ``schedule_by=time``,
        whichever is further)."""
        if not self.first_fraction:
            return False
        return schedule_done(self.state.step, self.total, self.clock) < self.first_fraction

    def run(self) -> dict:
        """Train to the end of the schedule (or ``trainer.max_minutes``); a SIGTERM (a cluster's
        notice of preemption, ``kill``'s default) or a first Ctrl-C ends it after the step under
        way, with ``last.pt`` saved, by raising :class:`Terminated`; a second Ctrl-C stops at once."""
        if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
            return self._run()
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}

        def note(signum, frame):
            self.terminated = signal.Signals(signum)
            if signum == signal.SIGINT:  # the next Ctrl-C is Python's: a KeyboardInterrupt at once
                signal.signal(signal.SIGINT, previous[signal.SIGINT])
                if self.place.is_main:
                    print("\nCtrl-C: stopping after this step and saving last.pt (Ctrl-C again: at once, unsaved)",
                          flush=True)

        for sig in previous:
            signal.signal(sig, note)
        try:
            return self._run()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _run(self) -> dict:
        state = self.state
        self.clock.start(self.resumed_position, state.step)
        self.first_step = self.read_at_step = state.step  # this process's first (a resumed run's step), last read
        self.in_phase = self.first_phase()  # the first step's
        if self.graphs is not None:
            self.graphs.building = not self.in_phase
        by_time = self.clock.by_time  # then the bar counts steps and shows the time left
        bar = progress_bar(total=None if by_time else self.total, initial=state.step, desc="training", unit="step",
                           disable=not self.place.is_main)
        if state.step >= self.total or self.clock.spent():  # resumed at the end
            bar.close()
            if self.place.is_main:
                limit = (f"its length of {self.total} steps" if state.step >= self.total
                         else "its trainer.max_minutes")
                say(f"step {state.step} is at or past {limit}: nothing to train (raise trainer.max_steps, "
                    "max_epochs or max_minutes to go on)")
            return self.metrics if self.metrics is not None else self.save_and_validate()
        self.data.sampler.start_at(self.epoch, self.offset)
        for batch in self.data.train_loader:  # every epoch from here on, one iterator
            in_phase = self.in_phase  # this step's phase, read once
            if self.graphs is not None and not in_phase:
                batch = self.graphs.complete(batch)  # one the workers made before the graph joined
            batch = batch.to(state.device, non_blocking=True)
            out = mean_over_ranks(train_step(state, batch, **(self.alone if in_phase else {})), self.place)
            self.offset += self.data.global_batch_size
            if self.offset >= self.epoch_samples:
                self.epoch, self.offset = self.epoch + 1, 0
            self.losses.append(float(out["loss"]))
            bar.set_postfix(loss=f"{self.losses[-1]:.3f}", lr=f"{state.lr:.2e}", refresh=False,  # drawn with the count
                            **({"left": f"{self.time_left_s():.0f}s"} if by_time else {}))
            bar.update(1)
            self.log(out, batch)
            stopped = broadcast_object(self.terminated, self.place)
            if stopped:
                self.stop_on_signal(bar, signal.Signals(stopped))
            out_of_time = self.read_clock()
            self.in_phase = self.first_phase()  # the next step's, from this reading
            if self.graphs is not None:
                self.graphs.building = not self.in_phase
            if in_phase and not self.in_phase and self.place.is_main:
                joins = {"events_first": "the image joins", "image_first": "the events join",
                         "dense_first": "the graph joins"}[self.first_key]
                say(f"step {state.step}: {joins} (trainer.{self.first_key}={self.first_fraction})")
            if state.step % self.val_every == 0 or state.step == self.total or out_of_time:
                self.save_and_validate()
            elif self.checkpoint_due():
                self.save("last.pt")
            if state.step >= self.total or out_of_time:
                break
        bar.close()
        return self.metrics

    def time_left_s(self) -> float:
        """The run's time left at the clock's last reading: its budget's, or less where its steps
        (``max_steps`` / ``max_epochs``) end it first at the pace of this process's steps so far."""
        left = self.clock.left_s()
        made = self.read_at_step - self.first_step  # steps in the clock's last reading
        if made > 0:
            pace = (self.clock.elapsed_s - self.clock.before_s) / made
            left = min(left, pace * max(0, self.total - self.read_at_step))
        return left

    def stop_on_signal(self, bar, sig: signal.Signals = signal.SIGTERM) -> None:
        self.save("last.pt")
        bar.close()
        path = self.checkpoints / "last.pt"
        name = "Ctrl-C" if sig == signal.SIGINT else sig.name
        if self.place.is_main:
            print(f"{name}: stopped after step {self.state.step} and saved {path}; continue with: python train.py "
                  f"resume={path} (the run's settings come back from its overrides.yaml; it goes on in its folder)",
                  flush=True)
        raise Terminated(f"stopped by {name} after step {self.state.step} ({path} saved)", 128 + int(sig))

    def read_clock(self) -> bool:
        """Read the run's clock after a step and, with ``schedule_by=time``, set the next step's
        learning rate from the reading. Returns True when ``trainer.max_minutes`` is spent: by this
        process (``schedule_by=steps``), or by the whole run, the time before a resume included
        (``schedule_by=time``). Every rank reads the same clock, so every rank stops at the same step."""
        elapsed = self.clock.tick(self.state.step, self.place)
        self.read_at_step = self.state.step
        if self.clock.by_time:
            self.state.refresh_lr()  # the next step's rate from this reading, not the one before the step
        minutes = self.trainer.max_minutes
        spent = elapsed if self.clock.by_time else elapsed - self.clock.before_s
        over = minutes is not None and spent > 60 * minutes
        if over and self.place.is_main:
            say(f"trainer.max_minutes={minutes} reached at step {self.state.step}")
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
        return {**self.state.state_dict(), "detector": self.state.detector_cfg.as_dict(), "config": self.config,
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
            say(f"step {state.step}: val {ages}; operating point {self.operating.describe()}")
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
