"""A hybrid's boxes joined with an events-only model's: what the events' own detections add.

    python benchmarks/late_fusion.py --hybrid HYBRID.pt --events EVENTS_ONLY.pt --dataset ego [--ages 1 5 10]
    python benchmarks/late_fusion.py --hybrid HYBRID.pt --grey --dataset ego     # the hybrid with a grey frame

Both checkpoints are scored by the sweep (the same label frames at every image age, each model with
its own sample settings); then, per frame, the two models' boxes are pooled, the events-only
model's scores times ``--weight``, and one NMS at the hybrid's ``eval.nms_threshold`` runs over
them, as an answer of a detector holding both would. Prints AP50 of the hybrid, of the events-only
model and of the pooled boxes at each age, and the hybrid's and the pooled 167 / 33 ms ratio (the
issue's target: at least 0.85). With ``--grey`` the second set of boxes is a checkpoint's answers
with its camera frame mid-grey (the sweep's ``blank_image``; the hybrid's own when ``--events`` is
not given): what the hybrid makes of its events alone, pooled with what it makes of them with the
image. A measurement of a design, not a detector a command runs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dagr_lite.apps.sweep import sweep_checkpoint  # noqa: E402
from dagr_lite.config import compose_config, resolve_config  # noqa: E402
from dagr_lite.engine.checkpoint import load_checkpoint  # noqa: E402
from dagr_lite.engine.runs import resolve_device  # noqa: E402
from dagr_lite.eval.score import score_entries  # noqa: E402
from dagr_lite.nn.head import nms  # noqa: E402


def pooled_entries(first: list[tuple], second: list[tuple], *, iou: float, weight: float = 1.0) -> list[tuple]:
    """Per frame, the boxes of both entry lists (the same frames in the same order, as the sweep
    gives them), the second's scores times ``weight``, after one NMS at ``iou`` (by decreasing score)."""
    pooled = []
    for a, b in zip(first, second, strict=True):
        if a[0] != b[0]:
            raise ValueError(f"the entries name different frames: {a[0]} and {b[0]}")
        boxes = np.concatenate([np.asarray(a[4]).reshape(-1, 4), np.asarray(b[4]).reshape(-1, 4)])
        scores = np.concatenate([np.asarray(a[5]), weight * np.asarray(b[5])])
        keep = nms(torch.as_tensor(boxes, dtype=torch.float64), torch.as_tensor(scores, dtype=torch.float64),
                   iou).numpy()
        pooled.append((*a[:4], boxes[keep], scores[keep]))
    return pooled


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hybrid", type=Path, required=True, help="a hybrid checkpoint")
    parser.add_argument("--events", type=Path, help="an events-only checkpoint (with --grey: any; default the hybrid)")
    parser.add_argument("--grey", action="store_true",
                        help="score the second checkpoint with its camera frame mid-grey (blank_image)")
    parser.add_argument("--dataset", default="stub", help="a dataset of conf/dataset")
    parser.add_argument("--split", default="test")
    parser.add_argument("--ages", type=int, nargs="+", default=[1, 5, 10], help="image ages in frames (1 first)")
    parser.add_argument("--weight", type=float, nargs="+", default=[1.0],
                        help="factors on the events-only model's scores (one row each)")
    args = parser.parse_args(argv)
    if args.events is None:
        if not args.grey:
            parser.error("--events is needed (or --grey, to pool the hybrid's answers with a grey frame)")
        args.events = args.hybrid
    for path in (args.hybrid, args.events):
        if not path.is_file():
            print(f"{path}: checkpoint file is missing", file=sys.stderr)
            return 1
    cfg = resolve_config(compose_config("sweep", [f"ckpt=[{args.hybrid},{args.events}]", f"dataset={args.dataset}",
                                                  f"split={args.split}", f"ages=[{','.join(map(str, args.ages))}]"]))
    device = resolve_device(cfg.device)
    second_cfg = cfg.copy()  # the second checkpoint's sweep: with --grey, on a mid-grey frame
    second_cfg.blank_image = args.grey
    entries, rows, frames = [{}, {}], [], None
    for path, kept, run_cfg in zip((args.hybrid, args.events), entries, (cfg, second_cfg)):
        checkpoint_rows, frames, _ = sweep_checkpoint(run_cfg, load_checkpoint(path), frames, device, entries_out=kept)
        rows.append({row["age_frames"]: row["AP50"] for row in checkpoint_rows})
    iou = float(cfg.eval.nms_threshold)
    print(f"\n{args.dataset}, {args.split} split, {len(frames)} label frames; AP50 at image ages (frames) "
          f"{' '.join(map(str, args.ages))}:")
    second = "grey frame" if args.grey else "events_only"
    table = {"hybrid": [rows[0][a] for a in args.ages], second: [rows[1][a] for a in args.ages]}
    for weight in args.weight:
        table[f"pooled, {second} x {weight:g}"] = [
            score_entries(pooled_entries(entries[0][(a, 0.0)], entries[1][(a, 0.0)], iou=iou, weight=weight),
                          backend=cfg.eval.backend)[0]["AP50"] for a in args.ages]
    for name, values in table.items():
        ratio = f"  {values[args.ages.index(5)] / values[0]:.2f} at 5 / 1" if 5 in args.ages and values[0] else ""
        print(f"  {name:<28} {' '.join(f'{v:.3f}' for v in values)}{ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
