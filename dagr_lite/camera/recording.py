"""Event recordings of any camera, read in time-ordered chunks.

:func:`open_recording` reads, by the file's suffix:

=================  =============================================  ==========================
suffix             camera / format                                read by
=================  =============================================  ==========================
``.aedat4``        iniVation DAVIS, DVXplorer (frame tracks too)  faery
``.raw``           Prophesee EVT2, EVT2.1, EVT3                   faery
``.dat``           Prophesee DAT                                  faery
``.es``            Event Stream (ATIS, DVS)                       faery
``.csv``           ``t,x,y,on`` text                              this module
``.h5``            this package's dataset layout                  :class:`~dagr_lite.data.events.EventFile`
=================  =============================================  ==========================

Events come as dicts of numpy arrays ``x, y, t, p`` (integers: ``t`` int64 microseconds on the
recording's own clock, which need not start at 0; ``p`` 0 or 1; ``x, y`` as the decoder gives them), a chunk at a time, so a recording of hundreds of
millions of events never sits in memory whole. Real recordings are not always in time order: with
``order="sort"`` events are sorted within a buffer of ``order_window_us``, and an event later than
that is an error naming where it is; with ``order="refuse"`` the first disorder is an error that
says how many events are out of order and where the first is. faery's binary decoders (AEDAT4, EVT,
DAT, ES) hold the clock non-decreasing (an event earlier than the one before it comes out at that
one's time) and refuse an event outside the sensor, so their chunks pass through unscanned; for EVT
and DAT files the words themselves are scanned first (:mod:`~dagr_lite.camera.rawtime`), so the
events the decoder re-times are refused under ``order="refuse"`` and counted (``Recording.retimed``)
under ``"sort"``. An Event Stream file cannot go back in time; an AEDAT4 file's disorder stays
unseen. ``.h5`` and CSV chunks get one compiled pass that checks both (tests/camera/test_recording.py
pins what faery does).

Frames come from the recording's own frame track (AEDAT4), from a video's own frame folder beside an
``.h5`` of this package's layout (times from the h5 file, also when ``frames=`` names that folder
without ``frame_times=``), from a frame folder (``frames=DIR`` with ``timestamps.txt``, one time in
microseconds per image in name order) or a video file (``frames=FILE.mp4``; times from
``frame_times=FILE`` or else the video's own clock), as ``(t_us, (H, W, 3) uint8)`` in time order,
one frame in memory at a time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numba
import numpy as np

from dagr_lite.camera.rawtime import Retimed, es_dvs_overrun, evt_version, payload_start, scan_times
from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.events import EventFile
from dagr_lite.data.frames import list_frames, read_frame

FAERY_SUFFIXES = {".aedat4": "aedat", ".raw": "evt", ".dat": "dat", ".es": "es", ".csv": "csv"}
H5_SUFFIXES = (".h5", ".hdf5")
FAERY_KINDS = set(FAERY_SUFFIXES.values())
SUFFIXES = tuple(FAERY_SUFFIXES) + H5_SUFFIXES
ORDERS = ("sort", "refuse")
# The time-order defaults: conf/detect.yaml's order and order_window_us (tests/camera/test_detect.py holds
# them equal).
ORDER, ORDER_WINDOW_US = "sort", 10_000
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
TIMESTAMPS_FILE = "timestamps.txt"
H5_CHUNK = 1 << 18  # events per chunk read from an h5 file

Events = dict  # {"x", "y", "t", "p"}: 1-D numpy arrays of one length


class RecordingError(UserError):
    """A recording that cannot be read as asked; the message names the file."""


def empty_events() -> Events:
    return {"x": np.zeros(0, np.int64), "y": np.zeros(0, np.int64), "t": np.zeros(0, np.int64),
            "p": np.zeros(0, np.int64)}


def concat(chunks: list[Events]) -> Events:
    return empty_events() if not chunks else {k: np.concatenate([c[k] for c in chunks]) for k in "xytp"}


def take(events: Events, index) -> Events:
    return {k: v[index] for k, v in events.items()}


@dataclass
class OrderStats:
    """What the time-order check saw: events read and events found earlier than one read before."""
    events: int = 0
    out_of_order: int = 0
    first_at: int | None = None  # index (in the recording) of the first event out of order
    first_t: int | None = None
    first_after: int | None = None


@numba.njit(cache=True, nogil=True)
def scan_chunk(t, x, y, after, width, height):
    """One pass over a chunk: whether an event is earlier than an event before it (``after``: the
    latest time before the chunk), whether an event lies outside the ``width x height`` sensor, and
    the chunk's latest time."""
    top = after
    late = outside = False
    for i in range(t.shape[0]):
        late |= t[i] < top
        top = max(top, t[i])
        outside |= (x[i] < 0) | (x[i] >= width) | (y[i] < 0) | (y[i] >= height)
    return late, outside, top


