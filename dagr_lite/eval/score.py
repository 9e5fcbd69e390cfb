"""Scoring a detector over a loader with COCO metrics, and pictures of events, frames and boxes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from torch import nn
from torch.utils.data import DataLoader

from dagr_lite.data import format as fmt
from dagr_lite.data.collate import Batch
from dagr_lite.eval.coco import CocoEvaluator
from dagr_lite.progress import progress_bar


def score_model(model: nn.Module, loader: DataLoader, device: torch.device, *, backend: str,
                conf_threshold: float, nms_threshold: float, progress: bool = True,
                desc: str = "evaluating") -> tuple[dict, CocoEvaluator]:
    """COCO metrics of ``model`` over every sample of ``loader`` (no batch is dropped)."""
    entries = detections_of(model, loader, device, conf_threshold=conf_threshold, nms_threshold=nms_threshold,
                            progress=progress, desc=desc)
    return score_entries(entries, backend=backend)


def detections_of(model: nn.Module, loader: DataLoader, device: torch.device, *, conf_threshold: float,
                  nms_threshold: float, progress: bool = True, desc: str = "evaluating") -> list[tuple]:
    """``(image name, height, width, true boxes, boxes, scores)`` of every sample of ``loader``, in
    its order (numpy arrays, xyxy): what :func:`score_entries` scores, and what ranks gather."""
    return detection_sets(model, loader, device, {None: (conf_threshold, nms_threshold)}, progress=progress,
                          desc=desc)[None]


@torch.no_grad()
def detection_sets(model: nn.Module, loader: DataLoader, device: torch.device, settings: dict, *,
                   progress: bool = True, desc: str = "evaluating") -> dict:
    """The entries of :func:`detections_of` under each of several ``settings`` ``{key: (score
    threshold, NMS IoU)}``, from one pass of the model: ``{key: entries}``."""
    was_training = model.training
    model.eval()
    sets: dict = {key: [] for key in settings}
    for batch in progress_bar(loader, desc=desc, leave=False, disable=not progress):
        batch = batch.to(device)
        raw, shapes, _ = model.outputs(batch)
        height, width = batch.images.shape[-2:]
        names = [fmt.label_key(batch.videos[b], int(batch.frames[b])) for b in range(len(batch))]
        truth = [batch.boxes[b].cpu().numpy() for b in range(len(batch))]
        for key, (conf_threshold, nms_threshold) in settings.items():
            detections = model.detections(raw, shapes, conf_threshold=conf_threshold, nms_threshold=nms_threshold)
            sets[key].extend((names[b], int(height), int(width), truth[b], det["boxes"].cpu().numpy(),
                              det["scores"].cpu().numpy()) for b, det in enumerate(detections))
    model.train(was_training)
    return sets


def score_entries(entries: list[tuple], *, backend: str) -> tuple[dict, CocoEvaluator]:
    """COCO metrics of the entries of :func:`detections_of`."""
    evaluator = CocoEvaluator(backend=backend)
    for entry in entries:
        evaluator.add(*entry)
    return evaluator.compute(), evaluator


CAPTION_HEIGHT = 14  # pixels of the caption bar above a sample's picture
TRUTH, ANSWER = (0, 200, 0), (255, 150, 0)  # the true boxes' colour, the predicted boxes' (and their scores')


def caption_lines(parts: list[str], width_px: int) -> list[str]:
    """``parts`` joined by "; " into as few lines as fit ``width_px`` in PIL's default font (a part
    longer than a line gets a line of its own)."""
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength
    lines: list[str] = []
    for part in parts:
        if lines and measure(f"{lines[-1]}; {part}") <= width_px:
            lines[-1] = f"{lines[-1]}; {part}"
        else:
            lines.append(part)
    return lines


def render_sample(batch: Batch, index: int, detections: dict | None = None, *, score_threshold: float = 0.3
                  ) -> np.ndarray:
    """``(14 L + H, 2W, 3)`` uint8: the frame with true (green) and predicted (orange, with their scores)
    boxes, beside the events of the sample's window (ON red, OFF blue on white) with the same boxes,
    under a caption of ``L`` lines (as many as its width needs) that names the sample and says so."""
    image = batch.images[index, :3].permute(1, 2, 0).cpu().numpy()  # the frame (or picture) alone
    height, width = image.shape[:2]
    if not image.shape[2]:  # a frameless sample: a grey frame
        image = np.full((height, width, 3), 128, np.uint8)
    canvas = np.full((height, width, 3), 255, np.uint8)
    events = batch.events[batch.ptr[index]:batch.ptr[index + 1]].cpu().numpy()
    events = events[events[:, 2] >= int(batch.t_start_us[index] - batch.t_image_us[index])]  # its own window
    if len(events):
        xs = np.clip(events[:, 0].astype(int), 0, width - 1)
        ys = np.clip(events[:, 1].astype(int), 0, height - 1)
        canvas[ys, xs] = np.where(events[:, 3:4] > 0.5, [220, 30, 30], [30, 60, 220])
    age_ms = (int(batch.t_end_us[index]) - int(batch.t_image_us[index])) / 1000
    framed = batch.images.shape[1] >= 3  # a frameless sample is drawn on grey and has no image age
    parts = [f"{batch.videos[index]} frame {int(batch.frames[index])}" + (f", {age_ms:.0f} ms after its image"
                                                                            if framed else ", no image"),
             "truth green" + (f", answers >= {score_threshold:g} orange" if detections is not None else ""),
             "events ON red, OFF blue"]
    lines = caption_lines(parts, 2 * width - 8)
    top = CAPTION_HEIGHT * len(lines)
    picture = Image.new("RGB", (2 * width, height + top), (0, 0, 0))
    for i, array in enumerate((image, canvas)):
        panel = Image.fromarray(np.ascontiguousarray(array))
        draw = ImageDraw.Draw(panel)
        for box in batch.boxes[index].cpu().tolist():
            draw.rectangle(box, outline=TRUTH)
        if detections is not None:
            for box, score in zip(detections["boxes"].cpu().tolist(), detections["scores"].cpu().tolist()):
                if score >= score_threshold:
                    draw.rectangle(box, outline=ANSWER)
                    draw.text((box[0] + 2, box[1] + 1), f"{score:.2f}", fill=ANSWER)
        picture.paste(panel, (i * width, top))
    draw = ImageDraw.Draw(picture)
    for k, line in enumerate(lines):
        draw.text((4, 1 + CAPTION_HEIGHT * k), line, fill=(255, 255, 255))
    return np.asarray(picture)


@torch.no_grad()
def save_pictures(model: nn.Module, loader: DataLoader, device: torch.device, folder: Path, count: int, *,
                  conf_threshold: float, nms_threshold: float) -> None:
    """PNGs of the first ``count`` samples of ``loader`` with true (green) and predicted (orange) boxes
    (:func:`render_sample`): the answers at ``conf_threshold`` and ``nms_threshold``, all of them drawn."""
    folder.mkdir(parents=True, exist_ok=True)
    model.eval()
    saved = 0
    for batch in loader:
        batch = batch.to(device)
        detections = model(batch, conf_threshold=conf_threshold, nms_threshold=nms_threshold)
        for b in range(len(batch)):
            if saved >= count:
                return
            picture = render_sample(batch, b, detections[b], score_threshold=conf_threshold)
            Image.fromarray(np.ascontiguousarray(picture)).save(
                folder / f"{fmt.label_key(batch.videos[b], int(batch.frames[b]))}.png")
            saved += 1
