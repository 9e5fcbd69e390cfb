"""The raw time scan counts exactly the events faery's EVT2, EVT3 and DAT decoders re-time.

Files are encoded here word by word from known times (independent of the scanner), disorder is
made where the decoders clamp it, and faery's own output is the reference: an event is re-timed
where faery gives it a later time than the one written.
"""
from __future__ import annotations

import numpy as np
import pytest

from dagr_lite.camera.rawtime import scan_times
from dagr_lite.camera.recording import RecordingError, concat, open_recording

WIDTH, HEIGHT = 64, 48
T0 = 5_000  # the header's t0, added to every time by the decoder


def header(kind: str) -> bytes:
    if kind == "dat":
        return f"% Version 2\n% Width {WIDTH}\n% Height {HEIGHT}\n% T0 {T0}\n".encode() + bytes([0x0C, 0x08])
    return (f"% evt {kind[-1]}.0\n% format EVT{kind[-1]};width={WIDTH};height={HEIGHT}\n"
            f"% geometry {WIDTH}x{HEIGHT}\n% t0 {T0}\n").encode()


def encode(kind: str, t, x, y, p) -> bytes:
    """A file of ``kind`` ("evt2", "evt3", "dat") holding the events in the order given, times
    relative to the header's t0."""
    words = []
    if kind == "dat":
        for ti, xi, yi, pi in zip(t, x, y, p):
            words += [int(ti), int(xi) | int(yi) << 14 | int(pi) << 28]
        return header(kind) + np.array(words, "<u4").tobytes()
    high = low = row = None
    for ti, xi, yi, pi in zip(t, x, y, p):
        ti = int(ti)
        if kind == "evt2":
            if ti >> 6 != high:
                high = ti >> 6
                words.append(0x8 << 28 | high)
            words.append(int(pi) << 28 | (ti & 63) << 22 | int(xi) << 11 | int(yi))
        else:
            if ti >> 12 != high:
                high = ti >> 12
                words.append(0x8000 | high)
            if ti & 0xFFF != low:
                low = ti & 0xFFF
                words.append(0x6000 | low)
            if yi != row:
                row = yi
                words.append(int(yi))
            words.append(0x2000 | int(pi) << 11 | int(xi))
    return header(kind) + np.array(words, "<u4" if kind == "evt2" else "<u2").tobytes()


def decoded_t(path) -> np.ndarray:
    import faery

    return np.concatenate([packet["t"].view(np.int64) for packet in faery.events_stream_from_file(path)])


