"""Where a training sample's loading time goes, part by part, on one core.

    python benchmarks/sample_load.py [--dataset ego] [--samples 300] [key=value ...]

Loads ``--samples`` training samples of the dataset (drawn at random, after 20 untimed) exactly as
a loader worker does (the recipe's image ages, crops and augmentation; overrides as for
``train.py``), timing each part: the events read (and checked), the camera frame decoded, the
carry picture, the augmentation, the rest (the sample's tensors); then the event graphs of the
samples in batches of 16, as the collate builds them. Prints milliseconds a sample and each
part's share.

The carry picture's kernel reads the events' stored columns (uint16, uint16, int64, uint8). The
baseline, measured in the same run on the same events, is the same kernel fed columns cast to
int64 / float64 first, as it was before; the ratio is printed.
"""
from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from dagr_lite.config import build_dataset, compose_config, graph_spec, resolve_config
from dagr_lite.data import dataset as dataset_module
from dagr_lite.data.collate import GraphCollate
from dagr_lite.data.dataset import picture_state
from dagr_lite.data.picture import add_events


def timed(owner, name: str, label: str, spent: dict) -> None:
    """Wraps ``owner.name`` so that each call's seconds add to ``spent[label]``."""
    inner = getattr(owner, name)

    @functools.wraps(inner)
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            spent[label] = spent.get(label, 0.0) + time.perf_counter() - start
    setattr(owner, name, wrapper)


def picture_kernel_ratio(dataset, rng: np.random.Generator, rounds: int = 60) -> tuple[float, float]:
    """Seconds a picture's events take through the kernel fed the stored columns, and fed them cast first."""
    height, width = dataset.image_size
    stored, cast = [], []
    for index in rng.choice(len(dataset), rounds, replace=False):
        v, k = dataset.sample_name(int(index))
        v = dataset.videos.index(v)
        events = dataset.events_of(v, dataset.frame_time_us(v, max(k - 5, 0)), dataset.frame_time_us(v, k))
        x, y, t, p = (events[key] for key in "xytp")
        for arm, out in ((0, stored), (1, cast)):
            counts, last = picture_state(height, width)
            start = time.perf_counter()
            if arm:
                add_events(counts, last, x.astype(np.int64), y.astype(np.int64), t.astype(np.float64),
                           p.astype(np.int64), width)
            else:
                add_events(counts, last, x, y, t, p, width)
            out.append(time.perf_counter() - start)
    return float(np.median(stored)), float(np.median(cast))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="ego", help="stub or ego (default: ego)")
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("overrides", nargs="*", help="train.py overrides (key=value)")
    args = parser.parse_args()
    torch.set_num_threads(1)  # one loader worker's share
    cfg = resolve_config(compose_config("train", [f"dataset={args.dataset}", *args.overrides]))
    dataset = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
    spent: dict[str, float] = {}
    timed(type(dataset), "_kept_events", "events read", spent)
    timed(type(dataset), "image_of", "frame decoded", spent)
    timed(dataset_module.CarryPicture, "add", "carry picture", spent)  # its events in, its channels out
    timed(dataset_module.CarryPicture, "picture", "carry picture", spent)
    if dataset.transform is not None:
        timed(type(dataset.transform), "__call__", "augmentation", spent)
    rng = np.random.default_rng(0)
    order = rng.choice(len(dataset), args.samples + 20, replace=False)
    for index in order[:20]:
        dataset[int(index)]
    spent.clear()
    start = time.perf_counter()
    samples = [dataset[int(index)] for index in order[20:]]
    total = time.perf_counter() - start
    spent["rest"] = total - sum(spent.values())
    graph_s = 0.0
    if cfg.model.use_events:
        collate = GraphCollate(graph_spec(cfg.model))
        start = time.perf_counter()
        for first in range(0, len(samples), 16):
            collate(samples[first:first + 16])
        graph_s = time.perf_counter() - start
    n = len(samples)
    print(f"{args.dataset}, {cfg.model.name}: {n} training samples, {np.mean([len(s.events) for s in samples]):.0f} "
          f"events and {tuple(samples[0].image.shape)} image channels x pixels a sample, one thread")
    for label, seconds in sorted(spent.items(), key=lambda item: -item[1]):
        print(f"  {label:<14} {1000 * seconds / n:6.2f} ms a sample ({100 * seconds / total:4.1f}%)")
    print(f"  {'sample':<14} {1000 * total / n:6.2f} ms a sample")
    if graph_s:
        print(f"  {'graphs':<14} {1000 * graph_s / n:6.2f} ms a sample (collate of 16, with the batch's tensors)")
    if cfg.data.carry_picture:
        stored, cast = picture_kernel_ratio(dataset, rng)
        print(f"carry picture's events (5 frames), kernel on the stored columns: {1000 * stored:.2f} ms, "
              f"on columns cast first (baseline): {1000 * cast:.2f} ms, {cast / stored:.2f}x")


if __name__ == "__main__":
    main()
