"""Recordings of every format faery writes read back what was written; bad files are refused by name."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from dagr_lite.camera.aedat import write_aedat4
from dagr_lite.camera.recording import (RecordingError, TimeOrder, scan_chunk, concat, open_recording,
                                        truncation_problem)

WIDTH, HEIGHT = 64, 48
T0 = 1_700_000_000_000  # a camera clock that does not start at 0 (microseconds)


def camera_events(seed: int = 0, n: int = 20_000) -> dict:
    """Events with several per pixel and microsecond, as real sensors give them."""
    rng = np.random.default_rng(seed)
    t = T0 + np.sort(rng.integers(0, 50_000, n))
    burst = slice(n // 2, n // 2 + 40)
    t[burst] = t[n // 2]  # a burst: 40 events in one microsecond
    x, y = rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n)
    x[burst], y[burst] = 5, 7  # ... at one pixel
    return {"x": x, "y": y, "t": t, "p": rng.integers(0, 2, n)}


def faery_write(path, events, **kwargs):
    import faery

    packed = np.zeros(len(events["t"]), faery.EVENTS_DTYPE)
    packed["t"], packed["x"], packed["y"], packed["on"] = events["t"], events["x"], events["y"], events["p"] > 0
    return faery.events_stream_from_array(packed, dimensions=(WIDTH, HEIGHT)).to_file(str(path), **kwargs)


FORMATS = [("rec.aedat4", {}), ("evt2.raw", {"version": "evt2"}), ("evt3.raw", {"version": "evt3"}),
           ("rec.dat", {}), ("rec.es", {}), ("rec.csv", {})]


@pytest.mark.parametrize(("name", "kwargs"), FORMATS, ids=[f[0] for f in FORMATS])
def test_every_format_faery_writes_reads_back_what_was_written(tmp_path, name, kwargs):
    events = camera_events()
    faery_write(tmp_path / name, events, **kwargs)
    rec = open_recording(tmp_path / name, size=(WIDTH, HEIGHT) if name.endswith(".csv") else None)
    chunks = list(rec.events())
    got = concat(chunks)
    assert rec.size == (WIDTH, HEIGHT)
    for key in "xyp":
        np.testing.assert_array_equal(got[key], events[key], err_msg=key)
    if name.endswith(".es"):  # ES stores times from the first event (faery returns that offset)
        np.testing.assert_array_equal(got["t"] - got["t"][0], events["t"] - events["t"][0])
    else:
        np.testing.assert_array_equal(got["t"], events["t"])
    assert all(len(c["t"]) for c in chunks) and not rec.has_frames


def test_aedat4_frame_track_reads_back_exactly_and_in_time_with_the_events(tmp_path):
    events = camera_events(1)
    rng = np.random.default_rng(2)
    frames = [(T0 + k * 20_000, rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)) for k in range(3)]
    frames.append((T0 + 60_000, rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)))  # a grey DAVIS frame
    write_aedat4(tmp_path / "davis.aedat4", events, (WIDTH, HEIGHT), frames)
    rec = open_recording(tmp_path / "davis.aedat4")
    got = concat(list(rec.events()))
    for key in "xytp":
        np.testing.assert_array_equal(got[key], events[key])
    read = list(rec.frames())
    assert [t for t, _ in read] == [t for t, _ in frames]
    for (_, image), (_, expected) in zip(read, frames):
        expected = expected if expected.ndim == 3 else np.repeat(expected[..., None], 3, axis=2)
        np.testing.assert_array_equal(image, expected)
    with pytest.raises(FileExistsError, match="nothing is overwritten"):
        write_aedat4(tmp_path / "davis.aedat4", events, (WIDTH, HEIGHT), frames)


def test_h5_recording_is_read_in_chunks_with_its_frames(monkeypatch, dataset):
    import dagr_lite.camera.recording as recording

    monkeypatch.setattr(recording, "H5_CHUNK", 1000)
    video = next(iter(dataset.events))
    split = dataset.splits[video]
    rec = open_recording(dataset.root / split / "events" / f"{video}.h5")
    chunks = list(rec.events())
    assert len(chunks) > 1 and max(len(c["t"]) for c in chunks) <= 1000
    for key in "xytp":
        np.testing.assert_array_equal(concat(chunks)[key], dataset.events[video][key])
    frames = list(rec.frames())
    assert len(frames) == len(dataset.frames[video])
    np.testing.assert_array_equal(frames[1][1].shape, dataset.frames[video][1].shape)


def test_frame_folder_with_timestamps_goes_with_the_events(tmp_path):
    from PIL import Image

    events = camera_events(3, 500)
    faery_write(tmp_path / "rec.es", events)
    folder = tmp_path / "frames"
    folder.mkdir()
    images = [np.full((HEIGHT, WIDTH, 3), 40 * k, np.uint8) for k in range(3)]
    for k, image in enumerate(images):
        Image.fromarray(image).save(folder / f"img_{k:02d}.png")
    (folder / "timestamps.txt").write_text("0\n33333\n66667\n")
    rec = open_recording(tmp_path / "rec.es", frames=folder)
    got = list(rec.frames())
    assert [t for t, _ in got] == [0, 33333, 66667]
    np.testing.assert_array_equal(got[2][1], images[2])
    (folder / "timestamps.txt").write_text("0\n33333\n")
    with pytest.raises(RecordingError, match="timestamps.txt: 2 times for 3 frames"):
        open_recording(tmp_path / "rec.es", frames=folder)
    (folder / "timestamps.txt").rename(tmp_path / "times.txt")
    with pytest.raises(RecordingError, match="timestamps.txt: the frame timestamp file is missing; .* frame_times=FILE"):
        open_recording(tmp_path / "rec.es", frames=folder)
    (tmp_path / "times.txt").write_text("0\n33333\n66667\n")
    assert [t for t, _ in open_recording(tmp_path / "rec.es", frames=folder, frame_times=tmp_path / "times.txt").frames()] \
        == [0, 33333, 66667]  # the times named by frame_times
    (tmp_path / "times.txt").rename(folder / "timestamps.txt")
    # times in seconds or milliseconds, or nanoseconds: refused with the fix, not read as microseconds
    for text, fix in (("0.0\n0.033333\n0.066667\n", "x 1e6"), ("0\n33.3\n66.7\n", "x 1e3"),
                      ("0\n33333333\n66666667\n", "/ 1e3")):
        (folder / "timestamps.txt").write_text(text)
        with pytest.raises(RecordingError, match=f"timestamps.txt: the frames are .* apart in the median; .*{fix}"):
            open_recording(tmp_path / "rec.es", frames=folder)


def _backwards(name: str, data: bytes) -> bytes:
    """The file's bytes with events 3 and 6 swapped (in EVT3, event 7's time set back to 1)."""
    if name.endswith(".csv"):
        lines = data.split(b"\r\n")
        lines[4], lines[7] = lines[7], lines[4]
        return b"\r\n".join(lines)
    start = 0
    while data.startswith(b"%", start):  # past the header lines
        start = data.index(b"\n", start) + 1
    if name == "evt3.raw":
        return data[:start] + data[start:].replace(bytes([0x07, 0x60]), bytes([0x01, 0x60]), 1)  # TIME_LOW 7 -> 1
    word = {"evt2.raw": 4, "rec.dat": 8}[name]
    start += word if name == "evt2.raw" else 2  # past EVT2's first time word / DAT's type and size bytes
    event = [data[start + k * word:start + (k + 1) * word] for k in range(10)]
    event[3], event[6] = event[6], event[3]
    return data[:start] + b"".join(event) + data[start + 10 * word:]


@pytest.mark.parametrize(("name", "kwargs"), FORMATS, ids=[f[0] for f in FORMATS])
def test_faery_refuses_events_off_the_sensor_and_never_goes_back_in_time_and_csv_shows_disorder(tmp_path, name, kwargs):
    """What lets faery's chunks pass through unscanned (recording.py's docstring)."""
    import faery

    packed = np.zeros(10, faery.EVENTS_DTYPE)
    packed["t"], packed["x"], packed["y"] = 1000 + np.arange(10), [1, 2, 3, 70, 5, 6, 7, 8, 9, 10], 1
    faery.events_stream_from_array(packed, dimensions=(99, 48)).to_file(str(tmp_path / name), **kwargs)
    data = (tmp_path / name).read_bytes()
    header = {"rec.es": (b"Event Stream\x02\x00\x00\x01c\x00", b"Event Stream\x02\x00\x00\x01@\x00"),
              "rec.aedat4": (b'"int">99<', b'"int">64<')}.get(name, (b"99", b"64"))
    off = tmp_path / f"off_{name}"
    off.write_bytes(data.replace(*header))  # the same events on a sensor 64 wide: x=70 lies off it
    message = (rf"{off}: event at t=1003 us lies at \(70, 1\), outside the 64x48 sensor" if name == "rec.csv" else
               rf"{off}: after 0 events, an event lies outside the 64x48 sensor its header declares \(x overflow \(x=70 .*width=64\)\)")
    with pytest.raises(RecordingError, match=message):
        list(open_recording(off, size=(64, 48) if name == "rec.csv" else None).events())
    if name == "rec.es":
        return  # ES stores times as unsigned steps: it cannot go back
    back = tmp_path / f"back_{name}"
    if name == "rec.aedat4":
        order = [0, 1, 2, 6, 4, 5, 3, 7, 8, 9]
        write_aedat4(back, {k: packed[f][order].astype(np.int64) for k, f in zip("xytp", ("x", "y", "t", "on"))},
                     size=(99, 48))
    else:
        back.write_bytes(_backwards(name, data))
    recording = open_recording(back, size=(99, 48))
    t = concat(list(recording.events()))["t"]
    if name == "rec.csv":  # read here, not by faery: the disorder is seen, sorted and counted, or refused
        assert np.array_equal(t, packed["t"].astype(np.int64)) and recording.order.out_of_order == 3
        with pytest.raises(RecordingError, match="3 of 10 events are out of time order; the first is event 4"):
            list(open_recording(back, size=(99, 48), order="refuse").events())
        return
    assert len(t) == 10 and np.all(np.diff(t) >= 0) and not np.array_equal(t, packed["t"].astype(np.int64))
    # EVT and DAT words are scanned before faery decodes them (camera/rawtime.py): the re-timed events are counted
    assert (None if recording.retimed is None else recording.retimed.late) == {"rec.aedat4": None, "evt3.raw": 1}.get(name, 3)


def test_time_order_sorts_within_its_window_and_says_where_disorder_is():
    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, 100_000, 3000))
    jitter = t + rng.integers(-400, 400, len(t))  # events up to 800 us out of order
    events = {"x": np.arange(len(t)), "y": np.zeros(len(t), int), "t": jitter, "p": np.ones(len(t), int)}
    order = TimeOrder("cam.h5", "sort", window_us=1000)
    parts = [part for i in range(0, len(t), 250) for part in order.push({k: v[i:i + 250] for k, v in events.items()})]
    got = concat(parts + order.flush())
    expected = np.argsort(jitter, kind="stable")
    np.testing.assert_array_equal(got["x"], expected)  # the same events, now in stable time order
    running = np.maximum.accumulate(jitter)
    assert order.stats.out_of_order == int(np.sum(jitter[1:] < running[:-1])) > 0

    tight = TimeOrder("cam.h5", "sort", window_us=10)
    with pytest.raises(RecordingError, match=r"cam.h5: event \d+ at t=\d+ us arrives after .*raise order_window_us"):
        for i in range(0, len(t), 250):
            tight.push({k: v[i:i + 250] for k, v in events.items()})


def test_chunks_in_order_pass_through_whole_and_held_back_by_the_window_only():
    t = np.arange(0, 10_000, 10)
    events = {"x": np.arange(len(t)), "y": np.zeros(len(t), int), "t": t, "p": np.ones(len(t), int)}
    order = TimeOrder("cam.h5", "sort", window_us=95)
    out = [order.push({k: v[i:i + 100] for k, v in events.items()}) for i in range(0, len(t), 100)]
    assert out[0] == []  # its last event is not yet 95 us old
    assert [len(p["t"]) for p in out[1]] == [100]  # now it is: the whole chunk goes out
    assert np.shares_memory(out[1][0]["t"], events["t"])  # a view of what was read, not a copy
    np.testing.assert_array_equal(concat([p for parts in out for p in parts] + order.flush())["x"], events["x"])


def test_compiled_check_finds_what_numpy_finds_on_strided_decoder_arrays():
    rng = np.random.default_rng(2)
    packed = np.zeros(5000, [("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])  # faery's 13-byte events
    packed["t"] = np.sort(rng.integers(10, 10**6, 5000))
    packed["x"], packed["y"] = rng.integers(0, 64, 5000), rng.integers(0, 48, 5000)
    t = packed["t"].view(np.int64)
    for late_at, outside_at in [(None, None), (1234, None), (None, 77), (4000, 4999), (0, 0)]:
        chunk = packed.copy()
        if late_at is not None:
            chunk["t"][late_at] = chunk["t"][late_at - 1] - 5 if late_at else 3
        if outside_at is not None:
            chunk["y"][outside_at] = 48
        ct = chunk["t"].view(np.int64)
        running = np.maximum.accumulate(np.concatenate([[5], ct]))
        late = np.flatnonzero(ct < running[:-1])
        outside = np.flatnonzero((chunk["x"] >= 64) | (chunk["y"] >= 48))
        got = scan_chunk(ct, chunk["x"], chunk["y"], 5, 64, 48)
        assert got == (len(late) > 0, len(outside) > 0, running.max())
        if outside_at is not None:
            with pytest.raises(RecordingError, match=r"cam.raw: event at t=\d+ us lies at \(\d+, 48\), outside the 64x48"):
                TimeOrder("cam.raw", "sort", 0, size=(64, 48)).push(
                    {"x": chunk["x"], "y": chunk["y"], "t": ct, "p": chunk["on"]})
    p = np.array([0, 1, 1, 2, 0, -1])
    order = TimeOrder("cam.raw", "sort", 0, size=(64, 48))
    out = order.push({"x": packed["x"][:6], "y": packed["y"][:6], "t": t[:6], "p": p}) + order.flush()
    np.testing.assert_array_equal(concat(out)["p"], [0, 1, 1, 1, 0, 0])


def test_refused_disorder_counts_every_late_event_of_the_file(tmp_path):
    t = np.array([10, 20, 15, 30, 40, 5, 50, 60])
    with h5py.File(tmp_path / "cam.h5", "w") as h5:
        for key, values in (("x", np.arange(8)), ("y", np.zeros(8)), ("t", t), ("p", np.ones(8))):
            h5[f"events/{key}"] = values.astype(np.int64)
        h5["timeidx"] = np.array([0], np.int64)
    rec = open_recording(tmp_path / "cam.h5", size=(8, 8), order="refuse")
    with pytest.raises(RecordingError, match=r"cam.h5: 2 of 8 events are out of time order; the first is event 2 "
                                             r"at t=15 us, after an event at t=20 us"):
        list(rec.events())
    rec = open_recording(tmp_path / "cam.h5", size=(8, 8), order="sort", order_window_us=100)
    assert concat(list(rec.events()))["t"].tolist() == sorted(t.tolist())


@pytest.mark.parametrize(("name", "kwargs", "cut", "message"), [
    ("rec.csv", {}, -3, "its last line is incomplete"),
    ("evt2.raw", {"version": "evt2"}, -2, "not a whole number of 4-byte words"),
    ("evt3.raw", {"version": "evt3"}, -1, "not a whole number of 2-byte words"),
    ("rec.dat", {}, -5, "not a whole number of 8-byte words"),
    ("rec.aedat4", {}, 0.5, "cannot read it as aedat after"),
    ("rec.es", {}, -3, "its last event lacks 3 of its 5 bytes"),
])
def test_a_truncated_recording_is_refused_naming_the_file(tmp_path, name, kwargs, cut, message):
    faery_write(tmp_path / name, camera_events(4), **kwargs)
    data = (tmp_path / name).read_bytes()
    (tmp_path / name).write_bytes(data[:int(len(data) * cut)] if isinstance(cut, float) else data[:cut])
    with pytest.raises(RecordingError, match=rf"{name}: .*{message}"):
        rec = open_recording(tmp_path / name, size=(WIDTH, HEIGHT))
        list(rec.events())


@pytest.mark.parametrize("n", [1, 2, 5000])
def test_a_whole_event_stream_file_is_not_called_truncated(tmp_path, n):
    events = {k: v[:n] for k, v in camera_events(5).items()}
    events["t"][n // 2:] += 10_000  # time steps of more than 127 us: overflow bytes
    faery_write(tmp_path / "rec.es", events)
    assert truncation_problem(tmp_path / "rec.es", "es") is None
    assert len(concat(list(open_recording(tmp_path / "rec.es").events()))["t"]) == n


def test_unknown_missing_and_mismatched_inputs_are_refused(tmp_path):
    (tmp_path / "rec.mp4").write_bytes(b"")
    with pytest.raises(RecordingError, match=r"rec.mp4: unknown recording format '.mp4'; expected one of .aedat4"):
        open_recording(tmp_path / "rec.mp4")
    with pytest.raises(RecordingError, match="gone.raw: no such file"):
        open_recording(tmp_path / "gone.raw")
    faery_write(tmp_path / "rec.csv", camera_events(5, 100))
    with pytest.raises(RecordingError, match="does not say its sensor size; give sensor.size"):
        open_recording(tmp_path / "rec.csv")
    (tmp_path / "junk.aedat4").write_bytes(b"not an aedat file at all")
    with pytest.raises(RecordingError, match=r"junk.aedat4: named .aedat4, but it does not begin as an AEDAT4 file"):
        open_recording(tmp_path / "junk.aedat4")
    # A frame track of another size than the events: the header's second sizeX says 65.
    write_aedat4(tmp_path / "davis.aedat4", camera_events(6, 100), (WIDTH, HEIGHT),
                 [(T0, np.zeros((HEIGHT, WIDTH, 3), np.uint8))])
    data = bytearray((tmp_path / "davis.aedat4").read_bytes())
    marker = b'<attr key="sizeX" type="int">64</attr>'
    second = data.index(marker, data.index(marker) + 1)
    data[second:second + len(marker)] = marker.replace(b"64", b"65")
    (tmp_path / "bad_frames.aedat4").write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="bad_frames.aedat4: its frame track 1 is 65x48, its events 64x48"):
        open_recording(tmp_path / "bad_frames.aedat4")


def test_export_writes_every_format_that_reads_back_the_dataset(dataset, tmp_path):
    from dagr_lite.camera.export import RENDER_FPS, export_dataset

    video = next(iter(dataset.events))
    written = export_dataset(dataset.root, tmp_path / "out", ["aedat4", "evt3", "csv", "mp4"], videos=[video])
    assert [p.name for p in written] == [f"{video}.aedat4", f"{video}.evt3.raw", f"{video}.csv", f"{video}.mp4"]
    height, width = dataset.frames[video][0].shape[:2]
    for path in written[:3]:
        got = concat(list(open_recording(path, size=(width, height)).events()))
        for key in "xytp":
            np.testing.assert_array_equal(got[key], dataset.events[video][key], err_msg=f"{path.name} {key}")
    frames = list(open_recording(written[0]).frames())
    assert len(frames) == len(dataset.frames[video])
    import av

    with av.open(str(written[3])) as video_file:  # the events in real time, a frame every 1 / RENDER_FPS s
        stream = video_file.streams.video[0]
        shown = sum(1 for _ in video_file.decode(stream))
        assert float(stream.average_rate) == pytest.approx(RENDER_FPS)
    span_s = (dataset.events[video]["t"][-1] - dataset.events[video]["t"][0]) / 1e6
    assert abs(shown / RENDER_FPS - span_s) <= 2 / RENDER_FPS
    before = {p: p.read_bytes() for p in written}
    assert export_dataset(dataset.root, tmp_path / "out", ["csv", "es"], videos=[video]) == [written[2].with_suffix(".es")]
    assert all(p.read_bytes() == data for p, data in before.items())  # kept, not written again


def test_an_interrupted_export_leaves_no_finished_looking_file_and_a_rerun_completes_it(dataset, tmp_path, monkeypatch):
    from dagr_lite.camera import export

    video = next(iter(dataset.events))
    real_packets = export._faery_packets

    def interrupted(recording):
        for packed in real_packets(recording):
            yield packed[:10]  # a little of the file is written, then Ctrl-C
            raise KeyboardInterrupt

    monkeypatch.setattr(export, "_faery_packets", interrupted)
    stale = tmp_path / "out" / dataset.splits[video] / f"{video}.partial1.csv"  # a killed run's leftover
    stale.parent.mkdir(parents=True)
    stale.write_text("t,x,y,on\n")
    with pytest.raises(KeyboardInterrupt):
        export.export_dataset(dataset.root, tmp_path / "out", ["evt3", "csv"], videos=[video])
    assert sorted(p.name for p in stale.parent.iterdir()) == [stale.name]  # nothing named as if finished
    monkeypatch.setattr(export, "_faery_packets", real_packets)
    written = export.export_dataset(dataset.root, tmp_path / "out", ["evt3", "csv"], videos=[video])
    assert sorted(p.name for p in stale.parent.iterdir()) == sorted(p.name for p in written)  # the leftover is gone
    got = concat(list(open_recording(written[1], size=dataset.frames[video][0].shape[1::-1]).events()))
    np.testing.assert_array_equal(got["t"], dataset.events[video]["t"])


def test_recording_statistics_count_bursts_and_hot_pixels(tmp_path):
    from dagr_lite.apps.recording_stats import recording_stats

    events = camera_events(7, 5000)
    faery_write(tmp_path / "rec.evt3.raw", events, version="evt3")
    stats = recording_stats(tmp_path / "rec.evt3.raw", tmp_path / "stats")
    keys = events["t"] * WIDTH * HEIGHT + events["y"] * WIDTH + events["x"]
    assert stats["events"] == 5000 and stats["t_first_us"] == int(events["t"][0])
    assert stats["events_sharing_pixel_and_microsecond"] == 5000 - len(np.unique(keys)) >= 39
    assert stats["hot_pixels"][0] == {"x": 5, "y": 7, "events": int(np.sum((events["x"] == 5) & (events["y"] == 7))),
                                      "rate": stats["hot_pixels"][0]["rate"]}
    assert (tmp_path / "stats" / "event_rate.png").stat().st_size > 0


def test_recording_statistics_of_a_clock_that_jumps_to_epoch_time(tmp_path):
    from dagr_lite.apps.recording_stats import recording_stats

    events = camera_events(8, 4000)
    jump = 1_700_000_000_000_000  # to Unix-epoch microseconds
    events["t"] = events["t"] - T0
    events["t"][2000:] += jump
    csv = tmp_path / "jump.csv"
    csv.write_text("t,x,y,on\n" + "".join(f"{t},{x},{y},{p}\n" for t, x, y, p in zip(*(events[k] for k in "txyp"))))
    stats = recording_stats(csv, tmp_path / "stats", size=(WIDTH, HEIGHT))
    t = events["t"]
    assert stats["clock_jumps"] == [{"from_us": int(t[1999]), "to_us": int(t[2000])}]
    assert stats["duration_s"] == pytest.approx((t[1999] - t[0] + t[-1] - t[2000]) / 1e6)
    keys = (t - np.where(np.arange(4000) >= 2000, jump, 0)) * WIDTH * HEIGHT + events["y"] * WIDTH + events["x"]
    assert stats["events_sharing_pixel_and_microsecond"] == 4000 - len(np.unique(keys))
    assert stats["peak_rate"] > 0 and (tmp_path / "stats" / "event_rate.png").stat().st_size > 0


def test_recording_statistics_place_hot_pixels_of_a_large_sensor(tmp_path):
    """Decoders give 16-bit coordinates: pixel indices of a 1280x720 sensor must not wrap."""
    import faery

    from dagr_lite.apps.recording_stats import recording_stats

    packed = np.zeros(300, faery.EVENTS_DTYPE)
    packed["t"] = T0 + np.arange(300)
    packed["x"], packed["y"] = np.where(np.arange(300) < 200, 1200, 3), np.where(np.arange(300) < 200, 700, 4)
    faery.events_stream_from_array(packed, dimensions=(1280, 720)).to_file(str(tmp_path / "big.es"))
    stats = recording_stats(tmp_path / "big.es", tmp_path / "stats")
    assert stats["hot_pixels"][0]["x"] == 1200 and stats["hot_pixels"][0]["y"] == 700
    assert stats["hot_pixels"][0]["events"] == 200


def test_a_failed_aedat4_write_leaves_no_file(tmp_path):
    events = camera_events(n=1000)
    wrong = [(int(events["t"][500]), np.zeros((HEIGHT + 1, WIDTH, 3), np.uint8))]  # a frame of another size
    with pytest.raises(ValueError, match=r"expected \(48, 64"):
        write_aedat4(tmp_path / "cam.aedat4", events, (WIDTH, HEIGHT), wrong)
    assert list(tmp_path.iterdir()) == []


def test_recording_statistics_count_repeats_across_chunk_boundaries(tmp_path, monkeypatch):
    import dagr_lite.camera.recording as recording
    from dagr_lite.apps.recording_stats import recording_stats

    rng = np.random.default_rng(4)
    t = np.sort(rng.integers(0, 40, 300)) * 20_000  # about 7 events per microsecond, 20 ms apart, on few pixels
    x, y = rng.integers(0, 3, 300), rng.integers(0, 2, 300)
    with h5py.File(tmp_path / "cam.h5", "w") as h5:
        for key, values in (("x", x), ("y", y), ("t", t), ("p", rng.integers(0, 2, 300))):
            h5[f"events/{key}"] = values.astype(np.int64)
        h5["timeidx"] = np.array([0], np.int64)
    keys = t * 6 + y * 3 + x
    expected = 300 - len(np.unique(keys))
    for chunk in (1 << 18, 7, 1):  # one chunk; chunks that cut microseconds; one event a chunk
        monkeypatch.setattr(recording, "H5_CHUNK", chunk)
        stats = recording_stats(tmp_path / "cam.h5", tmp_path / f"stats{chunk}", size=(3, 2))
        assert stats["events_sharing_pixel_and_microsecond"] == expected, chunk


def test_a_file_that_is_not_what_its_suffix_claims_is_called_by_what_it_is(tmp_path):
    events = camera_events(1, 200)
    faery_write(tmp_path / "rec.es", events)
    faery_write(tmp_path / "rec.raw", events, version="evt3")
    data = (tmp_path / "rec.es").read_bytes()
    (tmp_path / "renamed.raw").write_bytes(data[:-1])  # an .es file minus a byte, named .raw
    with pytest.raises(RecordingError, match=r"renamed\.raw: named \.raw, but it is an Event Stream file \(\.es\)"):
        open_recording(tmp_path / "renamed.raw", size=(1280, 720))
    raw = (tmp_path / "rec.raw").read_bytes()
    payload = raw[raw.rindex(b"\n%") + 1:]
    (tmp_path / "headerless.raw").write_bytes(payload[payload.index(b"\n") + 1:])
    with pytest.raises(RecordingError, match=r"headerless\.raw: a Prophesee \.raw file begins with its % header"):
        open_recording(tmp_path / "headerless.raw", size=(1280, 720))
    (tmp_path / "es.aedat4").write_bytes(data)
    with pytest.raises(RecordingError, match=r"es\.aedat4: named \.aedat4, but it is an Event Stream file"):
        open_recording(tmp_path / "es.aedat4")
    assert len(concat(list(open_recording(tmp_path / "rec.raw").events()))["t"]) == 200


def test_a_folder_or_a_pipe_is_not_called_a_missing_file(tmp_path):
    import os

    (tmp_path / "rec.aedat4").mkdir()
    with pytest.raises(RecordingError, match=r"rec\.aedat4: a folder, not a recording"):
        open_recording(tmp_path / "rec.aedat4")
    os.mkfifo(tmp_path / "pipe.raw")
    with pytest.raises(RecordingError, match=r"pipe\.raw: not a regular file \(a pipe or a device\)"):
        open_recording(tmp_path / "pipe.raw")


def test_h5_recording_given_its_own_frame_folder_takes_the_frame_times_from_the_h5(dataset, tmp_path):
    """A built-in video's frame folder holds no timestamps.txt: its times are in the h5 file, so naming
    the folder with frames= reads them there; another folder without one is still refused."""
    video = next(iter(dataset.events))
    split = dataset.splits[video]
    path = dataset.root / split / "events" / f"{video}.h5"
    folder = dataset.root / split / "frames" / video
    assert not (folder / "timestamps.txt").exists()
    alone = list(open_recording(path).frames())
    named = list(open_recording(path, frames=folder / ".." / ".." / "frames" / video).frames())  # spelt otherwise
    assert len(alone) == len(dataset.frames[video]) > 1
    assert [t for t, _ in named] == [t for t, _ in alone]
    for (_, got), (_, expected) in zip(named, alone):
        np.testing.assert_array_equal(got, expected)
    copy = tmp_path / "copy"
    copy.mkdir()
    for file in folder.iterdir():
        (copy / file.name).write_bytes(file.read_bytes())
    with pytest.raises(RecordingError, match="timestamps.txt: the frame timestamp file is missing"):
        open_recording(path, frames=copy)
