"""Live event streams over UDP, in faery's packet formats.

``t64_x16_y16_on8`` (faery's default): 13-byte events, ``<u8`` t, ``<u2`` x, ``<u2`` y, ``u1`` on.
``t32_x16_y15_on1``: 8-byte events, ``<u4`` t (wrapping), ``<u2`` x, ``<u2`` y << 1 | on.

:class:`UdpSource` receives on a thread into a queue, so no datagram waits on the detector; the
detector drains the queue when it is ready. Events that arrived while it was busy wait there, never
dropped: the summary says how many waited at most (``backlog_max``) and for how long (``wait_ms_max``). The
operating system can still drop datagrams when its receive buffer overflows; the source asks for
a large buffer and counts packets whose time runs backwards (``packets_out_of_order``).
"""
from __future__ import annotations

import collections
import socket
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
EVENTS_PER_PACKET = 100


def parse_address(url: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` to ``(host, port)``."""
    parsed = urlparse(url)
    if parsed.scheme != "udp" or not parsed.hostname or parsed.port is None:
        raise UserError(f"input={url!r}: a live stream is udp://HOST:PORT")
    return parsed.hostname, parsed.port


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


@dataclass
class UdpStats:
    packets: int = 0
    events: int = 0
    backlog_max: int = 0  # most events waiting in the queue when the detector came to read it
    wait_ms_max: float = 0.0  # longest a packet waited in the queue for the detector
    packets_out_of_order: int = 0  # packets whose first time is earlier than the previous packet's last


class UdpSource:
    """Events from ``udp://HOST:PORT`` (see the module), until ``idle_s`` seconds pass with no packet
    after the first, or ``seconds`` of wall-clock time pass (None: no limit). ``events()`` yields, chunk
    by chunk, what arrived since the chunk before, in arrival order; ``ready`` is set once the socket
    listens."""

    def __init__(self, url: str, size: tuple[int, int], *, fmt: str, idle_s: float, wait_first_s: float,
                 seconds: float | None):
        if fmt not in FORMATS:
            raise UserError(f"udp.format={fmt!r}: expected one of {sorted(FORMATS)}")
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
        while self._running:
            try:
                n = sock.recv_into(buffer)
            except socket.timeout:
                continue
            if n:
                self._queue.append((time.monotonic(), bytes(buffer[:n])))

    def events(self) -> Iterator[dict]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
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
        started, last_packet, last_t, t_high = time.monotonic(), None, -1, 0
        try:
            while True:
                now = time.monotonic()
                if self.seconds is not None and now - started > self.seconds:
                    return
                if last_packet is None and now - started > self.wait_first_s:
                    raise UserError(f"input={self.url}: no packet in {self.wait_first_s:g} s")
                if last_packet is not None and now - last_packet > self.idle_s and not self._queue:
                    return
                waiting = len(self._queue)
                if not waiting:
                    time.sleep(0.002)
                    continue
                arrived = [self._queue.popleft() for _ in range(waiting)]
                last_packet = time.monotonic()
                self.stats.wait_ms_max = max(self.stats.wait_ms_max, 1e3 * (last_packet - arrived[0][0]))
                payloads = [payload for _, payload in arrived]
                chunks = []
                for payload in payloads:
                    events = decode(payload, self.fmt, t_high)
                    if self.fmt == "t32_x16_y15_on1" and len(events["t"]) and events["t"][0] < last_t - (1 << 31):
                        t_high += 1 << 32  # the 32-bit clock wrapped
                        events["t"] += 1 << 32
                    if len(events["t"]):
                        if events["t"][0] < last_t:
                            self.stats.packets_out_of_order += 1
                        last_t = int(events["t"][-1])
                        chunks.append(events)
                self.stats.packets += len(payloads)
                count = sum(len(c["t"]) for c in chunks)
                self.stats.events += count
                self.stats.backlog_max = max(self.stats.backlog_max, count)
                if chunks:
                    yield concat(chunks)
        finally:
            self._running = False
            thread.join()
            sock.close()


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