def camera_events(seed: int, n: int = 20_000):
    """Several events per pixel and microsecond, in time order, over 50 ms."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 50_000, n))
    return t, rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n), rng.integers(0, 2, n)


KINDS = ["evt2", "evt3", "dat"]


def write(tmp_path, kind, *events):
    path = tmp_path / f"rec_{kind}{'.dat' if kind == 'dat' else '.raw'}"
    path.write_bytes(encode(kind, *events))
    return path


@pytest.mark.parametrize("kind", KINDS)
def test_in_order_file_has_nothing_retimed_and_every_event_counted(tmp_path, kind):
    t, x, y, p = camera_events(0)
    path = write(tmp_path, kind, t, x, y, p)
    assert np.array_equal(decoded_t(path), T0 + t)  # the encoder above writes what faery reads
    found = scan_times(path, kind[:3])
    assert (found.events, found.late, found.first_at) == (len(t), 0, None)


@pytest.mark.parametrize("kind", KINDS)
def test_late_events_are_exactly_those_the_decoder_moves_later(tmp_path, kind):
    t, x, y, p = camera_events(1)
    bucket = {"evt2": 64, "evt3": 4096, "dat": 4096}[kind]  # disorder the decoder clamps, not a wrap
    rng = np.random.default_rng(2)
    t = t.copy()
    for start in rng.choice(len(t) - 50, 300, replace=False):  # reverse short runs inside one bucket
        stop = start + int(rng.integers(2, 20))
        if t[start] // bucket == t[stop - 1] // bucket:
            t[start:stop] = t[start:stop][::-1].copy()
    path = write(tmp_path, kind, t, x, y, p)
    got = decoded_t(path)
    moved = np.flatnonzero(got != T0 + t)
    assert len(moved) > 100 and np.all(got[moved] > T0 + t[moved])  # faery re-times them later
    assert np.array_equal(got, np.maximum.accumulate(T0 + t))  # ... to the latest time before them
    found = scan_times(path, kind[:3])
    assert (found.events, found.late) == (len(t), len(moved))
    first = int(moved[0])
    assert (found.first_at, found.first_t, found.first_after) == (first, T0 + t[first], T0 + t[:first].max())


def test_wraps_follow_each_decoder(tmp_path):
    """DAT: a time 2^31 us below the one before is the 32-bit clock's wrap; EVT2: any lower
    TIME_HIGH is the 34-bit clock's; EVT3 reads no wrap: a lower TIME_HIGH is not taken, so what
    follows keeps the higher one (faery re-times it)."""
    t = np.array([100, 200, (1 << 32) - 50, 30, 60])
    path = write(tmp_path, "dat", t, *np.ones((3, 5), int))
    assert np.array_equal(decoded_t(path), T0 + np.array([100, 200, (1 << 32) - 50, (1 << 32) + 30, (1 << 32) + 60]))
    assert scan_times(path, "dat").late == 0
    t = np.array([100, 700, 300, 310])  # TIME_HIGH 10, then 4: read as a wrap
    path = write(tmp_path, "evt2", t, *np.ones((3, 4), int))
    assert decoded_t(path)[2] == T0 + (1 << 34) + 300 and scan_times(path, "evt2").late == 0
    t = np.array([4000 << 12, 10 << 12, (10 << 12) + 5])  # the 24-bit clock's wrap, or a step back
    path = write(tmp_path, "evt3", t, *np.ones((3, 3), int))
    assert np.array_equal(decoded_t(path), T0 + np.array([4000 << 12, 4000 << 12, (4000 << 12) + 5]))
    found = scan_times(path, "evt")
    assert (found.late, found.first_at) == (2, 1)


def test_evt3_vector_words_count_one_event_per_bit(tmp_path):
    words = [0x8000, 0x6000 | 7, 0x0003, 0x3000 | 1 << 11 | 4, 0x4000 | 0b101000000011, 0x5000 | 0b1001,
             0x6000 | 3, 0x2000 | 9]
    path = tmp_path / "vec.raw"
    path.write_bytes(header("evt3") + np.array(words, "<u2").tobytes())
    got = decoded_t(path)
    assert len(got) == 7 and np.array_equal(got, T0 + np.array([7] * 6 + [7]))
    found = scan_times(path, "evt")
    assert (found.events, found.late, found.first_at) == (7, 1, 6)


@pytest.mark.parametrize("kind", KINDS)
def test_order_refuse_refuses_and_sort_counts_what_the_decoder_retimes(tmp_path, kind):
    t = np.arange(20) * 3
    t[[5, 6, 7]] = t[[7, 5, 6]]  # one event early by two places: 15 and 18 follow 21
    path = write(tmp_path, kind, t, np.arange(20), np.ones(20, int), np.ones(20, int))
    with pytest.raises(RecordingError, match=rf"{path.name}: 2 of 20 events are written out of time order; the "
                                             rf"first is event 6 at t={T0 + 15} us, after an event at t={T0 + 21} us"):
        open_recording(path, order="refuse")
    recording = open_recording(path)
    assert recording.retimed.late == 2
    assert np.array_equal(concat(list(recording.events()))["t"], T0 + np.maximum.accumulate(t))


def test_uppercase_suffix_reads_as_its_format(tmp_path):
    import faery

    t, x, y, p = camera_events(3, 500)
    path = write(tmp_path, "evt3", t, x, y, p)
    upper = path.rename(tmp_path / "REC.RAW")
    assert np.array_equal(concat(list(open_recording(upper).events()))["t"], T0 + t)
    packed = np.zeros(len(t), faery.EVENTS_DTYPE)
    packed["t"], packed["x"], packed["y"], packed["on"] = t, x, y, p > 0
    faery.events_stream_from_array(packed, dimensions=(WIDTH, HEIGHT)).to_file(str(tmp_path / "rec.es"))
    upper = (tmp_path / "rec.es").rename(tmp_path / "REC.ES")
    assert np.array_equal(concat(list(open_recording(upper).events()))["t"], t - t[0])  # ES counts from its first event
