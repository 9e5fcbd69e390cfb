"""Labels and listings of the layout: the videos of a split, the label file and its boxes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError, Problem


def list_videos(root: Path | str, split: str) -> list[str]:
    """Names of the videos of a split, sorted; events files and frame folders paired by name."""
    split_dir = Path(root) / split
    if not split_dir.is_dir():
        raise DatasetFormatError.at(split_dir, f"split folder is missing (expected {fmt.EVENTS_DIR}/ "
                                               f"and {fmt.FRAMES_DIR}/ inside it)")
    events_dir, frames_root = split_dir / fmt.EVENTS_DIR, split_dir / fmt.FRAMES_DIR
    for folder in (events_dir, frames_root):
        if not folder.is_dir():
            raise DatasetFormatError.at(folder, "folder is missing")
    with_events = {p.name[: -len(fmt.EVENTS_SUFFIX)] for p in events_dir.iterdir()
                   if p.name.endswith(fmt.EVENTS_SUFFIX) and p.is_file()}
    with_frames = {p.name for p in frames_root.iterdir() if p.is_dir()}
    problems = [Problem(fmt.events_path(root, split, v), "", f"events file has no frame folder "
                                                             f"{fmt.frames_dir(root, split, v)}")
                for v in sorted(with_events - with_frames)]
    problems += [Problem(fmt.frames_dir(root, split, v), "", f"frame folder has no events file "
                                                             f"{fmt.events_path(root, split, v)}")
                 for v in sorted(with_frames - with_events)]
    if problems:
        raise DatasetFormatError(*problems)
    if not with_events:
        raise DatasetFormatError.at(events_dir, f"no {fmt.EVENTS_SUFFIX} event files found")
    return sorted(with_events)


Labels = dict[str, dict[int, np.ndarray]]  # video -> frame index -> (M, 4) float64 x_tl, y_tl, w, h


def read_json_object(path: Path | str, what: str = "file", expected: str = "a JSON object") -> dict:
    """The JSON object in a file; errors name the file (``what`` it is, the ``expected`` content)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError.at(path, f"{what} is missing")
    try:
        with open(path) as f:
            raw = json.load(f)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DatasetFormatError.at(path, f"cannot parse as JSON ({err})") from err
    if not isinstance(raw, dict):
        raise DatasetFormatError.at(path, f"expected {expected}, found {type(raw).__name__}")
    return raw


def load_label_file(path: Path | str) -> dict:
    """The raw contents of a label file in the ``bounding_boxes.json`` format; errors name the file."""
    return read_json_object(path, "label file", "a JSON object keyed <video>_frame_<k>")


def load_labels_json(root: Path | str) -> dict:
    """The raw contents of the dataset's ``bounding_boxes.json``; errors name the file."""
    return load_label_file(fmt.labels_path(root))


def parse_boxes(value) -> np.ndarray:
    """A label value (a list of ``[x_tl, y_tl, w, h]``) as a ``(M, 4)`` float64 array.

    Raises ``ValueError`` describing what was expected when the value is malformed or not finite.
    """
    if not isinstance(value, list):
        raise UserError(f"expected a list of [x_tl, y_tl, w, h] boxes, found {type(value).__name__}")
    for box in value:
        if (not isinstance(box, (list, tuple)) or len(box) != 4
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in box)):
            raise UserError(f"expected a box [x_tl, y_tl, w, h] of 4 numbers, found {box!r}")
    boxes = np.asarray(value, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(boxes)):
        raise UserError(f"boxes must be finite, found {boxes[~np.isfinite(boxes).all(axis=1)].tolist()}")
    return boxes


def read_label_file(path: Path | str) -> Labels:
    """A label file in the ``bounding_boxes.json`` format, grouped by video and frame index.

    Malformed keys or boxes raise naming the file and the key.
    """
    path = Path(path)
    labels: Labels = {}
    for key, value in load_label_file(path).items():
        parsed = fmt.parse_label_key(key)
        if parsed is None:
            raise DatasetFormatError.at(path, "key is not of the form <video>_frame_<k>", key=key)
        try:
            boxes = parse_boxes(value)
        except ValueError as err:
            raise DatasetFormatError.at(path, str(err), key=key) from err
        video, k = parsed
        labels.setdefault(video, {})[k] = boxes
    return labels


def read_labels(root: Path | str) -> Labels:
    """The dataset's ``bounding_boxes.json`` grouped by video and frame index (see :func:`read_label_file`)."""
    return read_label_file(fmt.labels_path(root))


def box_problems(boxes: np.ndarray, height: int, width: int, tol: float = 1e-3) -> list[str]:
    """Geometric problems of ``(M, 4)`` xywh boxes in an image of ``height x width`` pixels."""
    problems = []
    for x, y, w, h in boxes.tolist():
        if w <= 0 or h <= 0:
            problems.append(f"box {[x, y, w, h]} has non-positive size (expected w > 0 and h > 0)")
        elif x < -tol or y < -tol or x + w > width + tol or y + h > height + tol:
            problems.append(f"box {[x, y, w, h]} leaves the {width}x{height} image")
    return problems