class TimeOrder:
    """Puts chunks of events in time order within a bounded buffer, or refuses disorder, and checks
    that every event lies inside the sensor (one compiled pass per chunk does both).

    ``push`` takes a chunk as read and returns the events now certain to be in order, as a list of
    chunks: those at least ``window_us`` older than the latest time seen (sorted, stable); ``flush``
    returns the rest. Chunks already in order go out whole and uncopied once their last event is
    ``window_us`` old. An event arriving after events ``window_us`` or more later than it were
    already given out raises; ``order="refuse"`` raises at the first disorder (:meth:`Recording.events`
    then counts the rest of the recording with :meth:`_check`, so the message says how many). ``p`` comes out as 0 or 1
    (a bool array viewed as uint8; other values mapped by ``p > 0``).
    """

    def __init__(self, where: str, order: str, window_us: int, size: tuple[int, int] | None = None,
                 decoder_checked: bool = False, size_from: str = "its header declares"):
        if order not in ORDERS:
            raise RecordingError(f"order={order!r}: expected one of {ORDERS}")
        if window_us < 0:
            raise RecordingError(f"order_window_us must be >= 0, got {window_us}")
        self.where, self.order, self.window_us, self.size_from = where, order, int(window_us), size_from
        self.size = size if size is not None else (np.iinfo(np.int64).max,) * 2
        self.decoder_checked = decoder_checked  # the decoder refuses events off the sensor and never goes back in time
        self.stats = OrderStats()
        self._pending: list[Events] = []
        self._max_t = np.iinfo(np.int64).min  # latest time read
        self._given_t = -math.inf  # latest time given out

    def _check(self, chunk: Events) -> np.ndarray:
        """Indices of the chunk's events earlier than an event read before them; updates the counts,
        and refuses an event outside the sensor."""
        t, x, y = chunk["t"], chunk["x"], chunk["y"]
        if not len(t):
            return t[:0]
        if self.decoder_checked:
            self.stats.events += len(t)
            self._max_t = max(self._max_t, int(t[-1]))
            return t[:0]
        late, outside, top = scan_chunk(t, x, y, self._max_t, *self.size)
        if outside:
            i = int(np.argmax((x < 0) | (x >= self.size[0]) | (y < 0) | (y >= self.size[1])))
            raise RecordingError(f"{self.where}: event at t={int(t[i])} us lies at ({int(x[i])}, {int(y[i])}), "
                                 f"outside the {self.size[0]}x{self.size[1]} sensor {self.size_from}")
        if not late:
            self.stats.events += len(t)
            self._max_t = int(top)
            return t[:0]
        running = np.maximum.accumulate(np.concatenate([[self._max_t], t.astype(np.int64)]))
        late = np.flatnonzero(t < running[:-1])
        if self.stats.first_at is None:
            i = int(late[0])
            self.stats.first_at, self.stats.first_t = self.stats.events + i, int(t[i])
            self.stats.first_after = int(running[i])
        self.stats.out_of_order += len(late)
        self.stats.events += len(t)
        self._max_t = int(running[-1])
        return late

    def refused(self) -> RecordingError:
        s = self.stats
        return RecordingError(
            f"{self.where}: {s.out_of_order} of {s.events} events are out of time order; the first is event "
            f"{s.first_at} at t={s.first_t} us, after an event at t={s.first_after} us (order=sort sorts them "
            f"within order_window_us)")

    def push(self, chunk: Events) -> list[Events]:
        p = np.asarray(chunk["p"])
        if p.dtype == np.bool_:
            p = p.view(np.uint8)
        elif len(p) and (p.min() < 0 or p.max() > 1):
            p = (p > 0).astype(np.uint8)
        chunk = {"x": np.asarray(chunk["x"]), "y": np.asarray(chunk["y"]), "t": np.asarray(chunk["t"]), "p": p}
        t = chunk["t"]
        late = self._check(chunk)
        if self.order == "refuse":
            if len(late):
                raise self.refused()
            self._given_t = self._max_t
            return [chunk] if len(t) else []
        if len(late) and t.min() < self._given_t:  # (in order, every event is later than any given out)
            i = int(np.argmax(t < self._given_t))
            raise RecordingError(
                f"{self.where}: event {self.stats.events - len(t) + i} at t={int(t[i])} us arrives after events "
                f"up to t={int(self._given_t)} us were read: it is more than order_window_us={self.window_us} "
                "late; raise order_window_us")
        self._pending.append(chunk)
        before = self._max_t - self.window_us
        if len(late):
            return self._release(before)
        # In order: the held chunks are too, end to end; whole chunks go out uncopied.
        ready = []
        while self._pending and (not len(self._pending[0]["t"]) or self._pending[0]["t"][-1] <= before):
            ready.append(self._pending.pop(0))
        return self._given(ready)

    def flush(self) -> list[Events]:
        return self._release(math.inf)

    def _given(self, ready: list[Events]) -> list[Events]:
        ready = [r for r in ready if len(r["t"])]
        if ready:
            self._given_t = max(self._given_t, float(ready[-1]["t"][-1]))
        return ready

    def _release(self, before: float) -> list[Events]:
        """The pending events older than ``before``, in stable time order."""
        pending = concat(self._pending)
        pending = take(pending, np.argsort(pending["t"], kind="stable"))
        cut = int(np.searchsorted(pending["t"], before, side="right")) if math.isfinite(before) else len(pending["t"])
        self._pending = [take(pending, slice(cut, None))]
        return self._given([take(pending, slice(0, cut))])


