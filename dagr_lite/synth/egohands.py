"""EgoHands annotations: ``metadata.mat`` polygons to boxes, and labels for every frame.

EgoHands (Bambach et al., ICCV 2015) has 48 videos of 2700 frames at 1280x720 and 30 fps,
100 of them hand-labelled per video with polygons of four hands: ``myleft``, ``myright``,
``yourleft``, ``yourright``. ``metadata.mat`` holds a struct array ``video`` with fields
``video_id`` and ``labelled_frames``; each labelled frame has ``frame_num`` (1-based) and one
``(N, 2)`` array of ``[x, y]`` polygon points per hand (MATLAB pixel coordinates: the centre of
the top-left pixel is ``(1, 1)``; empty when the hand is not visible).

All four hand classes become the single class "hand". Frames between labelled ones get labels
from a labeller; the default (:func:`interpolate_labels`) interpolates a hand's box between two
labelled frames where that same hand is labelled in both, and records where each box came from.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.io

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError

HANDS = ("myleft", "myright", "yourleft", "yourright")
EGOHANDS_HEIGHT, EGOHANDS_WIDTH = 720, 1280
SOURCE_ANNOTATED, SOURCE_INTERPOLATED = "annotated", "interpolated"


def polygon_to_box(points, height: int = EGOHANDS_HEIGHT, width: int = EGOHANDS_WIDTH) -> np.ndarray | None:
    """``[x_tl, y_tl, w, h]`` around a MATLAB polygon, clipped to the image; None if empty.

    A MATLAB pixel centre ``(i, j)`` (1-based) is at ``(i - 0.5, j - 0.5)`` in the continuous
    0-based coordinates of the data contract, where pixel ``0`` covers ``[0, 1)``.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0:
        return None
    points = points.reshape(-1, 2) - 0.5
    x1, y1 = np.clip(points.min(axis=0), 0, [width, height])
    x2, y2 = np.clip(points.max(axis=0), 0, [width, height])
    if x2 <= x1 or y2 <= y1:
        return None
    return np.array([x1, y1, x2 - x1, y2 - y1])


@dataclass
class VideoAnnotations:
    """The labelled frames of one video: 0-based frame index -> hand name -> xywh box."""

    video: str
    frames: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)


def load_metadata(path: Path | str, *, height: int = EGOHANDS_HEIGHT, width: int = EGOHANDS_WIDTH
                  ) -> dict[str, VideoAnnotations]:
    """Read ``metadata.mat``: video name -> its labelled frames as boxes."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError.at(path, "EgoHands metadata file is missing")
    try:
        mat = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except (OSError, ValueError, TypeError) as err:
        raise DatasetFormatError.at(path, f"cannot read as a MATLAB file ({err})") from err
    if "video" not in mat:
        raise DatasetFormatError.at(path, "expected a struct array of videos", key="video")
    videos = {}
    for i, entry in enumerate(np.atleast_1d(mat["video"])):
        for name in ("video_id", "labelled_frames"):
            if not hasattr(entry, name):
                raise DatasetFormatError.at(path, f"field {name} is missing", key=f"video({i + 1})")
        annotations = VideoAnnotations(str(entry.video_id))
        for j, frame in enumerate(np.atleast_1d(entry.labelled_frames)):
            key = f"video({i + 1}).labelled_frames({j + 1})"
            if not hasattr(frame, "frame_num"):
                raise DatasetFormatError.at(path, "field frame_num is missing", key=key)
            k = int(frame.frame_num) - 1
            if k < 0:
                raise DatasetFormatError.at(path, f"frame_num {k + 1} is not 1-based", key=key)
            hands = {}
            for hand in HANDS:
                box = polygon_to_box(getattr(frame, hand, np.zeros((0, 2))), height, width)
                if box is not None:
                    hands[hand] = box
            annotations.frames[k] = hands
        videos[annotations.video] = annotations
    return videos


# A labeller gets the labelled frames of a video and its frame count and returns, per frame it
# labels, the boxes (M, 4) xywh and the source of each box.
Labeller = Callable[[VideoAnnotations, int], dict[int, tuple[np.ndarray, list[str]]]]


def interpolate_labels(annotations: VideoAnnotations, num_frames: int) -> dict[int, tuple[np.ndarray, list[str]]]:
    """Labels for the frames from the first to the last labelled one.

    Labelled frames keep their boxes (source ``annotated``). A frame between two labelled frames
    ``a < k < b`` gets, for each hand labelled in both, the box interpolated linearly in its
    corners (source ``interpolated``); a hand seen in only one of them gets no box there.
    Frames before the first or after the last labelled frame get no labels.
    """
    labelled = sorted(k for k in annotations.frames if k < num_frames)
    labels: dict[int, tuple[np.ndarray, list[str]]] = {}
    for k in labelled:
        hands = annotations.frames[k]
        boxes = np.array([hands[h] for h in HANDS if h in hands]).reshape(-1, 4)
        labels[k] = (boxes, [SOURCE_ANNOTATED] * len(boxes))
    for a, b in zip(labelled, labelled[1:]):
        shared = [h for h in HANDS if h in annotations.frames[a] and h in annotations.frames[b]]
        box_a = fmt.xywh_to_xyxy(np.array([annotations.frames[a][h] for h in shared]).reshape(-1, 4))
        box_b = fmt.xywh_to_xyxy(np.array([annotations.frames[b][h] for h in shared]).reshape(-1, 4))
        for k in range(a + 1, b):
            alpha = (k - a) / (b - a)
            boxes = fmt.xyxy_to_xywh((1 - alpha) * box_a + alpha * box_b)
            labels[k] = (boxes, [SOURCE_INTERPOLATED] * len(boxes))
    return labels


def default_split(videos: list[str], counts: tuple[int, int, int] = (30, 10, 8), seed: int = 0) -> dict[str, list[str]]:
    """A fixed train/valid/test split of the video names: sorted, shuffled with ``seed``, then cut.

    With the 48 EgoHands videos and the default counts this is 30 train, 10 valid, 8 test.
    """
    if sum(counts) != len(videos):
        raise UserError(f"split counts {counts} add up to {sum(counts)}, but there are {len(videos)} videos")
    order = sorted(videos)
    np.random.default_rng([seed]).shuffle(order)
    n_train, n_valid = counts[0], counts[1]
    return {"train": sorted(order[:n_train]), "valid": sorted(order[n_train:n_train + n_valid]),
            "test": sorted(order[n_train + n_valid:])}
