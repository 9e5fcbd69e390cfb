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

The augmentation moves the events, the boxes and the frame's pixels once, in compiled passes. Its
baseline, timed in the same run on the same samples and draws, is the chain of library functions
it replaces (``hflip``, ``zoom_translate``, ``crop``: a torch operation per step) with the frame
resampled by ``grid_sample``; the ratio is printed.
"""
from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch
import torch.nn.functional as F

from dagr_lite.config import build_dataset, compose_config, graph_spec, resolve_config
from dagr_lite.data import dataset as dataset_module
from dagr_lite.data.augment import crop, hflip, zoom_translate
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


def grid_sample_window(image: torch.Tensor, scale: float, tx: float, ty: float, window) -> torch.Tensor:
    """The frame's pixels of ``window`` resampled by ``grid_sample`` (the baseline's warp)."""
    _, height, width = image.shape
    x0, y0, w, h = window
    us = (torch.arange(width, dtype=torch.float32) + 0.5 - tx) / scale
    vs = (torch.arange(height, dtype=torch.float32) + 0.5 - ty) / scale
    grid = torch.stack(torch.meshgrid((2 * us / width - 1)[x0:x0 + w], (2 * vs / height - 1)[y0:y0 + h],
                                      indexing="xy"), dim=-1)
    out = F.grid_sample(image[None].float(), grid[None], mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0].round().clamp(0, 255).to(torch.uint8)


def baseline_augment(aug, sample, rng: np.random.Generator):
    """``aug``'s flip, zoom and crop (the same draws) through the library's functions, one step at a time."""
    flip, warp = aug._draw_geometry(sample, rng)
    if flip:
        sample = hflip(sample)
    moved = sample if warp is None else zoom_translate(sample, *warp, min_box_size=aug.min_box_size, image=False,
                                                       crop_follows=True)
    x0, y0, width, height = aug._crop_place(moved, rng)
    part = None if warp is None else grid_sample_window(sample.image, *warp, (x0, y0, width, height))
    return crop(moved, x0, y0, width, height, min_box_size=aug.min_box_size, image=part)


def augment_ratio(aug, samples, rounds: int = 3) -> tuple[float, float]:
    """Seconds a sample's augmentation takes (best of ``rounds``), fused and through the baseline."""
    best = {}
    for _ in range(rounds):
        for name, run in (("fused", aug), ("baseline", lambda s, r: baseline_augment(aug, s, r))):
            rng = np.random.default_rng(7)
            start = time.perf_counter()
            for sample in samples:
                run(sample, rng)
            best[name] = min(best.get(name, np.inf), (time.perf_counter() - start) / len(samples))
    return best["fused"], best["baseline"]


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
    if dataset.transform is not None and dataset.transform.crop < 1:
        transform, dataset.transform = dataset.transform, None
        plain = [dataset[int(index)] for index in order[20:]]  # the same samples before augmentation
        fused, baseline = augment_ratio(transform, plain)
        print(f"augmentation: fused {1000 * fused:.2f} ms a sample, through the library's steps with grid_sample "
              f"(baseline) {1000 * baseline:.2f} ms, {baseline / fused:.2f}x")
    if cfg.data.carry_picture:
        stored, cast = picture_kernel_ratio(dataset, rng)
        print(f"carry picture's events (5 frames), kernel on the stored columns: {1000 * stored:.2f} ms, "
              f"on columns cast first (baseline): {1000 * cast:.2f} ms, {cast / stored:.2f}x")


if __name__ == "__main__":
    main()