@dataclass
class Recording:
    """An event recording: its sensor ``size = (width, height)``, its event chunks and its frames.

    ``events()`` and ``frames()`` each read the recording afresh; ``order`` (the
    :class:`OrderStats` of the last ``events()`` pass) says what the time-order check saw.
    """
    path: Path
    kind: str
    size: tuple[int, int]
    _chunks: Callable[[], Iterator[Events]] = field(repr=False)
    _frames: Callable[[], Iterator[tuple[int, np.ndarray]]] | None = field(repr=False, default=None)
    order_mode: str = ORDER
    order_window_us: int = ORDER_WINDOW_US
    order: OrderStats = field(default_factory=OrderStats)
    retimed: Retimed | None = None  # EVT and DAT: the events written out of time order, which the decoder re-times

    @property
    def has_frames(self) -> bool:
        return self._frames is not None

    def events(self) -> Iterator[Events]:
        """Chunks of events in time order, inside the sensor, ``p`` 0 or 1 (no chunk is empty)."""
        sorter = TimeOrder(str(self.path), self.order_mode, self.order_window_us, self.size,
                           decoder_checked=self.kind in FAERY_KINDS - {"csv"},
                           size_from={"csv": "sensor.size gives", "h5": "of the recording"}.get(self.kind,
                                                                                          "its header declares"))
        self.order = sorter.stats
        read = 0
        try:
            for raw in self._chunks():
                read += len(raw["t"])
                try:
                    ready = sorter.push(raw)
                except RecordingError:
                    if self.order_mode == "refuse" and sorter.stats.out_of_order:
                        for rest in self._chunks_after(read):
                            sorter._check(dict(rest))
                        raise sorter.refused() from None
                    raise
                yield from ready
        except RecordingError:
            raise
        except Exception as err:  # a decoder's own error: an event off the sensor, truncated or corrupt data
            if "overflow" in str(err):
                raise RecordingError(f"{self.path}: after {read} events, an event lies outside the "
                                     f"{self.size[0]}x{self.size[1]} sensor its header declares ({err})") from err
            raise RecordingError(f"{self.path}: cannot read it as {self.kind} after {read} events ({err}); the file "
                                 "may be truncated or corrupt") from err
        yield from sorter.flush()

    def _chunks_after(self, read: int) -> Iterator[Events]:
        """The chunks after the first ``read`` events (to count disorder in the rest of the file)."""
        seen = 0
        for raw in self._chunks():
            seen += len(raw["t"])
            if seen > read:
                yield raw

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(t_us, (H, W, 3) uint8)`` in time order; nothing if the recording has no frames."""
        if self._frames is None:
            return iter(())
        return self._frames()


# How each kind of file begins (what its suffix claims is checked against this).
MAGIC = {"aedat": (b"#!AER-DAT4",), "es": (b"Event Stream",), "evt": (b"%",), "dat": (b"%",), "h5": (b"\x89HDF",)}
NAMES = {"aedat": "an AEDAT4 file (.aedat4)", "es": "an Event Stream file (.es)", "h5": "an HDF5 file (.h5)",
         "evt": "a Prophesee file (.raw or .dat)", "dat": "a Prophesee file (.raw or .dat)"}


def sniff(path: Path) -> str | None:
    """The kind of file ``path`` begins as (None: none of the binary kinds)."""
    with open(path, "rb") as f:
        head = f.read(16)
    return next((kind for kind, starts in MAGIC.items() if head.startswith(starts)), None)


def check_kind(path: Path, kind: str) -> None:
    """Refuse a file whose first bytes are not what its suffix claims, naming what it is; a Prophesee
    file without its ``%`` header (which says the format and the sensor) is refused too."""
    found = sniff(path)
    if kind == "csv" or found == kind or {found, kind} == {"evt", "dat"}:
        return
    if found is not None:
        raise RecordingError(f"{path}: named {path.suffix}, but it is {NAMES[found]}; give it the suffix of its format")
    if kind in ("evt", "dat"):
        raise RecordingError(f"{path}: a Prophesee {path.suffix} file begins with its % header (the format, EVT2 "
                             "or EVT3, and the sensor size); this one has none, so it cannot be read as one")
    raise RecordingError(f"{path}: named {path.suffix}, but it does not begin as {NAMES[kind]}")


def truncation_problem(path: Path, kind: str) -> str | None:
    """Why the file must have been cut short, or None: a CSV whose last line has no end, an EVT or
    DAT file whose payload stops inside a word, a DVS Event Stream file that stops inside an event
    (a cut at a word or event boundary cannot be told from a shorter recording)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
        if kind == "csv":
            f.seek(max(0, size - 1))
            return None if size == 0 or f.read(1) == b"\n" else "its last line is incomplete"
    if kind == "es":
        missing = es_dvs_overrun(path)
        return f"its last event lacks {missing} of its 5 bytes" if missing else None
    if kind not in ("evt", "dat"):
        return None
    word = 8 if kind == "dat" else (4 if evt_version(head) == 2 else 2)
    payload = size - payload_start(head, kind == "dat")
    if payload % word:
        return f"its {payload}-byte payload is not a whole number of {word}-byte words"
    return None


