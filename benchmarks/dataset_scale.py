"""A dataset of EventEgoHands' full shape: start-up time, per-sample load time and worker memory.

    python benchmarks/dataset_scale.py [--videos 48] [--frames 2700] [--events-per-frame 40]
                                       [--size 640x360] [--root DIR] [--samples 300]

Writes (once, into ``--root``, default a temporary folder) a dataset of ``--videos`` videos of
``--frames`` frames at ``--size`` split 30/10/8 like the paper's, with few events per frame and
a flat frame (so it stays small on disk), a box per frame, Blosc-compressed like the release.
Then reports:
  * start-up: opening the train split (every file's keys, ``timeidx`` and a few timestamps,
    every frame's JPEG header, the labels) and the numpy memory it allocates (tracemalloc), which
    stays far below the event arrays' size because no event array is read;
  * the time to load one sample (image age drawn 1-10, events since the image), median and p95;
  * the resident memory of each of two loader workers after a first and after all batches.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import torch

from dagr_lite.data import format as fmt
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.data.writer import VideoWriter, write_labels
from dagr_lite.engine.loading import make_loader

SPLIT_SHARES = {"train": 30, "valid": 10, "test": 8}


def write_dataset(root: Path, videos: int, frames: int, events_per_frame: int, height: int, width: int) -> float:
    """The dataset's files; returns the seconds it took."""
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    counts = np.round(np.array(list(SPLIT_SHARES.values())) * videos / sum(SPLIT_SHARES.values())).astype(int)
    counts[0] = videos - counts[1:].sum()
    splits = [s for s, c in zip(SPLIT_SHARES, counts) for _ in range(c)]
    frame = np.full((height, width, 3), 120, np.uint8)
    labels = {}
    for v, split in enumerate(splits):
        name = f"video_{v:02d}"
        with VideoWriter(root, split, name, num_frames=frames, height=height, width=width) as writer:
            for k in range(frames):
                writer.add_frame(frame)
            n = events_per_frame * frames
            t = np.sort(rng.integers(0, int(1e6 * frames / 30), n))
            writer.add_events(rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n))
        xy = rng.uniform(0, [width - 60, height - 60], (frames, 2))
        labels[name] = {k: np.array([[*xy[k], 50.0, 50.0]]) for k in range(frames)}
        print(f"\r  wrote {v + 1}/{videos} videos", end="", flush=True)
    write_labels(root, labels)
    print()
    return time.perf_counter() - started


def resident_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def worker_pids() -> list[int]:
    """Processes whose parent is this one (the loader's workers)."""
    me, pids = os.getpid(), []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    if int(stat.read().rsplit(")", 1)[1].split()[1]) == me:
                        pids.append(int(entry))
            except OSError:
                continue
    return sorted(pids)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--videos", type=int, default=48)
    parser.add_argument("--frames", type=int, default=2700)
    parser.add_argument("--events-per-frame", type=int, default=40)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--root", default=None, help="dataset folder (reused when it exists)")
    parser.add_argument("--samples", type=int, default=300)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    holder = tempfile.TemporaryDirectory() if args.root is None else None
    root = Path(args.root or holder.name)
    if not (root / "bounding_boxes.json").exists():
        print(f"writing {args.videos} videos x {args.frames} frames at {width}x{height} into {root}")
        seconds = write_dataset(root, args.videos, args.frames, args.events_per_frame, height, width)
        disk = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
        print(f"  {seconds:.0f} s, {disk / 2 ** 30:.2f} GiB on disk")
    tracemalloc.start()
    started = time.perf_counter()
    dataset = EventEgoHands(root, "train", image_age=(1, 10), window_us=fmt.DEFAULT_WINDOW_US, context_us=10_000,
                            refractory_us=0, support_us=0, max_events=None, graph_context_us=0)
    opened = time.perf_counter() - started
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    from dagr_lite.data.events import EventFile

    event_bytes = sum(EventFile(fmt.events_path(root, "train", v)).num_events for v in dataset.videos) * 13
    print(f"start-up of the train split ({len(dataset.videos)} videos, {len(dataset):,} samples): {opened:.1f} s, "
          f"{peak / 2 ** 20:.1f} MiB of numpy/Python allocations (its event arrays would be "
          f"{event_bytes / 2 ** 20:.0f} MiB)")
    rng = np.random.default_rng(1)
    times = []
    for index in rng.integers(0, len(dataset), args.samples):
        tic = time.perf_counter()
        dataset[int(index)]
        times.append(time.perf_counter() - tic)
    print(f"one sample: median {1e3 * np.median(times):.1f} ms, p95 {1e3 * np.percentile(times, 95):.1f} ms "
          f"({args.samples} random samples, image age 1-10 frames)")
    torch.manual_seed(0)
    subset = torch.utils.data.Subset(dataset, rng.integers(0, len(dataset), 64 * args.samples // 16).tolist())
    loader = make_loader(subset, batch_size=16, num_workers=2)
    iterator = iter(loader)
    next(iterator)
    first = {pid: resident_mb(pid) for pid in worker_pids()}
    for _ in range(len(loader) - 2):  # the workers stop after the last batch: measure before it
        next(iterator)
    last = {pid: resident_mb(pid) for pid in first}
    print(f"loader workers after 1 and after {len(loader) - 1} batches of 16 (resident MiB): "
          + ", ".join(f"{first[p]:.0f} -> {last[p]:.0f}" for p in first))


if __name__ == "__main__":
    main()
