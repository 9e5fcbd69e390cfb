"""The EventEgoHands data contract: every name and formula of the on-disk layout, in one place.

Layout (as released)::

    <root>/{train,valid,test}/events/<video>.h5
          events/x  events/y  events/t  events/p     1-D, same length; p in {0, 1}
          timeidx                                     1-D, one entry per frame
    <root>/{train,valid,test}/frames/<video>/frame_<k>.jpg   k = 0, 1, ... (no zero padding)
    <root>/bounding_boxes.json   {"<video>_frame_<k>": [[x_tl, y_tl, w, h], ...], ...}

``t`` is in microseconds from the start of the video, sorted ascending. ``timeidx[k]`` is the
index of the first event with ``t >= frame_time_us(k)``, so the events of ``[t_a, t_b)`` form one
contiguous slice. Boxes are top-left x, y, width, height in pixels of the version's resolution.

Frame times follow one of two conventions (:data:`FRAME_TIME_CONVENTIONS`), which differ by 1 us
at some frames (960 of the 2700 frames of a 90 s video at 30 fps, the last one included):

* ``"round"``: ``round(1e6 * k / fps)``. This package writes every file this way.
* ``"truncate"``: ``int(1e6 * ((1 / fps) * k))`` in float64, as the EventEgoHands reference
  loader computes them; a release file's ``timeidx`` may have been built this way.

Readers accept either: each file's convention is detected from its own ``timeidx`` and ``t``
and then used for all of its frame times (event windows, image and label times).

Everything else in the package imports these names instead of spelling them again.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError

# Splits, folders and files.
SPLITS = ("train", "valid", "test")
EVENTS_DIR = "events"
FRAMES_DIR = "frames"
EVENTS_SUFFIX = ".h5"
LABELS_FILE = "bounding_boxes.json"

# HDF5 keys.
KEY_X = "events/x"
KEY_Y = "events/y"
KEY_T = "events/t"
KEY_P = "events/p"
EVENT_KEYS = (KEY_X, KEY_Y, KEY_T, KEY_P)
KEY_TIMEIDX = "timeidx"

# Default frame rate of EgoHands (and so of every EventEgoHands version).
DEFAULT_FPS = 30.0
# The event window of one sample, one frame period at 30 fps, in microseconds: conf/data's window_us
# (tests/test_config.py holds them equal) and the window the dataset statistics draw.
DEFAULT_WINDOW_US = 33_333

_FRAME_RE = re.compile(r"^frame_(0|[1-9][0-9]*)\.jpg$")
_LABEL_KEY_RE = re.compile(r"^(?P<video>.+)_frame_(?P<k>0|[1-9][0-9]*)$")


# Frame-time conventions: ``round`` (written by this package) and ``truncate`` (accepted on reading).
FRAME_TIME_CONVENTIONS = ("round", "truncate")
WRITTEN_CONVENTION = "round"


def frame_time_us(k, fps: float = DEFAULT_FPS, convention: str = WRITTEN_CONVENTION):
    """Timestamp of frame ``k`` in microseconds under a frame-time convention.

    ``"round"``: ``round(1e6 * k / fps)``, half to even (as Python's ``round`` and ``np.rint``).
    ``"truncate"``: ``int(1e6 * ((1 / fps) * k))``, the same float64 operations in the same order,
    truncated toward zero. Works on ints and integer arrays; returns an int for an int and an
    int64 array for an array.
    """
    k = np.asarray(k, dtype=np.float64)
    if convention == "round":
        times = np.rint(1e6 * k / float(fps))
    elif convention == "truncate":
        times = np.trunc(1e6 * ((1.0 / float(fps)) * k))
    else:
        raise UserError(f"frame-time convention must be one of {FRAME_TIME_CONVENTIONS}, got {convention!r}")
    times = times.astype(np.int64)
    return int(times) if times.ndim == 0 else times


def differing_frames(num_frames: int, fps: float = DEFAULT_FPS) -> np.ndarray:
    """Indices of the frames whose time differs between the two conventions, ascending."""
    k = np.arange(num_frames)
    return np.flatnonzero(frame_time_us(k, fps, "round") != frame_time_us(k, fps, "truncate"))


def expected_timeidx(t: np.ndarray, num_frames: int, fps: float = DEFAULT_FPS,
                     convention: str = WRITTEN_CONVENTION) -> np.ndarray:
    """``timeidx`` of sorted timestamps ``t``: for each frame, the index of the first ``t >= t_frame``."""
    frame_times = frame_time_us(np.arange(num_frames), fps, convention)
    return np.searchsorted(t, frame_times, side="left").astype(np.int64)


def events_path(root: Path | str, split: str, video: str) -> Path:
    return Path(root) / split / EVENTS_DIR / f"{video}{EVENTS_SUFFIX}"


def frames_dir(root: Path | str, split: str, video: str) -> Path:
    return Path(root) / split / FRAMES_DIR / video


def frame_name(k: int) -> str:
    """File name of frame ``k``: ``frame_<k>.jpg``, no zero padding."""
    return f"frame_{int(k)}.jpg"


def frame_path(root: Path | str, split: str, video: str, k: int) -> Path:
    return frames_dir(root, split, video) / frame_name(k)


def parse_frame_name(name: str) -> int | None:
    """Frame index of a file called ``frame_<k>.jpg``, or None for any other name."""
    match = _FRAME_RE.match(name)
    return int(match.group(1)) if match else None


def labels_path(root: Path | str) -> Path:
    return Path(root) / LABELS_FILE


def label_key(video: str, k: int) -> str:
    """Key of frame ``k`` of ``video`` in ``bounding_boxes.json``: ``<video>_frame_<k>``."""
    return f"{video}_frame_{int(k)}"


def parse_label_key(key: str) -> tuple[str, int] | None:
    """``(video, k)`` of a label key, or None if it is not of the form ``<video>_frame_<k>``.

    Video names may themselves contain underscores; the last ``_frame_`` splits the key.
    """
    match = _LABEL_KEY_RE.match(key)
    return (match.group("video"), int(match.group("k"))) if match else None


def label_video(key: str) -> str | None:
    """The video a label key belongs to, or None if the key is malformed."""
    parsed = parse_label_key(key)
    return parsed[0] if parsed else None


def xywh_to_xyxy(boxes: np.ndarray) -> np.ndarray:
    """``(M, 4)`` top-left x, y, width, height -> ``(M, 4)`` x1, y1, x2, y2 (same units)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return np.concatenate([boxes[:, :2], boxes[:, :2] + boxes[:, 2:]], axis=1)


def xyxy_to_xywh(boxes: np.ndarray) -> np.ndarray:
    """``(M, 4)`` x1, y1, x2, y2 -> ``(M, 4)`` top-left x, y, width, height (same units)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