def _faery_chunks(path: Path, kind: str, size: tuple[int, int] | None) -> tuple[tuple[int, int], Callable]:
    import faery

    kwargs = {"file_type": kind}  # by this package's reading of the suffix (faery's own is case-sensitive: .ES)
    if size is not None:
        kwargs["dimensions_fallback"] = tuple(size)
    try:
        decoder = faery.events_stream_from_file(path, **kwargs)
        dimensions = tuple(int(v) for v in decoder.dimensions())
    except Exception as err:
        raise RecordingError(f"{path}: cannot open it as {kind} ({err}); the file may be truncated, corrupt or "
                             "of another format") from err
    problem = truncation_problem(path, kind)
    if problem is not None:
        raise RecordingError(f"{path}: {problem}; the file is truncated")
    if size is not None and kind in ("aedat", "es") and tuple(size) != dimensions:
        raise RecordingError(f"{path}: its header declares a {dimensions[0]}x{dimensions[1]} sensor, but "
                             f"sensor.size={list(size)} was given")

    def chunks() -> Iterator[Events]:
        for packet in faery.events_stream_from_file(path, **kwargs):
            if len(packet):
                yield {"x": packet["x"], "y": packet["y"], "t": packet["t"].view(np.int64), "p": packet["on"]}

    return dimensions, chunks


