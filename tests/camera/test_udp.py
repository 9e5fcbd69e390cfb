"""A live stream is safe on a network: junk datagrams are refused and counted, swapped datagrams
are read in order, and a flood keeps the queue bounded with the drops counted."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from dagr_lite.camera.detect import run_detect
from dagr_lite.camera.sensor import Sensor
from dagr_lite.camera.udp import UdpSource, encode, send
from dagr_lite.stream import StreamingDetector
from tests.camera.test_detect import free_port, lines
from tests.settings import UDP, video_settings

SIZE = (320, 180)


def packets(count: int, per_packet: int = 50, start_us: int = 0, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    t = start_us + np.sort(rng.integers(0, 1_000 * count, count * per_packet))
    events = {"x": rng.integers(0, SIZE[0], len(t)), "y": rng.integers(0, SIZE[1], len(t)), "t": t,
              "p": rng.integers(0, 2, len(t))}
    return [{key: value[i:i + per_packet] for key, value in events.items()} for i in range(0, len(t), per_packet)]


def source(**changes) -> UdpSource:
    return UdpSource(f"udp://127.0.0.1:{free_port()}", SIZE, **{**UDP, "idle_s": 1.0, "wait_first_s": 30.0, **changes},
                     seconds=None)


def test_junk_datagrams_are_refused_by_reason_and_the_good_ones_read():
    good = packets(6)
    junk_bytes = np.random.default_rng(1).integers(0, 256, 130, dtype=np.uint8).tobytes()  # 10 events of noise
    far = {key: value.copy() for key, value in good[0].items()}
    far["t"] = far["t"] + 4_400_000_000_000_000_000  # coordinates on the sensor, a time far ahead
    backwards = {key: value[::-1].copy() for key, value in good[1].items()}
    udp = source()
    payloads = [encode(good[0], UDP["fmt"]), junk_bytes, encode(good[1], UDP["fmt"]), b"\x00" * 12,
                encode(far, UDP["fmt"]), encode(backwards, UDP["fmt"]), *(encode(p, UDP["fmt"]) for p in good[2:])]
    events = udp.read(payloads)
    expected = np.concatenate([p["t"] for p in good])
    np.testing.assert_array_equal(events["t"], expected)
    assert udp.stats.packets_rejected == {"coordinates": 1, "length": 1, "time ahead of the stream": 1,
                                          "time order": 1}
    assert udp.stats.events == len(expected) and udp.stats.packets == len(payloads)


def test_datagrams_swapped_within_one_read_come_out_in_time_order():
    first, second = packets(2)
    udp = source()
    events = udp.read([encode(second, UDP["fmt"]), encode(first, UDP["fmt"])])
    np.testing.assert_array_equal(events["t"], np.concatenate([first["t"], second["t"]]))
    assert udp.stats.packets_out_of_order == 1 and not udp.stats.packets_rejected


def test_a_sender_whose_clock_jumps_is_followed_once_its_datagrams_agree():
    before, after = packets(3), packets(25, start_us=3_600_000_000, seed=2)
    udp = source()
    read = [udp.read([encode(p, UDP["fmt"])]) for p in before + after]
    assert udp.stats.packets_rejected == {"time ahead of the stream": 19} and udp.stats.clock_jumps == 1
    assert [r is None for r in read] == [False] * 3 + [True] * 19 + [False] * 6


def test_a_junk_datagram_among_good_ones_leaves_the_session_answering(trained_checkpoints, tmp_path):
    udp = source()
    good = packets(60, per_packet=50)
    junk = np.random.default_rng(1).integers(0, 256, 130, dtype=np.uint8).tobytes()

    def sender():
        udp.ready.wait(30)
        time.sleep(0.2)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for i, part in enumerate(good):
                sock.sendto(encode(part, UDP["fmt"]), udp.address)
                if i == 30:
                    sock.sendto(junk, udp.address)
                time.sleep(0.002)

    thread = threading.Thread(target=sender)
    thread.start()
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["events_only"])
    summary = run_detect(stream, udp, Sensor(SIZE), tmp_path / "live", rate_hz=100, live=True,
                         video=video_settings(enabled=False))
    thread.join()
    assert summary["udp"]["packets_rejected"] == {"coordinates": 1}
    assert summary["udp"]["events"] == summary["events_in"] == sum(len(p["t"]) for p in good)
    answers = lines(tmp_path / "live")
    assert answers and answers[-1]["t_us"] >= good[-1]["t"][0]  # answered after the junk, up to the end


def test_a_flood_keeps_the_queue_bounded_and_counts_what_it_drops():
    bound = 13 * 2_000  # 2,000 events of t64_x16_y16_on8
    udp = source(max_backlog_bytes=bound)
    flood = packets(400, per_packet=100)
    chunks = udp.events()
    sent = []

    def sender():
        udp.ready.wait(30)
        time.sleep(0.1)
        sent.append(send([{key: np.concatenate([p[key] for p in flood]) for key in flood[0]}], f"udp://127.0.0.1:"
                         f"{udp.address[1]}", fmt=UDP["fmt"], speed=0, events_per_packet=100))

    thread = threading.Thread(target=sender)
    thread.start()
    received = 0
    for chunk in chunks:  # a detector slower than the stream
        received += len(chunk["t"])
        time.sleep(0.05)
    thread.join()
    stats = udp.stats
    assert stats.backlog_bytes_max <= bound + 13 * 100  # the bound, and the datagram that arrived over it
    assert stats.backlog_dropped_events > 0 and stats.backlog_dropped_packets > 0
    assert received == stats.events
    # every event sent is read or counted as dropped (loopback: the operating system drops none here)
    assert received + stats.backlog_dropped_events == sent[0] == 40_000


def test_datagrams_the_operating_system_drops_are_counted(monkeypatch):
    """A receive buffer of a few kB and a reader slowed to 2 ms a datagram: the system drops some,
    reports them (SO_RXQ_OVFL on Linux), and every datagram sent is read, dropped from the queue or
    counted as dropped by the system."""
    import sys

    import dagr_lite.camera.udp as udp_module

    if not sys.platform.startswith("linux"):
        return
    monkeypatch.setattr(udp_module, "RECEIVE_BUFFER", 4096)
    udp = source()
    slow_enqueue = udp._enqueue

    def slow(arrival, payload):
        time.sleep(0.002)
        slow_enqueue(arrival, payload)

    udp._enqueue = slow
    flood = packets(300, per_packet=100)
    chunks = udp.events()
    sent = []

    def sender():  # a flood, then a trickle: the system reports its count with the datagrams it delivers
        udp.ready.wait(30)
        time.sleep(0.1)
        url = f"udp://127.0.0.1:{udp.address[1]}"
        sent.append(send([{key: np.concatenate([p[key] for p in flood[:290]]) for key in flood[0]}], url,
                         fmt=UDP["fmt"], speed=0, events_per_packet=100))
        for packet in flood[290:]:
            time.sleep(0.05)
            sent.append(send([packet], url, fmt=UDP["fmt"], speed=0, events_per_packet=100))

    thread = threading.Thread(target=sender)
    thread.start()
    received = sum(len(chunk["t"]) for chunk in chunks)
    thread.join()
    stats = udp.stats
    assert stats.os_dropped_packets > 0
    assert stats.packets + stats.backlog_dropped_packets + stats.os_dropped_packets == len(flood) == sum(sent) // 100
    assert received == stats.events


def test_a_stream_without_a_host_listens_on_loopback_only():
    from dagr_lite.camera.udp import parse_address
    from dagr_lite.errors import UserError

    assert parse_address("udp://:5000") == ("127.0.0.1", 5000)
    assert parse_address("udp://0.0.0.0:5000") == ("0.0.0.0", 5000)
    for bad in ("udp://host", "tcp://:5000", "udp://:port"):
        with pytest.raises(UserError, match="a live stream is udp://HOST:PORT"):
            parse_address(bad)
