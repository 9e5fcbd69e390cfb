"""DVS emulator throughput, and the time to build the stub dataset.

    python benchmarks/dvs.py [--steps 60] [--height 360 --width 640]

Emulates a synthetic hand scene (frames rendered beforehand, 41 steps per 30 fps frame as in
v4-v6) and prints pixel-frames per second for the clean and noisy presets, against a plain
per-frame numpy implementation of the clean model written below (one pass per event count,
as straightforward code does it), measured in the same run on the same frames. Then builds
the stub dataset into a temporary folder and prints how long it took.
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time

import numpy as np

from dagr_lite.synth.dvs import DVSEmulator, lin_log, preset, rgb_to_luma
from dagr_lite.synth.stub import HandScene, generate_stub


def plain_clean_events(frames: list[np.ndarray], times: list[float], threshold: float = 0.2):
    """Reference: the clean model without threshold spread, one numpy pass per event rank; each
    event where the difference, linear across the step, crosses its level."""
    memory = lin_log(rgb_to_luma(frames[0]))
    previous = memory.copy()
    out = []
    for frame, t_prev, t_now in zip(frames[1:], times[:-1], times[1:]):
        level = lin_log(rgb_to_luma(frame))
        change = level - memory
        start = previous - memory
        counts = np.floor(np.abs(change) / threshold + 1e-9).astype(np.int64)
        xs, ys, ts, ps = [], [], [], []
        for rank in range(1, int(counts.max()) + 1 if counts.size else 1):
            y, x = np.nonzero(counts >= rank)
            target = np.sign(change[y, x]) * rank * threshold
            fraction = np.clip((target - start[y, x]) / (change[y, x] - start[y, x]), 0.0, 1.0)
            xs.append(x)
            ys.append(y)
            ts.append(np.floor(t_prev + fraction * (t_now - t_prev)).astype(np.int64))
            ps.append((change[y, x] > 0).astype(np.uint8))
        memory = memory + np.sign(change) * counts * threshold
        previous = level
        if xs:
            t = np.concatenate(ts)
            order = np.argsort(t, kind="stable")
            out.append((np.concatenate(xs)[order], np.concatenate(ys)[order], t[order], np.concatenate(ps)[order]))
    return out


def time_emulator(frames, times, params, repeats=2):
    best, count = math.inf, 0
    for _ in range(repeats):
        emulator = DVSEmulator(frames[0].shape[0], frames[0].shape[1], params, seed=0)
        start = time.perf_counter()
        emulator.reset(frames[0], times[0])
        count = sum(len(emulator.step(f, t)["t"]) for f, t in zip(frames[1:], times[1:]))
        best = min(best, time.perf_counter() - start)
    return best, count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--width", type=int, default=640)
    args = parser.parse_args()
    scene = HandScene(0, height=args.height, width=args.width)
    dt = 1e6 / 30 / 41
    times = [i * dt for i in range(args.steps + 1)]
    frames = [scene.render(t * 1e-6) for t in times]
    pixel_frames = args.steps * args.height * args.width

    best = math.inf
    for _ in range(2):
        start = time.perf_counter()
        reference = plain_clean_events(frames, times)
        best = min(best, time.perf_counter() - start)
    baseline_rate = pixel_frames / best
    reference_count = sum(len(r[2]) for r in reference)
    print(f"{args.width}x{args.height}, {args.steps} steps of {dt:.0f} us")
    print(f"plain per-frame numpy (clean): {baseline_rate / 1e6:7.1f} M pixel-frames/s, {reference_count:,} events")
    for name in ("clean", "noisy"):
        params = preset(name, sigma_threshold=0.0) if name == "clean" else preset(name)
        seconds, count = time_emulator(frames, times, params)
        rate = pixel_frames / seconds
        note = " (same events as the plain one)" if name == "clean" and count == reference_count else ""
        print(f"dagr_lite {name:5s}:                 {rate / 1e6:7.1f} M pixel-frames/s, {count:,} events, "
              f"ratio {rate / baseline_rate:.2f}x{note}")

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        generate_stub(tmp + "/stub", progress=False)
        print(f"stub dataset build: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
