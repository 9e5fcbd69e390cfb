"""Training-step speed and memory of each model variant, split into its parts.

    python benchmarks/train_step.py [--steps 6] [--events 50000] [--batch 16] [--workers 2] [--worker-nice 19]
                                    [--device auto] [--channels-last auto]

For each variant (hybrid, events_only, image_only) at 320x180 and 640x360, trains ``--steps``
steps on synthetic samples (a rendered hand scene as the image, ``--events`` events per sample
from moving blob outlines plus noise) through the same loader the trainer uses (``--workers``
worker processes that also build the event graph, at the trainer's lower priority
``loader.worker_nice`` unless ``--worker-nice`` says otherwise). Prints per step: time waiting for data
(loading + graph building, as the training loop sees it), forward, backward + optimiser step,
samples per second, and the peak resident memory of the training process; and, for reference,
the graph building time of one batch in a single process. The check: waiting for data must
stay below a third of a step.

Then the same steps again on batches loaded beforehand (no workers running): the step's own
compute. Its ratio to the step with the workers is what the loader costs when it shares the
cores with the step (on few cores the workers' graph building slows the step's own threads,
even while no time is spent waiting for data).

The model, its weights' layout (``trainer.channels_last``) and its optimiser (the fused AdamW)
are the trainer's defaults; a hybrid with a carry branch (the default) reads a picture of each
sample's events beside its frame. Every step runs in the trainer's precision: on CUDA bfloat16
where the GPU has it (float16 elsewhere, here without the trainer's gradient scaler, which
barely changes the time), on a CPU bfloat16 where the CPU has it natively, else float32.
``--device auto`` runs on CUDA when present; times are then taken after
``torch.cuda.synchronize()`` and the peak GPU memory of each variant is printed too. ``benchmarks/cpu_step.py`` compares the two precisions on a CPU.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np
import torch
from torch.utils.data import Dataset

from dagr_lite.data import format as fmt
from dagr_lite.data.collate import GraphCollate
from dagr_lite.data.dataset import Sample, channels_first, event_picture
from dagr_lite.engine.loading import make_loader
from dagr_lite.engine.runs import resolve_device
from dagr_lite.engine.precision import amp_dtype, memory_format
from dagr_lite.config import build_model, build_optimizer, compose_config, resolve_config, trainer_settings
from dagr_lite.synth.stub import HandScene

WINDOW_US = fmt.DEFAULT_WINDOW_US


class SyntheticSamples(Dataset):
    """Samples with a rendered frame, ``events`` events and the scene's boxes (cheap to make).

    ``carry_recent_us`` (None: none): the frame gains a picture of the sample's events (as a hybrid
    with a carry branch reads it, ``data.carry_picture``; its span the horizon, its recent window
    this long), made by the dataset's own :func:`~dagr_lite.data.dataset.event_picture`."""

    def __init__(self, height: int, width: int, events: int, size: int = 64, carry_recent_us: int | None = None):
        self.height, self.width, self.events, self.size = height, width, events, size
        self.carry_recent_us = carry_recent_us
        scene = HandScene(0, height=height, width=width)
        self.frames = [np.clip(scene.frame(k), 0, 255).astype(np.uint8) for k in range(8)]
        self.boxes = [torch.from_numpy(np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], 1)).float()
                      for b in (scene.boxes(k) for k in range(8))]

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, index: int) -> Sample:
        rng = np.random.default_rng(index)
        n = self.events
        blobs = rng.uniform([40, 40], [self.width - 40, self.height - 40], (8, 2))
        which = rng.integers(0, 8, n)
        t = np.sort(rng.uniform(0, WINDOW_US, n))
        angle = rng.uniform(0, 2 * np.pi, n)
        xy = blobs[which] + np.stack([np.cos(angle), np.sin(angle)], 1) * rng.uniform(10, 30, (n, 1))
        xy[: n // 10] = rng.uniform([0, 0], [self.width, self.height], (n // 10, 2))
        xy = np.clip(np.round(xy), 0, [self.width - 1, self.height - 1])
        events = np.concatenate([xy, t[:, None], rng.integers(0, 2, (n, 1))], 1).astype(np.float32)
        k = index % 8
        parts = [self.frames[k]]
        if self.carry_recent_us is not None:
            parts.append(event_picture(xy[:, 0].astype(np.int64), xy[:, 1].astype(np.int64), t, events[:, 3], WINDOW_US,
                                       WINDOW_US, self.height, self.width, self.carry_recent_us))
        return Sample(events=torch.from_numpy(events), image=torch.from_numpy(channels_first(parts)),
                      boxes=self.boxes[k], labels=torch.zeros(len(self.boxes[k]), dtype=torch.int64),
                      video="bench", frame=index, image_frame=index, t_start_us=0, t_end_us=WINDOW_US, t_image_us=0)


def sync(device: torch.device) -> None:
    """Wait for the device's queued work, so a wall-clock reading covers it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def step_on(model, optimizer, batch, args) -> tuple[float, float]:
    """One training step on ``batch``, moved to ``args.device``, in the mixed precision ``args.amp``
    (the trainer's, or None): (forward, backward + optimiser) seconds."""
    device, dtype = args.device, args.amp
    start = time.perf_counter()
    batch = batch.to(device, non_blocking=True)
    with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
        out = model(batch)
    sync(device)
    forwarded = time.perf_counter()
    optimizer.zero_grad()
    out["loss"].float().backward()
    optimizer.step()
    sync(device)
    return forwarded - start, time.perf_counter() - forwarded


def run(variant: str, height: int, width: int, args) -> None:
    torch.manual_seed(0)
    device = args.device
    cfg = resolve_config(compose_config("train", [f"model={variant}", f"trainer.channels_last={args.channels_last}"]))
    model = build_model(cfg, height=height, width=width).to(device)
    model = model.to(memory_format=memory_format(trainer_settings(cfg), device))  # as the trainer lays it out
    optimizer = build_optimizer(cfg, model.parameters())  # the trainer's AdamW (fused)
    carry = int(cfg.data.carry_recent_us) if cfg.data.carry_picture else None  # the default hybrid's carry branch
    dataset = SyntheticSamples(height, width, args.events, size=args.batch * (args.steps + 1), carry_recent_us=carry)
    graph = model.graph_spec
    loader = make_loader(dataset, batch_size=args.batch, num_workers=args.workers, graph=graph,
                         worker_nice=args.worker_nice)
    waits, forwards, backwards = [], [], []
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    iterator = iter(loader)
    step_on(model, optimizer, next(iterator), args)  # warm-up step, untimed: workers start, first batch, kernels load
    for _ in range(args.steps):
        start = time.perf_counter()
        batch = next(iterator)
        loaded = time.perf_counter()
        forward, backward = step_on(model, optimizer, batch, args)
        waits.append(loaded - start)
        forwards.append(forward)
        backwards.append(backward)
    del iterator  # the workers stop
    wait, fwd, bwd = (float(np.mean(x)) for x in (waits, forwards, backwards))
    step = wait + fwd + bwd
    alone = step_alone(model, optimizer, dataset, args)
    graph_note = ""
    if graph is not None:
        samples = [dataset[i] for i in range(args.batch)]
        start = time.perf_counter()
        GraphCollate(graph)(samples)
        graph_note = f", one batch's graph alone {time.perf_counter() - start:.2f} s"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if device.type == "cuda":
        graph_note += f", peak GPU memory {torch.cuda.max_memory_allocated(device) / 2**20:.0f} MiB"
    verdict = "ok" if wait < step / 3 else "DATA-BOUND"
    print(f"{variant:11s} {width}x{height}: step {step:6.2f} s = wait for data {wait:5.2f} + forward {fwd:5.2f} "
          f"+ backward {bwd:5.2f}; {args.batch / step:5.1f} samples/s; data {wait / step:4.0%} of a step [{verdict}]"
          f"{graph_note}; peak RSS {peak:.0f} MiB", flush=True)
    print(f"{'':11s} {width}x{height}: the same steps on batches loaded beforehand {alone:6.2f} s: the step with "
          f"the loader's workers running takes {step / alone:4.2f}x the step alone", flush=True)


def step_alone(model, optimizer, dataset, args) -> float:
    """Mean time of ``args.steps`` training steps on batches loaded beforehand (no loader running)."""
    loader = make_loader(dataset, batch_size=args.batch, num_workers=0, graph=model.graph_spec)
    batches = [batch for _, batch in zip(range(args.steps + 1), loader)]
    times = []
    for batch in batches:
        times.append(sum(step_on(model, optimizer, batch, args)))
    return float(np.mean(times[1:]))  # the first is a warm-up


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--events", type=int, default=50_000, help="events per sample")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2, help="loader workers (the trainer's default is 2)")
    parser.add_argument("--worker-nice", type=int, default=None,
                        help="the workers' nice increment (default: the trainer's loader.worker_nice)")
    parser.add_argument("--variants", nargs="+", default=["hybrid", "events_only", "image_only"])
    parser.add_argument("--sizes", nargs="+", default=["320x180", "640x360"])
    parser.add_argument("--channels-last", choices=("auto", "true", "false"), default="auto",
                        help="the weights' layout, as trainer.channels_last (auto: channels last on a CPU)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda, cuda:1, ...")
    args = parser.parse_args()
    args.device = resolve_device(args.device)
    defaults = compose_config("train", [])
    args.amp = amp_dtype(defaults.trainer, args.device)  # as the trainer (on a CPU: bfloat16 where it is native)
    if args.worker_nice is None:
        args.worker_nice = int(defaults.loader.worker_nice)
    where = torch.cuda.get_device_name(args.device) if args.device.type == "cuda" else "CPU"
    print(f"batch {args.batch}, {args.events:,} events per sample, {args.workers} workers (nice {args.worker_nice}), "
          f"{torch.get_num_threads()} torch threads, on {args.device} ({where}), channels_last {args.channels_last}",
          flush=True)
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        for variant in args.variants:
            run(variant, height, width, args)


if __name__ == "__main__":
    main()
