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


@dataclass
class Header:
    """What the cheap checks of an event file found.

    ``problems``: ``(key, message)`` pairs; ``timeidx`` (int64) and ``num_events`` are filled
    when the arrays could be read; ``fitting``: the frame-time conventions that fit every
    ``timeidx`` entry examined (empty when there are problems).
    """

    problems: list[tuple[str, str]]
    timeidx: np.ndarray | None = None
    num_events: int = 0
    fitting: tuple[str, ...] = ()

    @property
    def convention(self) -> str | None:
        """The detected convention: the first that fits (``round`` when nothing tells them apart)."""
        return self.fitting[0] if self.fitting else None


# At most this many frames whose time differs between the conventions are examined on opening.
MAX_CONVENTION_PROBES = 64
# Polarities read on opening: this many events at each end of the file.
POLARITY_PROBE_EVENTS = 4096


def read_header(h5: h5py.File, num_frames: int | None = None, fps: float = fmt.DEFAULT_FPS) -> Header:
    """Cheap structural checks of an open event file and its frame-time convention.

    Reads only shapes, ``timeidx``, two timestamps around a bounded number of its entries and
    the polarities at both ends: missing keys, non-1-D arrays, unequal lengths, no events,
    ``timeidx`` out of range or decreasing, polarities outside {0, 1}, and ``timeidx``
    disagreeing with ``t`` at the first, middle and last frames and at up to
    ``MAX_CONVENTION_PROBES`` frames whose time differs between the conventions (those decide
    the convention). ``num_frames``, when given, is the number of frames on disk that
    ``timeidx`` must match.
    """
    problems = _structure_problems(h5)
    if problems:
        return Header(problems)
    num_events = int(h5[fmt.KEY_T].shape[0])
    timeidx = h5[fmt.KEY_TIMEIDX][()].astype(np.int64)
    header = Header(_timeidx_problems(timeidx, num_events, num_frames), timeidx, num_events)
    if header.problems:
        return header
    t = h5[fmt.KEY_T]
    first = int(t[0])
    if first < 0:
        header.problems.append((fmt.KEY_T, f"first timestamp is {first}; expected microseconds >= 0 "
                                           "from the video start"))
    header.problems += [(fmt.KEY_P, message) for message in _sampled_polarity_problems(h5[fmt.KEY_P])]
    timeidx_problems, header.fitting = _convention_problems(t, timeidx, fps)
    header.problems += timeidx_problems
    if header.problems:
        header.fitting = ()
    return header


def header_problems(h5: h5py.File, num_frames: int | None = None,
                    fps: float = fmt.DEFAULT_FPS) -> list[tuple[str, str]]:
    """The ``(key, message)`` problems of :func:`read_header`."""
    return read_header(h5, num_frames, fps).problems


def _structure_problems(h5: h5py.File) -> list[tuple[str, str]]:
    """Missing keys, non-1-D or non-integer arrays, unequal lengths, no events."""
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
    return problems


def _timeidx_problems(timeidx: np.ndarray, num_events: int, num_frames: int | None) -> list[tuple[str, str]]:
    """``timeidx`` of the wrong length, out of ``[0, num_events]`` or decreasing."""
    problems = []
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
    return problems


def polarity_problem(p: np.ndarray, start: int) -> str | None:
    """What is wrong with polarities ``p`` (events ``start, start + 1, ...``), or None if all are 0 or 1."""
    bad = np.flatnonzero((p != 0) & (p != 1))
    if not len(bad):
        return None
    return (f"values must be 0 or 1, found {p[bad[0]]} at index {start + int(bad[0])} "
            f"(in events {start}..{start + len(p) - 1})")


def _sampled_polarity_problems(p: h5py.Dataset) -> list[str]:
    n = p.shape[0]
    blocks = sorted({(0, min(n, POLARITY_PROBE_EVENTS)), (max(0, n - POLARITY_PROBE_EVENTS), n)})
    for lo, hi in blocks:
        message = polarity_problem(p[lo:hi], lo)
        if message is not None:
            return [message]
    return []


