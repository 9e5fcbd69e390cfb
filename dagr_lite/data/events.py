"""Event files of the released EventEgoHands layout: their header checks and ``EventFile``.

Event files are opened lazily and reopened in each process (h5py handles do not survive
pickling or forking), and event windows are read through ``timeidx`` so that a slice costs
its own events plus at most one frame interval of timestamps.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (registers the Blosc filter, 32001, before any file is opened)
import numpy as np

from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError, Problem


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
    if not len(p) or (p.min() >= 0 and p.max() <= 1 and np.issubdtype(p.dtype, np.integer)):
        return None  # the common case, in two reductions
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
        self._arrays: dict[str, h5py.Dataset] = {}  # the open file's arrays by key (a lookup costs ~2 ms)

    def frame_time_us(self, k):
        """Time of frame ``k`` (an int or an integer array) in microseconds, in this file's convention."""
        return fmt.frame_time_us(k, self.fps, self.convention)

    @property
    def num_frames(self) -> int:
        return len(self.timeidx)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_h5"], state["_pid"], state["_arrays"] = None, None, {}
        return state

    def _file(self) -> h5py.File:
        if self._h5 is None or self._pid != os.getpid():
            self._h5, self._pid, self._arrays = open_h5(self.path), os.getpid(), {}
        return self._h5

    def _array(self, key: str) -> h5py.Dataset:
        """The array ``key`` of this process's open file, looked up once."""
        h5 = self._file()
        if key not in self._arrays:
            self._arrays[key] = h5[key]
        return self._arrays[key]

    def close(self) -> None:
        if self._h5 is not None and self._pid == os.getpid():
            self._h5.close()
        self._h5, self._pid, self._arrays = None, None, {}

    def _read(self, key: str, start: int, stop: int) -> np.ndarray:
        """``key[start:stop]``; a failing read (a corrupt chunk, a lost disk) names the file and key."""
        try:
            values = self._array(key)[start:stop]
        except OSError as err:
            raise DatasetFormatError.at(self.path, f"cannot read entries {start}..{stop - 1} ({err})", key=key) from err
        return values.astype(np.int64, copy=False) if key == fmt.KEY_T else values

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
