"""Slice reads through ``timeidx`` against reading whole arrays, on one large event file.

    python benchmarks/slice_read.py [--events 50000000] [--compression blosc|gzip|none] [--chunk N] [--out DIR]

Writes a file of N events (90 s at 30 fps, as one EventEgoHands video) with the project's
writer, then in the same run measures:
  * a full ``np.asarray`` read of x, y, t, p (the baseline), giving a cost per event;
  * the median time of random 33 ms window reads (``EventFile.window``), and its ratio to the
    cost of reading just the window's own events at the full-read rate;
  * windows of several lengths, fitted as ``constant + per-event cost * events``, to show that a
    slice costs its own events plus a constant.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from dagr_lite.data import format as fmt
from dagr_lite.data.events import EventFile
from dagr_lite.data.writer import DEFAULT_CHUNK_EVENTS, EventFileWriter

DURATION_S = 90.0
HEIGHT, WIDTH = 360, 640


def write_file(path: Path, num_events: int, compression: str | None, chunk: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    num_frames = int(DURATION_S * fmt.DEFAULT_FPS)
    duration_us = int(DURATION_S * 1e6)
    piece = 2_000_000
    # Sorted uniform timestamps made piecewise: piece i covers its share of the duration.
    bounds = np.linspace(0, duration_us, -(-num_events // piece) + 1).astype(np.int64)
    with EventFileWriter(path, num_frames=num_frames, compression=compression, chunk_events=chunk,
                         overwrite=True) as writer:
        for i in tqdm(range(len(bounds) - 1), desc="writing", unit="piece"):
            n = min(piece, num_events - i * piece)
            t = np.sort(rng.integers(bounds[i], bounds[i + 1], n))
            writer.append(rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n), t, rng.integers(0, 2, n))


def full_read_seconds(path: Path) -> float:
    start = time.perf_counter()
    with h5py.File(path, "r") as h5:
        arrays = [np.asarray(h5[key]) for key in fmt.EVENT_KEYS]
    elapsed = time.perf_counter() - start
    assert len(arrays[2]) > 0
    return elapsed


def window_reads(reader: EventFile, length_us: int, repeats: int, rng: np.random.Generator):
    times, counts = [], []
    duration_us = int(DURATION_S * 1e6)
    for _ in range(repeats):
        t_start = int(rng.integers(0, duration_us - length_us))
        begin = time.perf_counter()
        events = reader.window(t_start, t_start + length_us)
        times.append(time.perf_counter() - begin)
        counts.append(len(events["t"]))
    return times, counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=50_000_000)
    parser.add_argument("--compression", choices=["blosc", "gzip", "none"], default="blosc")
    parser.add_argument("--chunk", type=int, default=DEFAULT_CHUNK_EVENTS, help="events per HDF5 chunk")
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--out", type=Path, default=None, help="folder for the file (default: a temporary one)")
    args = parser.parse_args()
    compression = None if args.compression == "none" else args.compression
    with tempfile.TemporaryDirectory(dir=args.out) as tmp:
        path = Path(tmp) / "bench.h5"
        write_file(path, args.events, compression, args.chunk)
        size_mb = path.stat().st_size / 2**20
        reader = EventFile(path, num_frames=int(DURATION_S * fmt.DEFAULT_FPS))
        rng = np.random.default_rng(1)
        window_reads(reader, 33_333, 20, rng)  # warm the file system cache and the reader
        full = min(full_read_seconds(path) for _ in range(2))
        per_event = full / args.events
        times, counts = window_reads(reader, 33_333, args.repeats, rng)
        median_time, median_count = statistics.median(times), statistics.median(counts)
        print(f"file: {args.events:,} events, {args.compression}, chunks of {args.chunk:,} events, {size_mb:.0f} MiB")
        print(f"full np.asarray read of x, y, t, p: {full:.2f} s ({per_event * 1e9:.1f} ns/event)")
        print(f"33 ms slice: median {median_time * 1e3:.2f} ms for a median {median_count:,.0f} events "
              f"({median_count / args.events:.5%} of the file)")
        print(f"  ratio full read / slice read: {full / median_time:,.0f}x")
        print(f"  ratio slice read / its own events at the full-read rate: "
              f"{median_time / (median_count * per_event):.2f}x")
        rows = []
        for length_ms in (1, 10, 33, 100, 330, 1000):
            t, c = window_reads(reader, length_ms * 1000, max(20, args.repeats // 4), rng)
            rows.append((statistics.median(c), statistics.median(t)))
            print(f"  window {length_ms:5d} ms: {rows[-1][0]:>10,.0f} events in {rows[-1][1] * 1e3:8.2f} ms")
        n, s = np.array(rows).T
        slope, constant = np.polyfit(n, s, 1)
        print(f"fit over window lengths: {constant * 1e3:.2f} ms + {slope * 1e9:.1f} ns/event "
              f"(full read: {per_event * 1e9:.1f} ns/event; ratio {slope / per_event:.2f})")
        reader.close()


if __name__ == "__main__":
    main()
