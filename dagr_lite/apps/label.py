"""Labels for every frame, the paper's way: ``python -m dagr_lite.apps.label ROOT --out DIR``.

EventEgoHands labels every frame by running a detector trained on the hand-labelled frames. This
does the same with our own image-only detector:

1. some labelled frames are held out (``--hold-out``, or ``--hide``: hide that share of all
   labels first, to measure on a fully labelled dataset such as the stub);
2. ``model=image_only`` is trained on the remaining labelled frames of the training videos
   (``data.labelled_only``: an unlabelled frame is unknown, not empty) for ``--minutes``;
3. it predicts boxes on every frame; the score threshold is the one with the best F1 (IoU >= 0.5)
   on the held-out frames;
4. it writes ``DIR/bounding_boxes.json`` (the kept labels as given, every other frame filled by
   ``--fill``: ``predicted`` or ``interpolated``) and ``DIR/label_sources.json`` (``given``,
   ``predicted`` or ``interpolated`` per box), and ``DIR/label_quality.json``: COCO AP of the
   predicted labels and of interpolation between the kept labels, on the same held-out frames.

The dataset itself is never changed; the training run lives in ``DIR/train``.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from dagr_lite.errors import UserError
from dagr_lite.apps.cli import user_errors
from dagr_lite.apps.sweep import match_boxes
from dagr_lite.data import format as fmt
from dagr_lite.data.frames import list_frames, read_frame
from dagr_lite.data.labels import list_videos, read_labels
from dagr_lite.data.writer import write_labels, write_text_atomically
from dagr_lite.eval.coco import CocoEvaluator
from dagr_lite.eval.operating import SCORE_THRESHOLDS, best_score
from dagr_lite.nn.head import postprocess
from dagr_lite.progress import progress_bar

# The labeller's detections: boxes from this score, NMS at this IoU (then best_threshold picks the score kept).
LABEL_SCORE = 0.01
LABEL_NMS_IOU = 0.65

Labels = dict[str, dict[int, np.ndarray]]  # video -> frame -> (M, 4) xywh


def split_labels(labels: Labels, *, share: float, seed: int) -> tuple[Labels, Labels]:
    """``(kept, held_out)``: a seeded ``share`` of each video's labelled frames held out."""
    kept, held = {}, {}
    for video in sorted(labels):
        frames = sorted(labels[video])
        rng = np.random.default_rng([seed, sum(map(ord, video))])
        out = set(rng.choice(frames, size=int(round(share * len(frames))), replace=False).tolist()) if frames else set()
        kept[video] = {k: labels[video][k] for k in frames if k not in out}
        held[video] = {k: labels[video][k] for k in frames if k in out}
    return kept, held


def interpolate_frame(kept: dict[int, np.ndarray], k: int) -> np.ndarray:
    """Boxes ``(M, 4)`` xywh at frame ``k`` from the kept labels around it: linear between the
    frames before and after when their boxes pair one to one (IoU >= 0.3), else the nearer
    frame's boxes (or the only neighbour's)."""
    frames = sorted(kept)
    before = [f for f in frames if f < k]
    after = [f for f in frames if f > k]
    if k in kept:
        return kept[k]
    if not before and not after:
        return np.zeros((0, 4))
    if not before or not after:
        return kept[after[0] if not before else before[-1]]
    a, b = before[-1], after[0]
    box_a, box_b = fmt.xywh_to_xyxy(kept[a]), fmt.xywh_to_xyxy(kept[b])
    order = match_boxes(box_a, box_b)
    if order is None:
        return kept[a] if k - a <= b - k else kept[b]
    fraction = (k - a) / (b - a)
    return fmt.xyxy_to_xywh((1 - fraction) * box_a + fraction * box_b[order])


