"""Reading event recordings: dagr_lite's reader against faery reading the same file alone, and the
memory ``detect`` holds over a long recording.

    python benchmarks/reading.py [--events 5000000] [--repeats 3] [--detect-events 0 --ckpt CKPT]

A camera-like recording (640x480, about 5 million events/s, several events per pixel and
microsecond, a clock that starts at 1.7e12 us) is written once per format by faery into a temporary
folder. For each format it prints faery's read time (iterating its decoder, touching every array),
ours (``open_recording(...).events()``: the decoder and the time-order buffer, which passes faery's
chunks through whole, as faery already refuses events off the sensor and never goes back in time),
the ratio (the target: at most 1.20) and both throughputs, the
best of ``--repeats`` runs each.

``--detect-events N --ckpt CKPT`` (an events-only checkpoint) also writes an N-event EVT3
recording and runs ``detect`` over it at 100 Hz without the video, printing the peak resident
memory of the process and the file's size: bounded memory is a peak that does not grow with N.
"""
from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import faery
import numpy as np

from dagr_lite.camera.recording import open_recording

WIDTH, HEIGHT = 640, 480
FORMATS = [("rec.aedat4", {}), ("evt2.raw", {"version": "evt2"}), ("evt3.raw", {"version": "evt3"}),
           ("rec.dat", {}), ("rec.es", {}), ("rec.csv", {})]


def camera_chunks(n: int, rate: float = 5e6, chunk: int = 1_000_000, seed: int = 0):
    """``n`` events in chunks: blobs moving over the sensor, bursts of events at one pixel and microsecond."""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        t = t0 + np.sort(rng.integers(0, int(m / rate * 1e6), m)) + int(start / rate * 1e6)
        centre = (WIDTH / 2 + 200 * np.sin(t / 3e5), HEIGHT / 2 + 150 * np.cos(t / 4e5))
        x = np.clip(centre[0] + rng.normal(0, 40, m), 0, WIDTH - 1).astype(np.uint16)
        y = np.clip(centre[1] + rng.normal(0, 40, m), 0, HEIGHT - 1).astype(np.uint16)
        packed = np.zeros(m, faery.EVENTS_DTYPE)
        packed["t"], packed["x"], packed["y"], packed["on"] = t, x, y, rng.random(m) < 0.5
        yield packed


def faery_read(path: Path) -> int:
    n = 0
    for packet in faery.events_stream_from_file(path, dimensions_fallback=(WIDTH, HEIGHT)):
        n += len(packet)
        packet["t"].sum(), packet["x"].sum(), packet["y"].sum(), packet["on"].sum()
    return n


def our_read(path: Path) -> int:
    n = 0
    for chunk in open_recording(path, size=(WIDTH, HEIGHT) if path.suffix == ".csv" else None).events():
        n += len(chunk["t"])
        chunk["t"].sum(), chunk["x"].sum(), chunk["y"].sum(), chunk["p"].sum()
    return n


def best_of(fn, path: Path, repeats: int) -> tuple[float, int]:
    times, n = [], 0
    for _ in range(repeats):
        tic = time.perf_counter()
        n = fn(path)
        times.append(time.perf_counter() - tic)
    return min(times), n


def detect_memory(folder: Path, n: int, ckpt: str) -> None:
    from dagr_lite.camera.detect import VideoSettings, run_detect
    from dagr_lite.camera.sensor import Sensor
    from dagr_lite.stream import StreamingDetector

    path = folder / "long.raw"
    faery.file_encoder.events_to_file(camera_chunks(n, rate=5e5), path, dimensions=(WIDTH, HEIGHT), version="evt3")
    stream = StreamingDetector.from_checkpoint(ckpt, conf_threshold=0.3, nms_threshold=0.65)  # conf/detect.yaml's
    fit = Sensor((WIDTH, HEIGHT), crop=(0, 60, 640, 360), scale=2)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    summary = run_detect(stream, open_recording(path), fit, folder / "out", rate_hz=100,
                         video=VideoSettings(enabled=False, fps=30, rate_hz=60, events_ms=10, max_seconds=None))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"detect over {n:,} events ({path.stat().st_size / 2**20:.0f} MiB EVT3, "
          f"{summary['recording_seconds']:.1f} s at 500k events/s): peak resident memory {peak:.0f} MiB "
          f"(before: {before:.0f} MiB); real-time factor {summary['real_time_factor']:.3f}, "
          f"{summary['events_per_second_sustained'] / 1e3:.0f}k events/s sustained")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=5_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--detect-events", type=int, default=0)
    parser.add_argument("--ckpt", help="an events-only checkpoint, for --detect-events")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(f"{args.events:,} events, {WIDTH}x{HEIGHT}, best of {args.repeats}")
        print(f"{'format':<12}{'faery s':>9}{'ours s':>9}{'ratio':>7}{'faery Mev/s':>13}{'ours Mev/s':>12}")
        for name, kwargs in FORMATS:
            path = folder / name
            faery.file_encoder.events_to_file(camera_chunks(args.events), path, dimensions=(WIDTH, HEIGHT), **kwargs)
            theirs, n_theirs = best_of(faery_read, path, args.repeats)
            ours, n_ours = best_of(our_read, path, args.repeats)
            assert n_theirs == n_ours == args.events, (name, n_theirs, n_ours)
            print(f"{name:<12}{theirs:>9.3f}{ours:>9.3f}{ours / theirs:>7.2f}{n_theirs / theirs / 1e6:>13.1f}"
                  f"{n_ours / ours / 1e6:>12.1f}")
            path.unlink()
        if args.detect_events:
            if not args.ckpt:
                raise SystemExit("--detect-events needs --ckpt (an events-only checkpoint)")
            detect_memory(folder, args.detect_events, args.ckpt)


if __name__ == "__main__":
    main()
