"""Packed convolutions in the streaming answer: the same 5 ms updates with torch's own convolutions
(the baseline) and with each convolution's weight laid out once for oneDNN, its SiLU in the same call
(``StreamingDetector(packed=True)``, the default; docs/design.md, "The streaming detector").

    python benchmarks/packed_convolutions.py --ckpt <hybrid>/checkpoints/best.pt [<events_only>/...]
                                             [--seconds 0.5] [--update-ms 5] [--repeats 3] [--threads 2]

Both detectors stream the stub's first test video from frame 3 (images at 30 Hz, part of the
update they arrive in), alternating, ``--repeats`` times each, in one process. For each checkpoint
it prints the real-time factor of each run (seconds of recording per second of compute), their
medians, the ratio packed / baseline, the time per update of each part, and the largest difference
between the two detectors' raw head outputs at the same moments (the packed path sums in another
order; the exactness tests hold both to the batch model).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dagr_lite.apps.demo import Recording
from dagr_lite.data.labels import list_videos
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.stream import StreamingDetector
from dagr_lite.synth.stub import stub_root

FIRST_FRAME = 3


def stream(detector: StreamingDetector, rec: Recording, update_us: float, seconds: float
           ) -> tuple[float, list, int]:
    """Updates of ``update_us`` over ``seconds`` from frame :data:`FIRST_FRAME`: the real-time factor,
    the raw head output after every fifth update, and the number of updates."""
    t, ev, times = rec.events["t"], rec.events, rec.frame_times
    t0 = float(times[FIRST_FRAME])
    t1 = min(t0 + seconds * 1e6, float(t[-1]))
    detector.reset()
    start = int(np.searchsorted(t, t0 - detector.window_us - detector.context_us))
    if detector.hybrid:
        detector.push_image(rec.frames[FIRST_FRAME], times[FIRST_FRAME])
    stop = int(np.searchsorted(t, t0))
    detector.push_events(**{key: v[start:stop] for key, v in ev.items()})  # warm-up, not timed
    detector.detect(t0)
    detector.timings = {}
    busy, raws, now, frame, start, answers = 0.0, [], t0, FIRST_FRAME + 1, stop, 0
    while now < t1:
        end_t = now + update_us
        stop = int(np.searchsorted(t, end_t))
        tic = time.perf_counter()
        while detector.hybrid and frame < len(rec.frames) and times[frame] < end_t:
            detector.push_image(rec.frames[frame], times[frame])
            frame += 1
        detector.push_events(**{key: v[start:stop] for key, v in ev.items()})
        detector.detect(end_t)
        busy += time.perf_counter() - tic
        answers += 1
        if answers % 5 == 0:
            raws.append(detector.head_outputs(end_t)[0])
        start, now = stop, end_t
    return (t1 - t0) * 1e-6 / busy, raws, answers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", nargs="+", required=True, help="trained checkpoints (hybrid and/or events-only)")
    parser.add_argument("--seconds", type=float, default=0.5, help="recording streamed per run")
    parser.add_argument("--update-ms", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3, help="runs of each detector, alternating")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    root = stub_root()
    rec = Recording(root, "test", list_videos(root, "test")[0])
    for path in args.ckpt:
        checkpoint = load_checkpoint(path)
        model = checkpoint.model(checkpoint.detector).eval()
        if (model.cfg.height, model.cfg.width) != (rec.height, rec.width):
            raise SystemExit(f"{path}: a model of {model.cfg.width}x{model.cfg.height}; the stub's video is "
                             f"{rec.width}x{rec.height}")
        operating = OperatingPoint(score=0.25, nms_iou=0.65)
        detectors = {arm: StreamingDetector(model, checkpoint.sample, operating, packed=arm == "packed")
                     for arm in ("baseline", "packed")}
        for detector in detectors.values():
            detector.warm_up()
        factors = {arm: [] for arm in detectors}
        parts = {arm: {} for arm in detectors}
        raws = {}
        for _ in range(args.repeats):
            for arm, detector in detectors.items():
                factor, raws[arm], answers = stream(detector, rec, args.update_ms * 1e3, args.seconds)
                factors[arm].append(factor)
                for name, seconds in detector.timings.items():
                    parts[arm].setdefault(name, []).append(1e3 * seconds / answers)
        diff = max(float((a - b).abs().max()) for a, b in zip(raws["baseline"], raws["packed"]))
        median = {arm: float(np.median(f)) for arm, f in factors.items()}
        print(f"\n{path}: {checkpoint.model_name}, {args.update_ms:g} ms updates over {args.seconds:g} s of the "
              f"stub test video {rec.video}, {args.threads} threads")
        for arm, values in factors.items():
            print(f"  {arm:<9} real-time factor {' '.join(f'{v:.3f}' for v in values)}  (median {median[arm]:.3f})")
        print("  where an update's time goes (ms, median of the runs): baseline, packed")
        for name in sorted(parts["baseline"], key=lambda n: -np.median(parts["baseline"][n])):
            print(f"    {name:<34} {np.median(parts['baseline'][name]):7.2f} "
                  f"{np.median(parts['packed'].get(name, [0.0])):7.2f}")
        print(f"  largest raw difference between the two: {diff:.2e}")
        print(f"packed convolutions, {checkpoint.model_name}: real-time factor {median['packed'] / median['baseline']:.2f}x "
              f"the baseline's")


if __name__ == "__main__":
    main()
