"""Reading the released EventEgoHands layout: event files, frames, labels and the video list.

Event files are opened lazily and reopened in each process (h5py handles do not survive
pickling or forking), and event windows are read through ``timeidx`` so that a slice costs
its own events plus at most one frame interval of timestamps.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (registers the Blosc filter, 32001, before any file is opened)
import numpy as np
from PIL import Image

from dagr_lite.data import format as fmt


@dataclass(frozen=True)
class Problem:
    """One thing wrong in a dataset: the file, the key or frame (may be empty) and what was expected."""

    path: Path
    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.key}: {self.message}" if self.key else f"{self.path}: {self.message}"


class DatasetFormatError(ValueError):
    """A dataset does not follow the layout; the message names the file, key and expectation.

    ``problems`` holds each :class:`Problem`; the message lists them one per line.
    """

    def __init__(self, *problems: Problem):
        self.problems = list(problems)
        super().__init__("\n".join(str(p) for p in problems))

    @classmethod
    def at(cls, path: Path | str, message: str, key: str = "") -> "DatasetFormatError":
        return cls(Problem(Path(path), key, message))


# Opening files and the cheap header checks.

def open_h5(path: Path | str) -> h5py.File:
    """Open an event file read-only, with an error that names the file when it is not HDF5."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError.at(path, "events file is missing")
    try:
        return h5py.File(path, "r", rdcc_nbytes=8 * 1024 * 1024)
    except OSError as err:
        raise DatasetFormatError.at(path, f"cannot open as HDF5 ({err})") from err