CSV_CHUNK = 1 << 16  # lines per chunk read from a CSV file


def _csv_chunks(path: Path, size: tuple[int, int]) -> tuple[tuple[int, int], Callable]:
    """A ``t,x,y,on`` CSV (faery's layout: a header line, ``x@W`` and ``y@H`` may name the sensor),
    read here rather than by faery so that times that run backwards are seen as they are: faery's
    decoder clamps them to the latest time, which neither sorting nor ``order=refuse`` could then
    see."""
    problem = truncation_problem(path, "csv")
    if problem is not None:
        raise RecordingError(f"{path}: {problem}; the file is truncated")
    with open(path) as f:
        header = f.readline()
    names = [name.split("@")[0].strip().lower() for name in header.split(",")]
    if names != ["t", "x", "y", "on"]:
        raise RecordingError(f"{path}: a CSV recording starts with the header t,x,y,on (faery's layout), got "
                             f"{header.strip()!r}")

    def chunks() -> Iterator[Events]:
        import itertools

        with open(path) as f:
            f.readline()
            line = 2
            while True:
                lines = list(itertools.islice(f, CSV_CHUNK))
                if not lines:
                    return
                try:
                    block = np.loadtxt(lines, delimiter=",", dtype=np.int64, ndmin=2)
                except ValueError as err:
                    raise RecordingError(f"{path}: lines {line} to {line + len(lines) - 1} are not t,x,y,on "
                                         f"integers ({err})") from err
                if block.shape[1] != 4:
                    raise RecordingError(f"{path}: line {line} has {block.shape[1]} values, expected t,x,y,on")
                line += len(lines)
                yield {"x": block[:, 1], "y": block[:, 2], "t": block[:, 0], "p": (block[:, 3] > 0).astype(np.uint8)}

    return size, chunks


def _aedat_frames(path: Path, size: tuple[int, int]) -> Callable | None:
    from faery.extension import aedat

    with aedat.Decoder(path) as decoder:
        tracks = [track for track in decoder.tracks() if track.data_type == "frame"]
    if not tracks:
        return None
    track = tracks[0]
    if track.dimensions is not None and tuple(track.dimensions) != tuple(size):
        raise RecordingError(f"{path}: its frame track {track.id} is {track.dimensions[0]}x{track.dimensions[1]}, "
                             f"its events {size[0]}x{size[1]}; frames and events must share the sensor")

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        with aedat.Decoder(path) as decoder:
            for packet_track, packet in decoder:
                if packet_track.id == track.id:
                    yield int(packet.t), _rgb(packet.pixels, f"{path} frame at {packet.t} us", size)

    return frames


def _rgb(pixels: np.ndarray, what: str, size: tuple[int, int]) -> np.ndarray:
    pixels = np.asarray(pixels)
    if pixels.dtype != np.uint8:  # 16-bit grey frames: keep the top byte
        pixels = (pixels >> 8).astype(np.uint8) if pixels.dtype == np.uint16 else pixels.astype(np.uint8)
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=2)
    pixels = pixels[..., :3]
    if pixels.shape[:2] != (size[1], size[0]):
        raise RecordingError(f"{what} is {pixels.shape[1]}x{pixels.shape[0]}, the events' sensor "
                             f"{size[0]}x{size[1]}; frames and events must share the sensor")
    return np.ascontiguousarray(pixels)