def with_unit_scores(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes that carry no confidence, as detections of score 1."""
    return boxes, np.ones(len(boxes))


def train_detector(work: Path, out: Path, *, minutes: float, steps: int | None, seed: int, samples: int) -> Path:
    """``model=image_only`` on the kept labels of ``work``'s training videos (``samples`` frames),
    each frame with its own image; returns its checkpoint."""
    from dagr_lite.config import compose_config
    from dagr_lite.config import budget_overrides
    from dagr_lite.engine.train import train

    cfg = compose_config("train", ["dataset=custom", f"dataset.root={work}", "model=image_only",
                                   f"run_dir={out / 'train'}", "data.labelled_only=true", f"seed={seed}",
                                   "data.image_age=0", "data.train_image_age=[0,0]",
                                   f"loader.batch_size={max(1, min(16, samples))}",
                                   "optim.lr=1e-3", "trainer.warmup_steps=20", "trainer.val_every=200",
                                   "trainer.image_every=0", *budget_overrides(minutes, steps)])
    train(cfg)
    return out / "train" / "checkpoints" / "best.pt"


@torch.no_grad()
def predict_all(checkpoint: Path, root: Path, videos: dict[str, str], *, batch_size: int = 16) -> dict:
    """``{video: {k: (boxes xywh, scores)}}`` of the detector on every frame."""
    from dagr_lite.engine.checkpoint import load_checkpoint

    model = load_checkpoint(checkpoint).model().eval()
    out = {}
    for video, split in progress_bar(videos.items(), desc="predicting", unit="video"):
        count = len(list_frames(fmt.frames_dir(root, split, video)))
        out[video] = {}
        for start in range(0, count, batch_size):
            ks = list(range(start, min(count, start + batch_size)))
            images = torch.stack([torch.from_numpy(np.ascontiguousarray(
                read_frame(fmt.frame_path(root, split, video, k)).transpose(2, 0, 1))) for k in ks])
            raw, shapes = model.head(model.image(images)[1:])
            for k, det in zip(ks, postprocess(raw, shapes, model.strides, conf_threshold=LABEL_SCORE,
                                              nms_threshold=LABEL_NMS_IOU,
                                              image_size=tuple(images.shape[-2:]))):
                out[video][k] = (fmt.xyxy_to_xywh(det["boxes"].numpy().astype(np.float64)), det["scores"].numpy())
    return out


def best_threshold(predicted: dict, held: Labels, thresholds=SCORE_THRESHOLDS) -> tuple[float, float]:
    """The score threshold with the best F1 at IoU >= 0.5 on the held-out frames, and that F1."""
    frames = [(fmt.xywh_to_xyxy(truth), fmt.xywh_to_xyxy(predicted[video][k][0]), predicted[video][k][1])
              for video, held_frames in held.items() for k, truth in held_frames.items()]
    score, (f1, _, _) = best_score(frames, thresholds)
    return score, f1


def quality(held: Labels, method: dict, height: int, width: int) -> dict:
    """COCO metrics of ``method``'s ``{video: {k: (boxes xywh, scores)}}`` on the held-out frames."""
    evaluator = CocoEvaluator()
    for video, frames in held.items():
        for k, truth in frames.items():
            boxes, scores = method[video][k]
            evaluator.add(fmt.label_key(video, k), height, width, fmt.xywh_to_xyxy(truth), fmt.xywh_to_xyxy(boxes),
                          scores)
    metrics = evaluator.compute()
    return {"frames": len(evaluator.images), **{key: metrics[key] for key in ("mAP", "AP50", "AP75")}}


def working_root(root: Path, work: Path, kept: Labels) -> None:
    """A view of the dataset with only the kept labels: its split folders linked, its labels written."""
    work.mkdir(parents=True, exist_ok=True)
    for split in fmt.SPLITS:
        if (root / split).is_dir() and not (work / split).exists():
            os.symlink((root / split).resolve(), work / split, target_is_directory=True)
    write_labels(work, kept, overwrite=True)


def label_dataset(root: Path | str, out: Path | str, *, hide: float | None = None, hold_out: float = 0.2,
                  minutes: float = 5.0, steps: int | None = None, fill: str = "predicted", seed: int = 0) -> dict:
    """Label every frame of ``root`` into ``out`` (see the module's text); returns the quality report."""
    root, out = Path(root), Path(out)
    if fill not in ("predicted", "interpolated"):
        raise UserError(f"fill must be predicted or interpolated, got {fill!r}")
    if (out / "bounding_boxes.json").exists():
        raise FileExistsError(f"{out}: holds labels already; choose a new --out")
    option, share = ("--hide", hide) if hide is not None else ("--hold-out", hold_out)
    if not 0 < share < 1:
        raise UserError(f"{option}: expected a share of the labelled frames in (0, 1), got {share:g} (the labels "
                         "are measured on the frames held out, so some must be and some kept)")
    if not minutes > 0:
        raise UserError(f"--minutes: expected a positive training budget in minutes, got {minutes:g}")
    if steps is not None and steps <= 0:
        raise UserError(f"--steps: expected a positive number of steps, got {steps}")
    videos = {v: s for s in fmt.SPLITS if (root / s).is_dir() for v in list_videos(root, s)}
    labels = read_labels(root)
    kept, held = split_labels(labels, share=share, seed=seed)
    if not any(held.values()):
        labelled = sum(len(frames) for frames in labels.values())
        raise UserError(f"{option} {share:g}: of the {labelled} labelled frames of {root} none is held out (the "
                         "share of each video's frames rounds to none); give a larger share")
    working_root(root, out / "work", kept)
    samples = sum(len(kept.get(v, {})) for v, split in videos.items() if split == "train")
    if samples == 0:
        raise UserError(f"{root}: no labelled frame of a training video is kept to train on")
    checkpoint = train_detector(out / "work", out, minutes=minutes, steps=steps, seed=seed, samples=samples)
    predicted = predict_all(checkpoint, root, videos)
    interpolated = {v: {k: with_unit_scores(interpolate_frame(kept.get(v, {}), k)) for k in predicted[v]}
                    for v in videos}
    height, width = read_frame(fmt.frame_path(root, videos[next(iter(videos))], next(iter(videos)), 0)).shape[:2]
    threshold, f1 = best_threshold(predicted, held)
    report = {"held_out": "hidden" if hide is not None else "held out", "share": hide if hide is not None else hold_out,
              "threshold": threshold, "f1_at_threshold": f1,
              "predicted": quality(held, predicted, height, width),
              "interpolated": quality(held, interpolated, height, width)}
    filled, sources = {}, {}
    for video in videos:
        filled[video] = {}
        for k in predicted[video]:
            if k in kept.get(video, {}):
                boxes, origin = kept[video][k], "given"
            elif fill == "predicted":
                boxes, scores = predicted[video][k]
                boxes, origin = boxes[scores >= threshold], "predicted"
            else:
                boxes, origin = interpolated[video][k][0], "interpolated"
            filled[video][k] = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
            sources[fmt.label_key(video, k)] = [origin] * len(filled[video][k])
    write_labels(out, filled, overwrite=False)
    write_text_atomically(out / "label_sources.json", json.dumps(sources))
    write_text_atomically(out / "label_quality.json", json.dumps(report, indent=1))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.apps.label", description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="dataset in the EventEgoHands layout, with some frames labelled")
    parser.add_argument("--out", type=Path, required=True, help="folder for the labels, report and training run")
    parser.add_argument("--hide", type=float, help="hide this share of all labels first and measure on them")
    parser.add_argument("--hold-out", type=float, default=0.2, help="share of labelled frames held out")
    parser.add_argument("--minutes", type=float, default=5.0, help="training budget")
    parser.add_argument("--steps", type=int, help="training length in steps instead")
    parser.add_argument("--fill", choices=("predicted", "interpolated"), default="predicted")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    with user_errors():  # a user's mistake: one line, no traceback
        report = label_dataset(args.root, args.out, hide=args.hide, hold_out=args.hold_out, minutes=args.minutes,
                               steps=args.steps, fill=args.fill, seed=args.seed)
    print(f"held-out frames: {report['predicted']['frames']} ({report['held_out']}, share {report['share']:g})")
    for method in ("predicted", "interpolated"):
        row = report[method]
        print(f"  {method:12s} mAP {row['mAP']:.3f}  AP50 {row['AP50']:.3f}  AP75 {row['AP75']:.3f}")
    print(f"score threshold {report['threshold']:.2f} (F1 {report['f1_at_threshold']:.3f}); labels in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