def header_problems(h5: h5py.File, num_frames: int | None = None,
                    fps: float = fmt.DEFAULT_FPS) -> list[tuple[str, str]]:
    """Cheap structural checks of an open event file, as ``(key, message)`` pairs.

    Reads only shapes, ``timeidx`` and a handful of timestamps: missing keys, non-1-D arrays,
    unequal lengths, no events, ``timeidx`` out of range or decreasing, and ``timeidx``
    disagreeing with ``t`` at the first, middle and last frames. ``num_frames``, when given,
    is the number of frames on disk that ``timeidx`` must match.
    """
    problems: list[tuple[str, str]] = []
    for key in (*fmt.EVENT_KEYS, fmt.KEY_TIMEIDX):
        if key not in h5:
            problems.append((key, "key is missing"))
        elif not isinstance(h5[key], h5py.Dataset) or h5[key].ndim != 1:
            problems.append((key, f"expected a 1-D dataset, found {_describe(h5[key])}"))
    if problems:
        return problems
    lengths = {key: h5[key].shape[0] for key in fmt.EVENT_KEYS}
    num_events = lengths[fmt.KEY_T]
    for key, n in lengths.items():
        if n != num_events:
            problems.append((key, f"length {n} differs from {fmt.KEY_T} length {num_events}"))
    if num_events == 0:
        problems.append((fmt.KEY_T, "the file holds no events (expected at least one)"))
    for key in (*fmt.EVENT_KEYS, fmt.KEY_TIMEIDX):
        if not np.issubdtype(h5[key].dtype, np.integer):
            problems.append((key, f"dtype {h5[key].dtype} is not an integer type"))
    if problems:
        return problems
    timeidx = h5[fmt.KEY_TIMEIDX][()].astype(np.int64)
    if num_frames is not None and len(timeidx) != num_frames:
        problems.append((fmt.KEY_TIMEIDX, f"has {len(timeidx)} entries but {num_frames} frames exist on disk "
                                          "(expected one entry per frame)"))
    if len(timeidx) and (timeidx.min() < 0 or timeidx.max() > num_events):
        problems.append((fmt.KEY_TIMEIDX, f"values must lie in [0, {num_events}], found "
                                          f"[{timeidx.min()}, {timeidx.max()}]"))
    elif np.any(timeidx[1:] < timeidx[:-1]):
        k = int(np.argmax(timeidx[1:] < timeidx[:-1]))
        problems.append((fmt.KEY_TIMEIDX, f"decreases at frame {k + 1} ({timeidx[k]} -> {timeidx[k + 1]}); "
                                          "expected non-decreasing"))
    if problems:
        return problems
    t = h5[fmt.KEY_T]
    if t[0] < 0:
        problems.append((fmt.KEY_T, f"first timestamp is {t[0]}; expected microseconds >= 0 from the video start"))
    for k in sorted({0, len(timeidx) // 2, len(timeidx) - 1} if len(timeidx) else ()):
        i, t_frame = int(timeidx[k]), fmt.frame_time_us(k, fps)
        if (i < num_events and t[i] < t_frame) or (i > 0 and t[i - 1] >= t_frame):
            problems.append((fmt.KEY_TIMEIDX, f"entry {k} = {i} is not the first event at or after "
                                              f"frame time {t_frame} us"))
            break
    return problems


def _describe(node) -> str:
    if isinstance(node, h5py.Dataset):
        return f"a dataset of shape {node.shape}"
    return "a group"


class EventFile:
    """One ``<video>.h5`` event file, read by slices through ``timeidx``.

    The HDF5 handle is opened on first use in each process, so the object can be created in
    the main process and shipped to DataLoader workers. ``timeidx`` is held in memory (one
    integer per frame); events are never loaded whole.

    Args:
        path: the ``.h5`` file.
        fps: frame rate that defines frame times (``timeidx`` refers to them).
        num_frames: number of frames on disk; ``timeidx`` must have this many entries.
    """

    def __init__(self, path: Path | str, *, fps: float = fmt.DEFAULT_FPS, num_frames: int | None = None):
        self.path = Path(path)
        self.fps = float(fps)
        with open_h5(self.path) as h5:
            try:
                problems = header_problems(h5, num_frames, self.fps)
            except OSError as err:
                raise DatasetFormatError.at(self.path, f"cannot read the file's index ({err})") from err
            if problems:
                raise DatasetFormatError(*(Problem(self.path, key, msg) for key, msg in problems))
            self.num_events = int(h5[fmt.KEY_T].shape[0])
            self.timeidx = h5[fmt.KEY_TIMEIDX][()].astype(np.int64)  # (K,)
        self.frame_times = fmt.frame_time_us(np.arange(len(self.timeidx)), self.fps)  # (K,)
        self._h5: h5py.File | None = None
        self._pid: int | None = None

    @property
    def num_frames(self) -> int:
        return len(self.timeidx)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_h5"], state["_pid"] = None, None
        return state

    def _file(self) -> h5py.File:
        if self._h5 is None or self._pid != os.getpid():
            self._h5, self._pid = open_h5(self.path), os.getpid()
        return self._h5

    def close(self) -> None:
        if self._h5 is not None and self._pid == os.getpid():
            self._h5.close()
        self._h5, self._pid = None, None

    def _read(self, key: str, start: int, stop: int) -> np.ndarray:
        """``key[start:stop]``; a failing read (a corrupt chunk, a lost disk) names the file and key."""
        try:
            values = self._file()[key][start:stop]
        except OSError as err:
            raise DatasetFormatError.at(self.path, f"cannot read entries {start}..{stop - 1} ({err})", key=key) from err
        return values.astype(np.int64) if key == fmt.KEY_T else values

    def read(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Events ``[start, stop)`` by index, as arrays ``x, y, t, p`` of equal length (``t`` int64)."""
        start, stop = max(0, int(start)), min(self.num_events, int(stop))
        stop = max(start, stop)
        return {name: self._read(key, start, stop) for name, key in zip("xytp", fmt.EVENT_KEYS)}

    def _bracket(self, t_us: int) -> tuple[int, int]:
        """``[lo, hi]`` holding the index of the first event with ``t >= t_us``, from ``timeidx`` alone.

        Events before ``lo`` are earlier than the last frame time ``<= t_us``; events from ``hi`` on
        are not earlier than the next frame time. ``lo == hi`` at a frame time.
        """
        j = int(np.searchsorted(self.frame_times, t_us, side="right")) - 1  # last frame with time <= t_us
        if j >= 0 and self.frame_times[j] == t_us:
            return int(self.timeidx[j]), int(self.timeidx[j])
        lo = 0 if j < 0 else int(self.timeidx[j])
        hi = int(self.timeidx[j + 1]) if j + 1 < self.num_frames else self.num_events
        return lo, hi

    def index_of_time(self, t_us: int) -> int:
        """Index of the first event with ``t >= t_us``.

        ``timeidx`` brackets the answer within one frame interval; only the timestamps of that
        interval are read, and none at a frame time.
        """
        lo, hi = self._bracket(t_us)
        if hi <= lo:
            return lo
        t_segment = self._read(fmt.KEY_T, lo, hi)  # (hi - lo,)
        return lo + int(np.searchsorted(t_segment, t_us, side="left"))

    def window(self, t_start_us: int, t_end_us: int) -> dict[str, np.ndarray]:
        """All events with ``t_start_us <= t < t_end_us`` (empty arrays if there are none).

        One read of ``t`` covers the window plus at most one frame interval at each end; the
        other arrays are read for the window's own events only.
        """
        t_end_us = max(t_end_us, t_start_us)
        lo, _ = self._bracket(t_start_us)
        _, hi = self._bracket(t_end_us)
        t = self._read(fmt.KEY_T, lo, hi)  # (hi - lo,)
        start = int(np.searchsorted(t, t_start_us, side="left"))
        stop = int(np.searchsorted(t, t_end_us, side="left"))
        events = {name: self._read(key, lo + start, lo + stop)
                  for name, key in zip("xyp", (fmt.KEY_X, fmt.KEY_Y, fmt.KEY_P))}
        events["t"] = t[start:stop]
        return {name: events[name] for name in "xytp"}


# Frames.

def read_frame(path: Path | str, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Decode one frame to an ``(H, W, 3)`` uint8 RGB array; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError.at(path, "frame file is missing")
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB"))
    except (OSError, SyntaxError, ValueError) as err:
        raise DatasetFormatError.at(path, f"cannot decode image ({err})") from err
    if expected_hw is not None and array.shape[:2] != tuple(expected_hw):
        raise DatasetFormatError.at(path, f"frame is {array.shape[1]}x{array.shape[0]} (WxH), "
                                          f"expected {expected_hw[1]}x{expected_hw[0]}")
    return array


def frame_size(path: Path | str) -> tuple[int, int]:
    """``(H, W)`` of a frame from its header alone (no decoding)."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            width, height = image.size
    except FileNotFoundError as err:
        raise DatasetFormatError.at(path, "frame file is missing") from err
    except (OSError, SyntaxError, ValueError) as err:
        raise DatasetFormatError.at(path, f"cannot read image header ({err})") from err
    return height, width


def list_frames(directory: Path | str) -> dict[int, str]:
    """``{k: file name}`` of the ``frame_<k>.jpg`` files in a video's frame folder."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetFormatError.at(directory, "frame folder is missing")
    frames = {}
    for name in os.listdir(directory):
        k = fmt.parse_frame_name(name)
        if k is not None:
            frames[k] = name
    return frames


# Videos of a split.

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


# Labels.

Labels = dict[str, dict[int, np.ndarray]]  # video -> frame index -> (M, 4) float64 x_tl, y_tl, w, h


def load_labels_json(root: Path | str) -> dict:
    """The raw contents of ``bounding_boxes.json``; errors name the file."""
    path = fmt.labels_path(root)
    if not path.is_file():
        raise DatasetFormatError.at(path, "label file is missing")
    try:
        with open(path) as f:
            raw = json.load(f)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DatasetFormatError.at(path, f"cannot parse as JSON ({err})") from err
    if not isinstance(raw, dict):
        raise DatasetFormatError.at(path, f"expected a JSON object keyed <video>_frame_<k>, "
                                          f"found {type(raw).__name__}")
    return raw


def parse_boxes(value) -> np.ndarray:
    """A label value (a list of ``[x_tl, y_tl, w, h]``) as a ``(M, 4)`` float64 array.

    Raises ``ValueError`` describing what was expected when the value is malformed or not finite.
    """
    if not isinstance(value, list):
        raise ValueError(f"expected a list of [x_tl, y_tl, w, h] boxes, found {type(value).__name__}")
    for box in value:
        if (not isinstance(box, (list, tuple)) or len(box) != 4
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in box)):
            raise ValueError(f"expected a box [x_tl, y_tl, w, h] of 4 numbers, found {box!r}")
    boxes = np.asarray(value, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(boxes)):
        raise ValueError(f"boxes must be finite, found {boxes[~np.isfinite(boxes).all(axis=1)].tolist()}")
    return boxes


def read_labels(root: Path | str) -> Labels:
    """``bounding_boxes.json`` grouped by video and frame index; malformed entries raise naming the key."""
    path = fmt.labels_path(root)
    labels: Labels = {}
    for key, value in load_labels_json(root).items():
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


def box_problems(boxes: np.ndarray, height: int, width: int, tol: float = 1e-3) -> list[str]:
    """Geometric problems of ``(M, 4)`` xywh boxes in an image of ``height x width`` pixels."""
    problems = []
    for x, y, w, h in boxes.tolist():
        if w <= 0 or h <= 0:
            problems.append(f"box {[x, y, w, h]} has non-positive size (expected w > 0 and h > 0)")
        elif x < -tol or y < -tol or x + w > width + tol or y + h > height + tol:
            problems.append(f"box {[x, y, w, h]} leaves the {width}x{height} image")
    return problems