def read_frame_times(path: Path, count: int | None = None) -> np.ndarray:
    """Frame times in microseconds from a text file, one per line (``#`` comments allowed)."""
    if not path.is_file():
        raise RecordingError(f"{path}: the frame timestamp file is missing")
    try:
        times = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=1)
    except ValueError as err:
        raise RecordingError(f"{path}: expected one time in microseconds per line ({err})") from err
    if count is not None and len(times) != count:
        raise RecordingError(f"{path}: {len(times)} times for {count} frames")
    if np.any(np.diff(times) < 0):
        i = int(np.argmax(np.diff(times) < 0))
        raise RecordingError(f"{path}: frame times must not decrease; line {i + 2} ({times[i + 1]:g}) is earlier "
                             f"than line {i + 1} ({times[i]:g})")
    check_frame_interval(path, times)
    return times.astype(np.int64)


# Frame intervals a camera gives, in microseconds: 10 kHz to one frame in 10 s.
FRAME_INTERVAL_US = (100.0, 10_000_000.0)


def check_frame_interval(path: Path, times: np.ndarray) -> None:
    """Refuse frame times whose median interval no camera gives in microseconds (times in seconds
    or milliseconds, or in nanoseconds), naming the fix."""
    if len(times) < 2:
        return
    interval = float(np.median(np.diff(times)))
    low, high = FRAME_INTERVAL_US
    if interval < low:
        raise RecordingError(f"{path}: the frames are {interval:g} apart in the median; frame times are microseconds "
                             f"(30 fps: 33333 apart). Times in seconds need x 1e6, in milliseconds x 1e3")
    if interval > high:
        raise RecordingError(f"{path}: the frames are {interval:g} us ({interval / 1e6:g} s) apart in the median; "
                             "frame times are microseconds. Times in nanoseconds need / 1e3")


def _folder_frames(folder: Path, times_file: Path | None, size: tuple[int, int]) -> Callable:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    numbered = list_frames(folder)
    if numbered and len(numbered) == len(files):  # frame_<k>.jpg: order by k, not by name
        files = [folder / numbered[k] for k in sorted(numbered)]
    if not files:
        raise RecordingError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in the frame folder")
    if times_file is None and not (folder / TIMESTAMPS_FILE).is_file():
        raise RecordingError(f"{folder / TIMESTAMPS_FILE}: the frame timestamp file is missing; a frame folder needs "
                             f"its frames' times in microseconds, one per line: there, or named by frame_times=FILE")
    times = read_frame_times(times_file or folder / TIMESTAMPS_FILE, len(files))

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        for t_us, file in zip(times, files):
            yield int(t_us), _rgb(read_frame(file), str(file), size)

    return frames


def _video_frames(video: Path, times_file: Path | None, size: tuple[int, int]) -> Callable:
    import av

    times = read_frame_times(times_file) if times_file is not None else None

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        try:
            container = av.open(str(video))
        except Exception as err:
            raise RecordingError(f"{video}: cannot open it as a video ({err})") from err
        with container:
            stream = container.streams.video[0]
            for k, frame in enumerate(container.decode(stream)):
                if times is not None and k >= len(times):
                    raise RecordingError(f"{times_file}: {len(times)} times, but {video} has more frames")
                t_us = int(times[k]) if times is not None else int(round(float(frame.time) * 1e6))
                yield t_us, _rgb(frame.to_ndarray(format="rgb24"), f"{video} frame {k}", size)

    return frames


def h5_frames_dir(path: Path) -> Path:
    """The frame folder of a video of this package's layout, ``<root>/<split>/frames/<video>`` beside
    ``<root>/<split>/events/<video>.h5`` (whose frame times the h5 file holds); found from the file's
    resolved path, so a relative name or a link to the file finds it too."""
    path = path.resolve()
    return path.parent.parent / fmt.FRAMES_DIR / path.stem


