"""The times a Prophesee file's words give its events, before any decoder makes them monotonic.

faery's decoders for EVT 2.0, EVT 3.0 and DAT give an event stamped earlier than the event before
it that event's time (a clamp: the event is silently re-timed later), so a time-order check on
their output sees nothing. :func:`scan_times` reads the words themselves with the decoder's own
rules for a clock that wraps, and counts the events the decoder will re-time, so that
``order=refuse`` can refuse them and ``order=sort`` can count them.

The decoders' rules, as measured on faery 0.7 (tests/camera/test_rawtime.py):

- EVT 2.0 (32-bit words): a ``TIME_HIGH`` word (type 0x8) holds bits 6-33 of the time, each CD
  event (type 0x0 off, 0x1 on) bits 0-5. A ``TIME_HIGH`` lower than the one before is read as the
  34-bit clock's wrap (2^34 us added).
- EVT 3.0 (16-bit words): ``TIME_HIGH`` (0x8) holds bits 12-23, ``TIME_LOW`` (0x6) bits 0-11; an
  ``ADDR_X`` word (0x2) is one event, a ``VECT_12`` (0x4) or ``VECT_8`` (0x5) word one event per
  bit set. No wrap is read: a ``TIME_HIGH`` lower than the one before (the 24-bit clock's wrap
  after 16.8 s too) is not taken, so every event after it is re-timed until the time catches up.
- DAT (8-byte events, a 32-bit time then the address): a time more than 2^31 us below the one
  before is the 32-bit clock's wrap (2^32 us added).

An AEDAT4 event packet may be compressed and an Event Stream file stores unsigned time steps (it
cannot go back in time), so neither is scanned for time. :func:`es_dvs_overrun` walks a DVS Event
Stream file's bytes to see whether its last event is whole.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

BLOCK_BYTES = 1 << 26  # read 64 MiB of words at a time


@dataclass
class Retimed:
    """Events of a file stamped earlier than an event before them (its decoder gives them a later time)."""
    events: int = 0  # events the words hold
    late: int = 0
    first_at: int | None = None  # the first such event's index in the file
    first_t: int | None = None  # its time as written (us)
    first_after: int | None = None  # the latest time written before it (us)


# state: [high, low, overflow, top, events, late, first_at, first_t, first_after, previous]
NO_FIRST = -1


@numba.njit(cache=True, nogil=True)
def _note(state, t):
    if t < state[3]:
        if state[5] == 0:
            state[6], state[7], state[8] = state[4], t, state[3]
        state[5] += 1
    else:
        state[3] = t
    state[4] += 1


@numba.njit(cache=True, nogil=True)
def _scan_evt2(words, state):
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        kind = w >> 28
        if kind == 8:
            high = w & 0x0FFFFFFF
            if high < state[0]:
                state[2] += np.int64(1) << 34
            state[0] = high
        elif kind <= 1:
            _note(state, state[2] + ((state[0] << 6) | ((w >> 22) & 0x3F)))


@numba.njit(cache=True, nogil=True)
def _scan_evt3(words, state):
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        kind = w >> 12
        if kind == 8:
            state[0] = w & 0xFFF
        elif kind == 6:
            state[1] = w & 0xFFF
        elif kind == 2 or kind == 4 or kind == 5:
            t = (state[0] << 12) | state[1]
            bits = 1 if kind == 2 else (w & 0xFFF if kind == 4 else w & 0xFF)
            count = 1
            if kind != 2:
                count = 0
                while bits:
                    count += bits & 1
                    bits >>= 1
            for _ in range(count):
                _note(state, t)


@numba.njit(cache=True, nogil=True)
def _scan_dat(times, state):
    for i in range(times.shape[0]):
        raw = np.int64(times[i])
        if state[9] - raw > (np.int64(1) << 31):
            state[2] += np.int64(1) << 32
        state[9] = raw
        _note(state, state[2] + raw)


def payload_start(head: bytes, dat: bool) -> int:
    """Where the words of an EVT or DAT file begin: after the ``%`` header lines (and, in DAT, the
    event type and size bytes)."""
    at = 0
    while head.startswith(b"%", at):
        end = head.find(b"\n", at)
        if end < 0:
            return len(head)
        at = end + 1
    return at + 2 if dat else at


def evt_version(head: bytes) -> int:
    """2 or 3: the EVT version a ``.raw`` file's header names (3 where it names none, as faery reads it)."""
    lowered = head.lower()
    return 2 if b"evt 2" in lowered or b"evt2" in lowered else 3


def header_t0(head: bytes) -> int:
    """The ``% t0`` (EVT) or ``% T0`` (DAT) line's time in microseconds, which faery adds to every
    event's time (0 without one)."""
    for line in head[:payload_start(head, False)].splitlines():
        words = line.lstrip(b"% ").split()
        if len(words) == 2 and words[0].lower() == b"t0" and words[1].isdigit():
            return int(words[1])
    return 0


def scan_times(path: Path | str, kind: str) -> Retimed:
    """Count the events of an EVT (``kind="evt"``) or DAT (``"dat"``) file written earlier than an
    event before them; read in blocks, so a file of any size takes a little memory."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    start = payload_start(head, kind == "dat")
    if kind == "dat":
        word, scan, dtype = 8, _scan_dat, np.dtype("<u4")
    elif evt_version(head) == 2:
        word, scan, dtype = 4, _scan_evt2, np.dtype("<u4")
    else:
        word, scan, dtype = 2, _scan_evt3, np.dtype("<u2")
    state = np.zeros(10, np.int64)
    state[3] = np.iinfo(np.int64).min
    size = path.stat().st_size
    whole = (size - start) // word * word
    block = BLOCK_BYTES // word * word
    with open(path, "rb") as f:
        for offset in range(0, whole, block):
            f.seek(start + offset)
            data = np.frombuffer(f.read(min(block, whole - offset)), dtype)
            scan(data[::2] if kind == "dat" else data, state)
    found = Retimed(events=int(state[4]), late=int(state[5]))
    if found.late:
        t0 = header_t0(head)
        found.first_at, found.first_t, found.first_after = int(state[6]), t0 + int(state[7]), t0 + int(state[8])
    return found


ES_DVS_HEADER = 20  # "Event Stream", version (3 bytes), type (1: DVS), width and height (2 bytes each)


@numba.njit(cache=True, nogil=True)
def _es_dvs_end(data, start):
    """Where the byte walk of DVS events ends: 0xFF (a time overflow) and 0xFE (a reset) are one byte,
    any other first byte begins a 5-byte event (time step and polarity, x, y)."""
    at = start
    n = data.shape[0]
    while at < n:
        at += 1 if data[at] >= 0xFE else 5
    return at


def es_dvs_overrun(path: Path | str) -> int | None:
    """For a DVS Event Stream file: how many bytes its last event lacks (0: the file ends on a whole
    event); None for the other ES types (ATIS, generic, colour), which are not walked."""
    data = np.memmap(path, np.uint8, mode="r")
    if len(data) < ES_DVS_HEADER or data[15] != 1:
        return None
    return int(_es_dvs_end(data, ES_DVS_HEADER)) - len(data)
