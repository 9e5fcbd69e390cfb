"""Live event streams over UDP, in faery's packet formats.

``t64_x16_y16_on8`` (faery's default): 13-byte events, ``<u8`` t, ``<u2`` x, ``<u2`` y, ``u1`` on.
``t32_x16_y15_on1``: 8-byte events, ``<u4`` t (wrapping), ``<u2`` x, ``<u2`` y << 1 | on.

:class:`UdpSource` receives on a thread into a queue, so no datagram waits on the detector; the
detector drains the queue when it is ready. The queue is bounded (``max_backlog_bytes``): when the
stream outpaces the detector, the oldest datagrams are dropped, counted and reported as it happens
(``backlog_dropped_events``), so memory stays bounded whoever sends. The summary says how many
events waited at most (``backlog_max``) and for how long (``wait_ms_max``).

Every datagram is checked before its events reach the detector: a length that is not whole
events, a coordinate off the sensor, times that run backwards inside it, or a first time more
than ``MAX_AHEAD_US`` ahead of the stream (junk, or another format) reject the whole datagram,
counted by reason (``packets_rejected``); a run of ``AHEAD_TO_ACCEPT`` datagrams that agree on a
clock far ahead is taken as the sender's clock jumping (``clock_jumps``). The datagrams of one read
are put in time order, so datagrams the network swapped are read the same whatever the timing; a
datagram older than what the detector has read is counted by the detector as late. The operating
system can still drop datagrams when its receive buffer overflows: the source asks for a large buffer.
"""
from __future__ import annotations

import collections
import dataclasses
import socket
import sys
import threading
import time
from dataclasses import dataclass
from typing import Iterator
from urllib.parse import urlparse

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.camera.recording import concat

FORMATS = {
    "t64_x16_y16_on8": np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "u1")]),
    "t32_x16_y15_on1": np.dtype([("t", "<u4"), ("x", "<u2"), ("y_on", "<u2")]),
}
RECEIVE_BUFFER = 1 << 24  # bytes asked of the operating system
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux: datagrams dropped so far, with each datagram
EVENTS_PER_PACKET = 100
MAX_AHEAD_US = 10_000_000  # a datagram starting this far ahead of the stream is refused ...
AHEAD_TO_ACCEPT = 20       # ... unless this many in a row agree on the new clock (within MAX_AHEAD_US)