def _h5_recording(path: Path, size: tuple[int, int] | None) -> tuple[tuple[int, int], Callable, Callable | None]:
    """A video of this package's layout: ``<root>/<split>/events/<video>.h5`` and its frame folder."""
    frames_dir = h5_frames_dir(path)
    count = len(list_frames(frames_dir)) if frames_dir.is_dir() else None
    file = EventFile(path, num_frames=count)
    if count:
        height, width = read_frame(frames_dir / list_frames(frames_dir)[0]).shape[:2]
        size = size or (width, height)
    elif size is None:
        raise RecordingError(f"{path}: no frame folder at {frames_dir} to take the sensor size from; give "
                             "sensor.size=[width,height]")

    def chunks() -> Iterator[Events]:
        for start in range(0, file.num_events, H5_CHUNK):
            yield file.read(start, start + H5_CHUNK)
        file.close()

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        for k in range(count):
            yield int(file.frame_time_us(k)), _rgb(read_frame(frames_dir / fmt.frame_name(k)),
                                                   f"{frames_dir} frame {k}", size)

    return tuple(size), chunks, (frames if count else None)


def open_recording(path: Path | str, *, size: tuple[int, int] | None = None, frames: Path | str | None = None,
                   frame_times: Path | str | None = None, order: str = ORDER,
                   order_window_us: int = ORDER_WINDOW_US) -> Recording:
    """Open an event recording (see the module's table); ``size = (width, height)`` is needed where
    the file does not say it (CSV, and EVT/DAT files without a size in their header); ``frames`` a
    frame folder or video file whose frames go with the events."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise RecordingError(f"{path}: unknown recording format {suffix or '(no suffix)'!r}; expected one of "
                             f"{', '.join(SUFFIXES)}")
    if path.is_dir():
        raise RecordingError(f"{path}: a folder, not a recording; give the recording's file")
    if path.exists() and not path.is_file():
        raise RecordingError(f"{path}: not a regular file (a pipe or a device); give a recording file")
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    if size is not None:
        size = (int(size[0]), int(size[1]))
        if min(size) <= 0:
            raise RecordingError(f"sensor.size={list(size)}: width and height must be positive")
    if suffix == ".csv" and size is None:
        raise RecordingError(f"{path}: a CSV recording does not say its sensor size; give sensor.size=[width,height]")
    check_kind(path, "h5" if suffix in H5_SUFFIXES else FAERY_SUFFIXES[suffix])
    retimed = None
    if suffix in H5_SUFFIXES:
        kind = "h5"
        size, chunks, frame_source = _h5_recording(path, size)
    elif suffix == ".csv":
        kind, frame_source = "csv", None
        size, chunks = _csv_chunks(path, size)
    else:
        kind = FAERY_SUFFIXES[suffix]
        size, chunks = _faery_chunks(path, kind, size)
        retimed = _retimed(path, kind, order)
        frame_source = _aedat_frames(path, size) if kind == "aedat" else None
    if frames is not None:
        frames = Path(frames)
        times = Path(frame_times) if frame_times is not None else None
        own = kind == "h5" and frame_source is not None and times is None and frames.is_dir() and \
            frames.resolve() == h5_frames_dir(path)
        if own:
            pass  # the video's own frame folder: its frames' times are the h5 file's (a timestamps.txt there is not read)
        elif frames.is_dir():
            frame_source = _folder_frames(frames, times, size)
        elif frames.is_file():
            frame_source = _video_frames(frames, times, size)
        else:
            raise RecordingError(f"frames={frames}: no such folder or video file")
    return Recording(path, kind, size, chunks, frame_source, order, int(order_window_us),
                     retimed=retimed)


def _retimed(path: Path, kind: str, order: str) -> Retimed | None:
    """The events of an EVT or DAT file written out of time order (which faery's decoder re-times to
    the time of the event before them); refused under ``order="refuse"``."""
    if kind not in ("evt", "dat"):
        return None
    found = scan_times(path, kind)
    if found.late and order == "refuse":
        raise RecordingError(
            f"{path}: {found.late} of {found.events} events are written out of time order; the first is event "
            f"{found.first_at} at t={found.first_t} us, after an event at t={found.first_after} us (order=sort "
            "reads them at the time of the event before them, as the decoder does, and counts them)")
    return found