def probe_frames(num_frames: int, fps: float = fmt.DEFAULT_FPS, limit: int = MAX_CONVENTION_PROBES) -> list[int]:
    """Frames whose ``timeidx`` entry the opening check compares with ``t``, ascending.

    The first, middle and last frames, and up to ``limit`` of the frames whose time differs
    between the conventions, evenly spread and always including the first and last of them.
    """
    differing = fmt.differing_frames(num_frames, fps)
    if len(differing) > limit:
        differing = differing[np.unique(np.linspace(0, len(differing) - 1, limit).round().astype(np.int64))]
    ends = {0, num_frames // 2, num_frames - 1} if num_frames else set()
    return sorted(ends | {int(k) for k in differing})


def _t_around(t: h5py.Dataset, i: int, n: int) -> tuple[int | None, int | None]:
    """``(t[i - 1], t[i])``, None where the index lies outside ``[0, n)``."""
    segment = t[max(i - 1, 0):min(i + 1, n)].astype(np.int64)
    return (int(segment[0]) if i > 0 else None), (int(segment[-1]) if i < n else None)


def _fits(before: int | None, at: int | None, t_frame: int) -> bool:
    """Whether an entry between events at ``before`` and ``at`` is the first event at or after ``t_frame``."""
    return (at is None or at >= t_frame) and (before is None or before < t_frame)


def _first_at_or_after(t: h5py.Dataset, t_us: int) -> int:
    """Index of the first event with ``t >= t_us``, by bisection (about 30 reads of one value)."""
    lo, hi = 0, t.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if int(t[mid]) < t_us:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _convention_problems(t: h5py.Dataset, timeidx: np.ndarray, fps: float) -> tuple[list, tuple[str, ...]]:
    """``timeidx`` against ``t`` at the :func:`probe_frames`: the problem, or the conventions that fit."""
    n = t.shape[0]
    fitting, ruled_out = list(fmt.FRAME_TIME_CONVENTIONS), {}
    for k in probe_frames(len(timeidx), fps):
        before, at = _t_around(t, int(timeidx[k]), n)
        for convention in list(fitting):
            if not _fits(before, at, fmt.frame_time_us(k, fps, convention)):
                fitting.remove(convention)
                ruled_out[convention] = k
        if not fitting:
            expected = {c: (_first_at_or_after(t, t_frame), t_frame)
                        for c in fmt.FRAME_TIME_CONVENTIONS for t_frame in [fmt.frame_time_us(k, fps, c)]}
            return [(fmt.KEY_TIMEIDX, fits_neither_message(k, int(timeidx[k]), expected, ruled_out))], ()
    return [], tuple(fitting)


def fits_neither_message(k: int, stored: int, expected: dict[str, tuple[int, int]], ruled_out: dict[str, int]) -> str:
    """The problem of ``timeidx`` entry ``k``, the first that no frame-time convention explains.

    ``expected``: per convention, the entry it implies and the frame time; ``ruled_out``: per
    convention, the entry that first disagreed with it.
    """
    options = " or ".join(f"{index} ({convention}: first event at or after {t_frame} us)"
                          for convention, (index, t_frame) in expected.items())
    message = f"entry {k} = {stored} fits neither frame-time convention; expected {options}"
    earlier = [f"entry {ruled_out[c]} rules out {c}" for c, (index, _) in expected.items()
               if index == stored and ruled_out.get(c, k) != k]
    return message + (f" ({', '.join(earlier)})" if earlier else "")


def _describe(node) -> str:
    if isinstance(node, h5py.Dataset):
        return f"a dataset of shape {node.shape}"
    return "a group"


class EventFile:
    """One ``<video>.h5`` event file, read by slices through ``timeidx``.

    The HDF5 handle is opened on first use in each process, so the object can be created in
    the main process and shipped to DataLoader workers. ``timeidx`` is held in memory (one
    integer per frame); events are never loaded whole.

    Frame times follow the file's own convention (see :mod:`dagr_lite.data.format`), detected
    on opening: :attr:`convention`, :meth:`frame_time_us`. Reads check that every polarity is
    0 or 1.

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
                header = read_header(h5, num_frames, self.fps)
            except OSError as err:
                raise DatasetFormatError.at(self.path, f"cannot read the file's index ({err})") from err
        if header.problems:
            raise DatasetFormatError(*(Problem(self.path, key, msg) for key, msg in header.problems))
        self.num_events = header.num_events
        self.timeidx = header.timeidx  # (K,)
        self.convention: str = header.convention
        self.frame_times = fmt.frame_time_us(np.arange(len(self.timeidx)), self.fps, self.convention)  # (K,)
        self._h5: h5py.File | None = None
        self._pid: int | None = None

    def frame_time_us(self, k):
        """Time of frame ``k`` (an int or an integer array) in microseconds, in this file's convention."""
        return fmt.frame_time_us(k, self.fps, self.convention)

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

    def _read_polarity(self, start: int, stop: int) -> np.ndarray:
        """``p[start:stop]``, raising naming the file, key, value and index when one is not 0 or 1."""
        p = self._read(fmt.KEY_P, start, stop)
        message = polarity_problem(p, start)
        if message is not None:
            raise DatasetFormatError.at(self.path, message, key=fmt.KEY_P)
        return p

    def read(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Events ``[start, stop)`` by index, as arrays ``x, y, t, p`` of equal length (``t`` int64)."""
        start, stop = max(0, int(start)), min(self.num_events, int(stop))
        stop = max(start, stop)
        events = {name: self._read(key, start, stop) for name, key in zip("xyt", fmt.EVENT_KEYS)}
        events["p"] = self._read_polarity(start, stop)
        return events

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
        events = {name: self._read(key, lo + start, lo + stop) for name, key in zip("xy", (fmt.KEY_X, fmt.KEY_Y))}
        events["t"], events["p"] = t[start:stop], self._read_polarity(lo + start, lo + stop)
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


# JPEG markers: start and end of image, start of scan, and the frame headers (SOF0..SOF15 but
# DHT, JPG and DAC), which hold the image size.
_SOI, _EOI, _SOS = 0xD8, 0xD9, 0xDA
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE_MARKERS = frozenset({0x01, *range(0xD0, 0xD8)})
_JPEG_READ = 4096
_JPEG_TAIL = 32


def jpeg_size(path: Path | str) -> tuple[int, int]:
    """``(H, W)`` of a JPEG file from its frame header, without decoding; errors name the file.

    Reads the first few KB (more only when large metadata segments come first) and the last
    bytes: a file that does not start as a JPEG, has no frame header before its image data,
    or lacks the end-of-image marker near its end (a truncated file) is an error.
    """
    try:
        with open(path, "rb", buffering=0) as f:
            size = _jpeg_frame_size(f)
            f.seek(max(0, f.seek(0, os.SEEK_END) - _JPEG_TAIL))
            tail = f.read(_JPEG_TAIL)
    except FileNotFoundError as err:
        raise DatasetFormatError.at(path, "frame file is missing") from err
    except OSError as err:
        raise DatasetFormatError.at(path, f"cannot read the frame ({err})") from err
    except _NotJpeg as err:
        raise DatasetFormatError.at(path, f"not a readable JPEG: {err}") from err
    if bytes((0xFF, _EOI)) not in tail:
        raise DatasetFormatError.at(path, "not a readable JPEG: no end-of-image marker at the end (truncated file?)")
    return size


class _NotJpeg(Exception):
    pass


def _jpeg_frame_size(f) -> tuple[int, int]:
    """``(H, W)`` from the first frame header of the JPEG stream in binary file ``f``."""
    data, base = f.read(_JPEG_READ), 0  # data holds the bytes from offset base on
    if data[:2] != bytes((0xFF, _SOI)):
        raise _NotJpeg("does not start with the JPEG start-of-image marker")
    pos = 2
    while True:
        if pos + 9 > base + len(data):  # the next segment's head lies beyond what was read
            f.seek(pos)
            data, base = f.read(_JPEG_READ), pos
            if len(data) < 4:
                raise _NotJpeg(f"file ends at byte {pos} before the frame header (truncated header)")
        i = pos - base
        if data[i] != 0xFF:
            raise _NotJpeg(f"expected a marker at byte {pos}, found 0x{data[i]:02x}")
        marker = data[i + 1]
        if marker == 0xFF or marker in _STANDALONE_MARKERS:
            pos += 1 if marker == 0xFF else 2
            continue
        if marker in (_SOS, _EOI, _SOI):
            raise _NotJpeg(f"no frame header before marker 0x{marker:02x} at byte {pos}")
        if marker in _SOF_MARKERS:
            if len(data) < i + 9:
                raise _NotJpeg(f"file ends inside the frame header at byte {pos} (truncated header)")
            height, width = int.from_bytes(data[i + 5:i + 7], "big"), int.from_bytes(data[i + 7:i + 9], "big")
            if height == 0 or width == 0:
                raise _NotJpeg(f"frame header gives a size of {width}x{height} (WxH)")
            return height, width
        pos += 2 + int.from_bytes(data[i + 2:i + 4], "big")


def frame_header_problems(frames: dict[int, Path], expected_hw: tuple[int, int] | None,
                          expected_from: str = "", read_size=None) -> tuple[list[Problem], tuple[int, int] | None]:
    """Every frame's JPEG header read (:func:`jpeg_size`) and its size compared, in frame order.

    ``frames``: frame index -> file. ``expected_hw``: the size every frame must have; None takes
    the first readable frame's. ``expected_from`` says where the expected size comes from
    (``"as configured"``), for the messages. ``read_size(path) -> (H, W)`` replaces
    :func:`jpeg_size` (to decode the frames, say). Returns the problems and the size.
    """
    read_size = read_size or jpeg_size
    problems = []
    for k in sorted(frames):
        path = frames[k]
        try:
            hw = read_size(path)
        except DatasetFormatError as err:
            problems += err.problems
            continue
        if expected_hw is None:
            expected_hw, expected_from = hw, f"as {path.name}"
        elif hw != expected_hw:
            problems.append(Problem(path, "", f"frame is {hw[1]}x{hw[0]} (WxH), expected {expected_hw[1]}x"
                                              f"{expected_hw[0]}{' ' + expected_from if expected_from else ''}"))
    return problems, expected_hw


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
        raise ValueError(f"expected a list of [x_tl, y_tl, w, h] boxes, found {type(value).__name__}")
    for box in value:
        if (not isinstance(box, (list, tuple)) or len(box) != 4
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in box)):
            raise ValueError(f"expected a box [x_tl, y_tl, w, h] of 4 numbers, found {box!r}")
    boxes = np.asarray(value, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(boxes)):
        raise ValueError(f"boxes must be finite, found {boxes[~np.isfinite(boxes).all(axis=1)].tolist()}")
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