def parse_address(url: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` to ``(host, port)``; ``udp://:PORT`` listens on loopback only (another
    host can reach the port only where the user names an address that it can reach, e.g. 0.0.0.0)."""
    parsed = urlparse(url)
    try:
        port = parsed.port
    except ValueError:
        port = None
    if parsed.scheme != "udp" or port is None:
        raise UserError(f"input={url!r}: a live stream is udp://HOST:PORT (udp://:PORT: this machine only)")
    return parsed.hostname or "127.0.0.1", port


def decode(payload: bytes, fmt: str, t_high: int = 0) -> dict:
    """One datagram's events as ``x, y, t, p`` arrays (``t_high`` is added to a wrapping 32-bit clock)."""
    dtype = FORMATS[fmt]
    raw = np.frombuffer(payload[: len(payload) // dtype.itemsize * dtype.itemsize], dtype=dtype)
    if fmt == "t64_x16_y16_on8":
        return {"x": raw["x"].astype(np.int64), "y": raw["y"].astype(np.int64), "t": raw["t"].astype(np.int64),
                "p": (raw["on"] > 0).astype(np.int64)}
    return {"x": raw["x"].astype(np.int64), "y": (raw["y_on"] >> 1).astype(np.int64),
            "t": raw["t"].astype(np.int64) + t_high, "p": (raw["y_on"] & 1).astype(np.int64)}


def encode(events: dict, fmt: str) -> bytes:
    packed = np.zeros(len(events["t"]), FORMATS[fmt])
    packed["t"], packed["x"] = events["t"], events["x"]
    if fmt == "t64_x16_y16_on8":
        packed["y"], packed["on"] = events["y"], events["p"]
    else:
        packed["y_on"] = (np.asarray(events["y"]) << 1) | (np.asarray(events["p"]) & 1)
    return packed.tobytes()


def check_datagram(events: dict, payload_size: int, itemsize: int, size: tuple[int, int]) -> str | None:
    """Why a datagram's events may not reach the detector (None: they may)."""
    if payload_size == 0 or payload_size % itemsize:
        return "length"
    if np.any(events["x"] >= size[0]) or np.any(events["y"] >= size[1]):
        return "coordinates"
    if np.any(np.diff(events["t"]) < 0):
        return "time order"
    return None


@dataclass
class UdpStats:
    packets: int = 0
    events: int = 0
    backlog_max: int = 0  # most events waiting in the queue when the detector came to read it
    wait_ms_max: float = 0.0  # longest a packet waited in the queue for the detector
    packets_out_of_order: int = 0  # packets whose first time is earlier than the previous packet's last
    packets_rejected: dict = dataclasses.field(default_factory=dict)  # reason -> datagrams refused
    backlog_dropped_packets: int = 0  # the oldest datagrams dropped to keep the queue bounded
    backlog_dropped_events: int = 0
    clock_jumps: int = 0  # runs of datagrams that agreed on a clock far ahead, then taken
    backlog_bytes_max: int = 0  # the most bytes queued at once (at most max_backlog_bytes + one datagram)
    os_dropped_packets: int | None = None  # datagrams the operating system dropped, its receive buffer full
    # (Linux's SO_RXQ_OVFL; None where the system does not report it)


class UdpSource:
    """Events from ``udp://HOST:PORT`` (see the module), until ``idle_s`` seconds pass with no packet
    after the first, or ``seconds`` of wall-clock time pass (None: no limit). ``events()`` yields, chunk
    by chunk, what arrived since the chunk before, in arrival order; ``ready`` is set once the socket
    listens."""

    def __init__(self, url: str, size: tuple[int, int], *, fmt: str, idle_s: float, wait_first_s: float,
                 seconds: float | None, max_backlog_bytes: int):
        if fmt not in FORMATS:
            raise UserError(f"udp.format={fmt!r}: expected one of {sorted(FORMATS)}")
        if max_backlog_bytes <= 0:
            raise UserError(f"udp.max_backlog_mb must be positive, got {max_backlog_bytes / 2 ** 20:g}")
        self.max_backlog_bytes = int(max_backlog_bytes)
        self._queued_bytes = 0
        self._lock = threading.Lock()
        self._clock = {"last_t": -1, "t_high": 0, "ahead": []}  # the stream's time, for checking datagrams
        self.address = parse_address(url)
        self.url, self.size, self.fmt = url, (int(size[0]), int(size[1])), fmt
        self.idle_s, self.seconds, self.wait_first_s = float(idle_s), seconds, float(wait_first_s)
        self.stats = UdpStats()
        self.order = None
        self.has_frames = False
        self.path = url
        self._queue: collections.deque[tuple[float, bytes]] = collections.deque()  # (arrival, payload)
        self._running = False
        self.ready = threading.Event()

    def frames(self):
        return iter(())

    def _receive(self, sock: socket.socket) -> None:
        buffer = bytearray(65536)
        counting = self.stats.os_dropped_packets is not None
        ancillary = socket.CMSG_SPACE(4) if counting else 0
        while self._running:
            try:
                n, cmsgs, _, _ = sock.recvmsg_into([buffer], ancillary)
            except socket.timeout:
                continue
            for level, kind, data in cmsgs:  # the system's count of datagrams dropped so far
                if counting and level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(data) >= 4:
                    self._os_dropped(int.from_bytes(data[:4], sys.byteorder))
            if n:
                self._enqueue(time.monotonic(), bytes(buffer[:n]))

    def _os_dropped(self, total: int) -> None:
        if total > self.stats.os_dropped_packets:
            before, self.stats.os_dropped_packets = self.stats.os_dropped_packets, total
            if before // 1000 != total // 1000 or not before:
                print(f"udp: the operating system dropped {total} datagrams so far (its receive buffer was full: "
                      "the detector's reader fell behind)", file=sys.stderr, flush=True)

    def _enqueue(self, arrival: float, payload: bytes) -> None:
        """Queue a datagram; over the bound, drop the oldest, counted and said as it happens."""
        with self._lock:
            self._queue.append((arrival, payload))
            self._queued_bytes += len(payload)
            self.stats.backlog_bytes_max = max(self.stats.backlog_bytes_max, self._queued_bytes)
            dropped = 0
            while self._queued_bytes > self.max_backlog_bytes and len(self._queue) > 1:
                _, old = self._queue.popleft()
                self._queued_bytes -= len(old)
                dropped += len(old) // FORMATS[self.fmt].itemsize
                self.stats.backlog_dropped_packets += 1
            if dropped:
                before = self.stats.backlog_dropped_events
                self.stats.backlog_dropped_events += dropped
                if before // 100_000 != self.stats.backlog_dropped_events // 100_000 or not before:
                    print(f"udp: the detector lags the stream; {self.stats.backlog_dropped_events} events dropped "
                          f"from the oldest so far (udp.max_backlog_mb)", file=sys.stderr, flush=True)

    def _take_queue(self) -> list[tuple[float, bytes]]:
        with self._lock:
            arrived = list(self._queue)
            self._queue.clear()
            self._queued_bytes = 0
        return arrived

    def read(self, payloads: list[bytes]) -> dict | None:
        """The events of the datagrams of one read, those refused left out, in time order (datagrams
        the network swapped come out the same whatever the timing); None when none is left."""
        self.stats.packets += len(payloads)
        chunks = [events for payload in payloads for events in [self._accept(payload)] if events is not None]
        count = sum(len(c["t"]) for c in chunks)
        self.stats.events += count
        self.stats.backlog_max = max(self.stats.backlog_max, count)
        if not chunks:
            return None
        events = concat(chunks)
        order = np.argsort(events["t"], kind="stable")
        return {key: value[order] for key, value in events.items()}

    def _accept(self, payload: bytes) -> dict | None:
        """One datagram's events, or None when it is refused (counted in ``stats.packets_rejected``)."""
        clock, itemsize = self._clock, FORMATS[self.fmt].itemsize
        events = decode(payload, self.fmt, clock["t_high"])
        reason = check_datagram(events, len(payload), itemsize, self.size)
        if reason is not None:
            _refuse(self.stats, reason)
            return None
        if self.fmt == "t32_x16_y15_on1" and events["t"][0] < clock["last_t"] - (1 << 31):
            clock["t_high"] += 1 << 32  # the 32-bit clock wrapped
            events["t"] += 1 << 32
        if clock["last_t"] >= 0 and events["t"][0] > clock["last_t"] + MAX_AHEAD_US:
            ahead = clock["ahead"]
            if ahead and abs(int(events["t"][0]) - ahead[-1]) > MAX_AHEAD_US:
                ahead.clear()  # not the same new clock
            ahead.append(int(events["t"][-1]))
            if len(ahead) < AHEAD_TO_ACCEPT:
                _refuse(self.stats, "time ahead of the stream")
                return None
            self.stats.clock_jumps += 1
        clock["ahead"] = []
        if events["t"][0] < clock["last_t"]:
            self.stats.packets_out_of_order += 1
        clock["last_t"] = max(clock["last_t"], int(events["t"][-1]))
        return events

    def events(self) -> Iterator[dict]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        if sys.platform.startswith("linux"):
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self.stats.os_dropped_packets = 0
            except OSError:
                pass
        try:
            sock.bind(self.address)
        except OSError as err:
            sock.close()
            raise UserError(f"input={self.url}: cannot listen there ({err})") from err
        sock.settimeout(0.05)
        self._running = True
        thread = threading.Thread(target=self._receive, args=(sock,), daemon=True)
        thread.start()
        self.ready.set()
        started, last_packet = time.monotonic(), None
        try:
            while True:
                now = time.monotonic()
                if self.seconds is not None and now - started > self.seconds:
                    return
                if last_packet is None and now - started > self.wait_first_s:
                    raise UserError(f"input={self.url}: no packet in {self.wait_first_s:g} s")
                if last_packet is not None and now - last_packet > self.idle_s and not self._queue:
                    return
                if not self._queue:
                    time.sleep(0.002)
                    continue
                arrived = self._take_queue()
                last_packet = time.monotonic()
                self.stats.wait_ms_max = max(self.stats.wait_ms_max, 1e3 * (last_packet - arrived[0][0]))
                events = self.read([payload for _, payload in arrived])
                if events is not None:
                    yield events
        finally:
            self._running = False
            thread.join()
            sock.close()


def _refuse(stats: UdpStats, reason: str) -> None:
    stats.packets_rejected[reason] = stats.packets_rejected.get(reason, 0) + 1


def send(chunks, url: str, *, fmt: str, speed: float = 1.0,
         events_per_packet: int = EVENTS_PER_PACKET) -> int:
    """Send time-ordered event chunks to ``udp://HOST:PORT`` at the recording's own pace (``speed``
    times real time; 0: as fast as possible). Returns the number of events sent."""
    address = parse_address(url)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent, t_first, started = 0, None, time.monotonic()
    try:
        for events in chunks:
            for i in range(0, len(events["t"]), events_per_packet):
                part = {k: v[i:i + events_per_packet] for k, v in events.items()}
                if t_first is None:
                    t_first = int(part["t"][0])
                if speed > 0:
                    due = (int(part["t"][0]) - t_first) / 1e6 / speed - (time.monotonic() - started)
                    if due > 0:
                        time.sleep(due)
                sock.sendto(encode(part, fmt), address)
                sent += len(part["t"])
    finally:
        sock.close()
    return sent
