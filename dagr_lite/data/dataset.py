"""The EventEgoHands dataset: one sample per label frame (docs/design.md, "One sample").

For label frame ``k`` a sample holds the image of frame ``k - image_lag``, the events with
``t`` in ``[t_k - window_us, t_k)`` and the boxes of frame ``k``. The events bring the stale
image up to date.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from dagr_lite.data import format as fmt
from dagr_lite.data.reader import (DatasetFormatError, EventFile, Problem, box_problems, frame_header_problems,
                                   list_frames, list_videos, read_frame, read_labels)

# At most this many frame problems are listed when the dataset refuses to open.
MAX_LISTED_PROBLEMS = 10


@dataclass
class Sample:
    """One training or evaluation sample.

    Attributes:
        events: ``(N, 4)`` float32 columns x, y, t, p: pixel coordinates, microseconds since
            ``t_start_us`` (so in ``[0, window_us)``), polarity in {0, 1}; sorted by t.
        image: ``(3, H, W)`` uint8 RGB frame ``image_frame``.
        boxes: ``(M, 4)`` float32 x1, y1, x2, y2 in pixels (M may be 0).
        labels: ``(M,)`` int64 class indices (0 = hand).
        video: video name; ``frame``: label frame index k; ``image_frame``: ``k - image_lag``.
        t_start_us, t_end_us: the event window ``[t_start_us, t_end_us)``, ``t_end_us = t_k``.
    """

    events: torch.Tensor
    image: torch.Tensor
    boxes: torch.Tensor
    labels: torch.Tensor
    video: str
    frame: int
    image_frame: int
    t_start_us: int
    t_end_us: int

    @property
    def height(self) -> int:
        return self.image.shape[1]

    @property
    def width(self) -> int:
        return self.image.shape[2]

    def replace(self, **changes) -> "Sample":
        return replace(self, **changes)


class EventEgoHands(Dataset):
    """Samples of one split of a dataset in the EventEgoHands layout.

    Opening checks each video cheaply (keys, lengths, ``timeidx`` against the frame count and a
    few timestamps, every frame's JPEG header and size, label geometry) and raises
    :class:`DatasetFormatError` naming the file and key. Event files are read lazily, per worker
    process; each file's frame times follow its own convention (:attr:`EventFile.convention`).

    Args:
        root: dataset folder (holding ``train/``, ``valid/``, ``test/``, ``bounding_boxes.json``).
        split: ``train``, ``valid`` or ``test``.
        image_lag: the image is of frame ``k - image_lag`` (>= 0); frames ``k < image_lag`` give no sample.
        window_us: length of the event window ending at the label frame's time.
        max_events: cap on events per sample; above it, events are subsampled uniformly
            (seeded by ``seed``, the epoch and the sample index), keeping time order.
        fps: frame rate defining the frame times.
        image_size: expected ``(H, W)`` of the frames; a disagreeing frame is an error.
        videos: restrict to these videos of the split (all by default).
        transform: called as ``transform(sample, rng)`` on each sample (augmentation).
        clip_boxes: clip boxes to the image and drop empty ones instead of raising.
        seed: seed of the event subsampling and of ``transform``'s generator.
    """

    def __init__(self, root: Path | str, split: str, *, image_lag: int = 1, window_us: int = fmt.DEFAULT_WINDOW_US,
                 max_events: int | None = None, fps: float = fmt.DEFAULT_FPS,
                 image_size: Sequence[int] | None = None, videos: Sequence[str] | None = None,
                 transform: Callable[[Sample, np.random.Generator], Sample] | None = None,
                 clip_boxes: bool = False, seed: int = 0):
        if split not in fmt.SPLITS:
            raise ValueError(f"split must be one of {fmt.SPLITS}, got {split!r}")
        if image_lag < 0:
            raise ValueError(f"image_lag must be >= 0 (an image from the future is not causal), got {image_lag}")
        if window_us <= 0:
            raise ValueError(f"window_us must be > 0, got {window_us}")
        if max_events is not None and max_events <= 0:
            raise ValueError(f"max_events must be positive or None, got {max_events}")
        self.root, self.split = Path(root), split
        self.image_lag, self.window_us, self.max_events = int(image_lag), int(window_us), max_events
        self.fps, self.transform, self.seed, self.epoch = float(fps), transform, int(seed), 0
        available = list_videos(self.root, split)
        if videos is not None:
            unknown = sorted(set(videos) - set(available))
            if unknown:
                raise DatasetFormatError.at(self.root / split, f"videos {unknown} are not in this split "
                                                               f"(it holds {available})")
            available = [v for v in available if v in set(videos)]
        self.videos = available
        labels = read_labels(self.root)
        self.image_size: tuple[int, int] | None = tuple(image_size) if image_size is not None else None
        self._size_from: Path | None = None  # the frame that set image_size, when not configured
        self._events: list[EventFile] = []
        self._boxes: list[dict[int, np.ndarray]] = []
        sample_video, sample_frame = [], []
        for v, video in enumerate(self.videos):
            events, boxes = self._open_video(video, labels.get(video, {}), clip_boxes)
            self._events.append(events)
            self._boxes.append(boxes)
            ks = np.arange(self.image_lag, events.num_frames)
            sample_video.append(np.full(len(ks), v, dtype=np.int64))
            sample_frame.append(ks)
        self._sample_video = np.concatenate(sample_video) if sample_video else np.zeros(0, np.int64)
        self._sample_frame = np.concatenate(sample_frame) if sample_frame else np.zeros(0, np.int64)

    def _open_video(self, video: str, labels: dict[int, np.ndarray], clip_boxes: bool):
        frames_dir = fmt.frames_dir(self.root, self.split, video)
        frames = list_frames(frames_dir)
        num_frames = len(frames)
        if frames and max(frames) != num_frames - 1:
            first_gap = min(set(range(num_frames)) - set(frames))
            raise DatasetFormatError.at(frames_dir, f"frames are not numbered 0..{num_frames - 1}: "
                                                    f"{fmt.frame_name(first_gap)} is missing")
        events = EventFile(fmt.events_path(self.root, self.split, video), fps=self.fps, num_frames=num_frames)
        self._check_frames({k: frames_dir / name for k, name in frames.items()})
        label_file = fmt.labels_path(self.root)
        problems, boxes = [], {}
        for k, xywh in labels.items():
            key = fmt.label_key(video, k)
            if k >= num_frames:
                problems.append(Problem(label_file, key, f"label for frame {k}, but the video has {num_frames} frames"))
                continue
            xyxy = fmt.xywh_to_xyxy(xywh)
            if clip_boxes:
                height, width = self.image_size
                xyxy = np.clip(xyxy, 0, [width, height, width, height])
                xyxy = xyxy[(xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])]
            else:
                problems += [Problem(label_file, key, msg) for msg in box_problems(xywh, *self.image_size)]
            boxes[k] = xyxy.astype(np.float32)
        if problems:
            problems.append(Problem(label_file, "", "run `python -m dagr_lite.data.check ROOT` for a full report, "
                                                    "or set clip_boxes to clip boxes to the image"))
            raise DatasetFormatError(*problems)
        return events, boxes

    def _check_frames(self, frames: dict[int, Path]) -> None:
        """Every frame's JPEG header: readable, and of the dataset's size (the first frame's if not configured)."""
        expected_from = "as the dataset is configured" if self._size_from is None else f"as {self._size_from}"
        problems, size = frame_header_problems(frames, self.image_size, expected_from)
        if self.image_size is None and size is not None:
            self.image_size, self._size_from = size, frames[min(frames)]
        if len(problems) > MAX_LISTED_PROBLEMS:
            problems = problems[:MAX_LISTED_PROBLEMS] + [
                Problem(frames[min(frames)].parent, "", f"... and {len(problems) - MAX_LISTED_PROBLEMS} more "
                                                        "frame problems in this folder")]
        if problems:
            raise DatasetFormatError(*problems)

    def set_epoch(self, epoch: int) -> None:
        """Vary event subsampling and augmentation between epochs (same epoch, same samples)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self._sample_frame)

    def sample_name(self, index: int) -> tuple[str, int]:
        """``(video, label frame k)`` of sample ``index``, without reading it."""
        return self.videos[self._sample_video[index]], int(self._sample_frame[index])

    def __getitem__(self, index: int) -> Sample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample index {index} out of range for {len(self)} samples")
        index = int(index) % len(self)
        v, k = int(self._sample_video[index]), int(self._sample_frame[index])
        video, events_file = self.videos[v], self._events[v]
        t_end = events_file.frame_time_us(k)
        t_start = t_end - self.window_us
        raw = events_file.window(t_start, t_end)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        n = len(raw["t"])
        keep = slice(None)
        if self.max_events is not None and n > self.max_events:
            keep = np.sort(rng.choice(n, size=self.max_events, replace=False))
        height, width = self.image_size
        x, y = raw["x"][keep], raw["y"][keep]
        if len(x) and (x.max() >= width or y.max() >= height):
            raise DatasetFormatError.at(events_file.path, f"events of [{t_start}, {t_end}) us lie outside the "
                                                          f"{width}x{height} frame (x max {x.max()}, y max {y.max()})",
                                        key="events/x, events/y")
        events = np.stack([x.astype(np.float32), y.astype(np.float32),
                           (raw["t"][keep] - t_start).astype(np.float32),
                           raw["p"][keep].astype(np.float32)], axis=1).reshape(-1, 4)  # (N, 4)
        image_frame = k - self.image_lag
        image = read_frame(fmt.frame_path(self.root, self.split, video, image_frame), self.image_size)  # (H, W, 3)
        boxes = self._boxes[v].get(k, np.zeros((0, 4), np.float32))  # (M, 4)
        sample = Sample(events=torch.from_numpy(events),
                        image=torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))),  # (3, H, W)
                        boxes=torch.from_numpy(boxes.copy()),
                        labels=torch.zeros(len(boxes), dtype=torch.int64),
                        video=video, frame=k, image_frame=image_frame, t_start_us=t_start, t_end_us=t_end)
        if self.transform is not None:
            sample = self.transform(sample, rng)
        return sample

    def close(self) -> None:
        for events in self._events:
            events.close()
