"""COCO scoring at the test split's full size: the vectorised backend against pycocotools.

    python benchmarks/coco_eval.py [--images 21600] [--detections 100] [--backends numpy pycocotools faster]

Synthetic images with 1-4 hands and ``--detections`` scored boxes each (near the hands and
elsewhere), fed through :class:`CocoEvaluator` exactly as an evaluation run does (``add`` per
image, then ``compute``). Prints each backend's time for adding and for computing, the ratio
to pycocotools measured in the same run, and the largest difference of the statistics.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from dagr_lite.eval.coco import METRIC_KEYS, CocoEvaluator


def synthetic(images: int, detections: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for i in range(images):
        m = int(rng.integers(1, 5))
        xy = rng.uniform(0, 560, (m, 2))
        gt = np.concatenate([xy, xy + rng.uniform(10, 80, (m, 2))], axis=1)
        near = gt[rng.integers(0, m, detections // 2)] + rng.normal(0, 6, (detections // 2, 4))
        far_xy = rng.uniform(0, 600, (detections - len(near), 2))
        far = np.concatenate([far_xy, far_xy + rng.uniform(5, 60, (len(far_xy), 2))], axis=1)
        dt = np.concatenate([near, far])
        dt[:, 2:] = np.maximum(dt[:, 2:], dt[:, :2] + 1)
        yield f"video_frame_{i}", gt, dt, rng.uniform(0, 1, detections).astype(np.float32)


def run(backend: str, data) -> tuple[float, float, dict]:
    start = time.perf_counter()
    evaluator = CocoEvaluator(backend=backend)
    for name, gt, dt, scores in data:
        evaluator.add(name, 360, 640, gt, dt, scores)
    added = time.perf_counter() - start
    metrics = evaluator.compute()
    return added, time.perf_counter() - start - added, metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=21_600)
    parser.add_argument("--detections", type=int, default=100)
    parser.add_argument("--backends", nargs="+", default=["numpy", "pycocotools", "faster"])
    args = parser.parse_args()
    data = list(synthetic(args.images, args.detections))
    print(f"{args.images:,} images, {args.images * args.detections:,} detections")
    results = {}
    for backend in args.backends:
        try:
            results[backend] = run(backend, data)
        except ImportError as err:
            print(f"{backend:12s} skipped ({err})")
            continue
        added, computed, metrics = results[backend]
        print(f"{backend:12s} add {added:6.1f} s  compute {computed:6.1f} s  total {added + computed:6.1f} s  "
              f"mAP {metrics['mAP']:.6f}  AP50 {metrics['AP50']:.6f}")
    if "numpy" in results and "pycocotools" in results:
        ours, ref = results["numpy"], results["pycocotools"]
        diff = max(abs(ours[2][k] - ref[2][k]) for k in METRIC_KEYS)
        print(f"numpy backend: {(ref[0] + ref[1]) / (ours[0] + ours[1]):.1f}x faster than pycocotools, "
              f"largest difference of the statistics {diff:.1e}")


if __name__ == "__main__":
    main()
