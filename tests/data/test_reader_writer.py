import json
import pickle

import h5py
import numpy as np
import pytest
from PIL import Image

from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.events import EventFile
from dagr_lite.data.frames import frame_size, jpeg_size, read_frame
from dagr_lite.data.labels import list_videos, read_labels
from dagr_lite.data.writer import EventFileWriter, write_events, write_frame, write_labels, write_video
from tests.conftest import make_dataset, random_events


def brute_force_window(events, t_start, t_end):
    mask = (events["t"] >= t_start) & (events["t"] < t_end)
    return {name: events[name][mask] for name in "xytp"}


@pytest.mark.parametrize("compression", [None, "gzip", "blosc"])
def test_round_trip_of_every_piece(tmp_path, compression):
    written = make_dataset(tmp_path, compression=compression, num_frames=6, events_per_video=500)
    assert list_videos(tmp_path, "train") == ["CARDS_COURTYARD_B_T", "vid_b"]
    labels = read_labels(tmp_path)
    for video, split in written.splits.items():
        events = EventFile(fmt.events_path(tmp_path, split, video), num_frames=6)
        raw = events.read(0, events.num_events)
        for name in "xytp":
            np.testing.assert_array_equal(raw[name], written.events[video][name])
        np.testing.assert_array_equal(events.timeidx, fmt.expected_timeidx(written.events[video]["t"], 6))
        frame = read_frame(fmt.frame_path(tmp_path, split, video, 3))
        assert frame.shape == written.frames[video][3].shape and frame.dtype == np.uint8
        # JPEG is lossy: a close copy of the frame, not an exact one.
        assert np.abs(frame.astype(int) - written.frames[video][3]).max() <= 6
        assert set(labels[video]) == set(written.labels[video])
        for k, boxes in written.labels[video].items():
            np.testing.assert_allclose(labels[video][k], boxes.reshape(-1, 4), atol=1e-3)


def test_blosc_files_use_the_blosc_filter(tmp_path):
    path = write_events(tmp_path / "a.h5", [1, 2], [3, 4], [5, 6], [0, 1], num_frames=1, compression="blosc")
    with h5py.File(path, "r") as h5:
        for key in fmt.EVENT_KEYS:
            assert "32001" in h5[key]._filters
            assert h5[key].chunks is not None


def test_window_slices_equal_a_brute_force_mask(tmp_path):
    rng = np.random.default_rng(1)
    num_frames = 20
    # Bursty stream with repeated timestamps, starting after 0 and ending before the last frame.
    t = np.sort(np.concatenate([rng.integers(50_000, 300_000, 4000), np.full(50, 100_000),
                                np.full(30, fmt.frame_time_us(5))]))
    events = {"x": rng.integers(0, 64, len(t)), "y": rng.integers(0, 48, len(t)), "t": t,
              "p": rng.integers(0, 2, len(t))}
    path = write_events(tmp_path / "v.h5", **events, num_frames=num_frames, chunk_events=512)
    reader = EventFile(path, num_frames=num_frames)
    frame_times = fmt.frame_time_us(np.arange(num_frames))
    windows = [(-50_000, 10_000),  # starts before the first event and before frame 0
               (0, 40_000),  # empty window before the first event
               (600_000, 700_000),  # after the last event and the last frame
               (250_000, 10**9),  # ends after the last event
               (100_000, 100_000), (100_000, 100_001), (99_999, 100_000),  # empty and tiny windows at a burst
               (frame_times[5], frame_times[6]), (frame_times[5] - 1, frame_times[5] + 1)]
    windows += [tuple(sorted(rng.integers(-10_000, 700_000, 2))) for _ in range(200)]
    for t_start, t_end in windows:
        got, want = reader.window(int(t_start), int(t_end)), brute_force_window(events, t_start, t_end)
        for name in "xytp":
            np.testing.assert_array_equal(got[name], want[name], err_msg=f"window [{t_start}, {t_end})")
        assert reader.index_of_time(int(t_start)) == np.searchsorted(t, t_start, side="left")


def test_event_file_survives_pickling_and_reopens(tmp_path):
    path = write_events(tmp_path / "v.h5", [1, 2, 3], [1, 2, 3], [0, 10, 40_000], [1, 0, 1], num_frames=2)
    reader = EventFile(path, num_frames=2)
    np.testing.assert_array_equal(reader.window(0, 100)["t"], [0, 10])
    clone = pickle.loads(pickle.dumps(reader))
    np.testing.assert_array_equal(clone.window(0, 100_000)["t"], [0, 10, 40_000])


def test_appending_in_pieces_equals_writing_at_once(tmp_path):
    events = random_events(np.random.default_rng(3), 5000, fmt.frame_time_us(10))
    whole = write_events(tmp_path / "whole.h5", **events, num_frames=10)
    with EventFileWriter(tmp_path / "pieces.h5", num_frames=10, chunk_events=256) as writer:
        bounds = [0, 1, 1, 700, 2500, 2501, 5000]
        for a, b in zip(bounds[:-1], bounds[1:]):
            writer.append(*(events[n][a:b] for n in "xytp"))
    with h5py.File(whole) as h5a, h5py.File(tmp_path / "pieces.h5") as h5b:
        for key in (*fmt.EVENT_KEYS, fmt.KEY_TIMEIDX):
            np.testing.assert_array_equal(h5a[key][()], h5b[key][()])


def test_writer_never_replaces_and_never_leaves_partial_files(tmp_path):
    path = write_events(tmp_path / "v.h5", [1], [1], [5], [1], num_frames=1)
    with pytest.raises(FileExistsError, match="v.h5"):
        write_events(path, [1], [1], [5], [1], num_frames=1)
    with pytest.raises(RuntimeError):
        with EventFileWriter(tmp_path / "w.h5", num_frames=1) as writer:
            writer.append([1], [1], [5], [1])
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.h5"]
    write_frame(tmp_path / "f.jpg", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(FileExistsError):
        write_frame(tmp_path / "f.jpg", np.zeros((4, 4, 3), np.uint8))
    write_labels(tmp_path, {"a": {0: [[1, 1, 2, 2]]}})
    with pytest.raises(FileExistsError):
        write_labels(tmp_path, {"a": {0: []}})
    write_labels(tmp_path, {"b": {3: []}}, merge=True)
    assert json.loads((tmp_path / fmt.LABELS_FILE).read_text()) == {"a_frame_0": [[1, 1, 2, 2]], "b_frame_3": []}


@pytest.mark.parametrize("bad,match", [
    (dict(t=[5, 3]), "sorted"), (dict(t=np.array([5, 3], np.uint64)), "sorted"),
    (dict(p=[0, 2]), "events/p must be 0 or 1"), (dict(x=[0, 64]), r"events/x must lie in \[0, 64\)"),
    (dict(t=[-1, 3]), ">= 0"), (dict(y=[1]), "has 1 values"), (dict(t=[0.5, 1.0]), "must be integers"),
])
def test_writer_rejects_bad_events(tmp_path, bad, match):
    events = {"x": [0, 1], "y": [0, 1], "t": [1, 2], "p": [0, 1], **bad}
    with pytest.raises(ValueError, match=match):
        write_events(tmp_path / "v.h5", **events, num_frames=1, width=64, height=48)
    assert not list(tmp_path.iterdir())


def test_writer_checks_coordinates_and_options_before_writing(tmp_path):
    with pytest.raises(ValueError, match=r"events/x must lie in \[0, 65536\)"):
        write_events(tmp_path / "v.h5", [70_000], [1], [1], [1], num_frames=1)  # would wrap in uint16
    with pytest.raises(ValueError, match="compression must be one of"):
        write_events(tmp_path / "w.h5", [1], [1], [1], [1], num_frames=1, compression="zstd")
    assert not list(tmp_path.iterdir())


def test_rewriting_a_video_removes_its_old_frames(tmp_path):
    frames = [np.full((8, 8, 3), 50, np.uint8)] * 5
    events = {"x": [1], "y": [1], "t": [10], "p": [1]}
    write_video(tmp_path, "train", "v", events=events, frames=frames)
    with pytest.raises(FileExistsError, match=r"v\.h5"):
        write_video(tmp_path, "train", "v", events=events, frames=frames[:3])
    assert len(list(fmt.frames_dir(tmp_path, "train", "v").iterdir())) == 5  # nothing was touched
    write_video(tmp_path, "train", "v", events=events, frames=frames[:3], overwrite=True)
    assert sorted(p.name for p in fmt.frames_dir(tmp_path, "train", "v").iterdir()) == [
        "frame_0.jpg", "frame_1.jpg", "frame_2.jpg"]
    assert EventFile(fmt.events_path(tmp_path, "train", "v"), num_frames=3).num_frames == 3
    with pytest.raises(ValueError, match="no frames given"):
        write_video(tmp_path, "train", "w", events=events, frames=[])


def test_reader_errors_name_file_and_key(tmp_path):
    path = tmp_path / "v.h5"
    with h5py.File(path, "w") as h5:
        for key in (fmt.KEY_X, fmt.KEY_Y, fmt.KEY_T):
            h5[key] = np.arange(3)
        h5[fmt.KEY_TIMEIDX] = np.array([0])
    with pytest.raises(DatasetFormatError, match=r"v\.h5: events/p: key is missing"):
        EventFile(path)
    with pytest.raises(DatasetFormatError, match=r"missing\.h5: events file is missing"):
        EventFile(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(DatasetFormatError, match=r"text\.h5: cannot open as HDF5"):
        EventFile(tmp_path / "text.h5")


def test_file_without_events_is_an_error(tmp_path):
    path = tmp_path / "empty.h5"
    with h5py.File(path, "w") as h5:
        for key in fmt.EVENT_KEYS:
            h5[key] = np.zeros(0, np.int64)
        h5[fmt.KEY_TIMEIDX] = np.zeros(3, np.int64)
    with pytest.raises(DatasetFormatError, match=r"empty\.h5: events/t: the file holds no events"):
        EventFile(path, num_frames=3)
    # The writer never makes such a file.
    with pytest.raises(ValueError, match=r"empty2\.h5: no events were written"):
        write_events(tmp_path / "empty2.h5", [], [], [], [], num_frames=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.h5"]


def test_unsigned_timestamps_read_and_check_like_signed_ones(tmp_path):
    path = tmp_path / "u.h5"
    t = np.array([0, 10, 40_000, 70_000], np.uint32)
    with h5py.File(path, "w") as h5:
        h5[fmt.KEY_X], h5[fmt.KEY_Y] = np.arange(4, dtype=np.uint16), np.arange(4, dtype=np.uint16)
        h5[fmt.KEY_T], h5[fmt.KEY_P] = t, np.ones(4, np.uint8)
        h5[fmt.KEY_TIMEIDX] = fmt.expected_timeidx(t.astype(np.int64), 3).astype(np.uint32)
    reader = EventFile(path, num_frames=3)
    window = reader.window(-33_333, 33_333)  # starts before 0: must not wrap around
    assert window["t"].dtype == np.int64 and window["t"].tolist() == [0, 10]
    assert (window["t"] - (-33_333)).tolist() == [33_333, 33_343]


def test_corrupt_chunk_names_the_file_and_key(tmp_path):
    events = random_events(np.random.default_rng(0), 20_000, fmt.frame_time_us(4))
    path = write_events(tmp_path / "c.h5", **events, num_frames=4, compression="gzip", chunk_events=4096)
    with h5py.File(path, "r") as h5:
        info = h5[fmt.KEY_X].id.get_chunk_info(2)
    with open(path, "r+b") as f:
        f.seek(info.byte_offset)
        f.write(b"\x00garbage" * (info.size // 8))
    reader = EventFile(path, num_frames=4)
    with pytest.raises(DatasetFormatError, match=r"c\.h5: events/x: cannot read entries"):
        reader.read(0, 20_000)


def test_timeidx_that_disagrees_with_t_is_an_error(tmp_path):
    path = write_events(tmp_path / "v.h5", [1, 1, 1], [1, 1, 1], [0, 40_000, 70_000], [1, 1, 1], num_frames=3)
    with h5py.File(path, "a") as h5:
        h5[fmt.KEY_TIMEIDX][2] = 1
    with pytest.raises(DatasetFormatError, match=r"v\.h5: timeidx: entry 2 = 1 fits neither frame-time convention; "
                                                 r"expected 2 \(round: first event at or after 66667 us\) "
                                                 r"or 2 \(truncate: first event at or after 66666 us\)"):
        EventFile(path, num_frames=3)


def test_corrupt_and_missing_frames_name_the_file(tmp_path):
    path = write_frame(tmp_path / "frame_0.jpg", np.full((8, 8, 3), 100, np.uint8))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetFormatError, match=r"frame_0\.jpg: cannot decode image"):
        read_frame(path)
    (tmp_path / "frame_1.jpg").write_bytes(b"\xff\xd8garbage")
    with pytest.raises(DatasetFormatError, match=r"frame_1\.jpg: cannot decode image"):
        read_frame(tmp_path / "frame_1.jpg")
    with pytest.raises(DatasetFormatError, match=r"frame_2\.jpg: frame file is missing"):
        read_frame(tmp_path / "frame_2.jpg")
    write_frame(tmp_path / "frame_3.jpg", np.zeros((8, 6, 3), np.uint8))
    with pytest.raises(DatasetFormatError, match=r"frame_3\.jpg: frame is 6x8 \(WxH\), expected 8x8"):
        read_frame(tmp_path / "frame_3.jpg", (8, 8))


def test_labels_errors_name_the_key(tmp_path):
    (tmp_path / fmt.LABELS_FILE).write_text(json.dumps({"v_frame_0": [[1, 2, 3]]}))
    with pytest.raises(DatasetFormatError, match=r"bounding_boxes\.json: v_frame_0: expected a box"):
        read_labels(tmp_path)
    (tmp_path / fmt.LABELS_FILE).write_text(json.dumps({"v_frame_x": []}))
    with pytest.raises(DatasetFormatError, match=r"v_frame_x: key is not of the form"):
        read_labels(tmp_path)
    (tmp_path / fmt.LABELS_FILE).write_text("{not json")
    with pytest.raises(DatasetFormatError, match=r"bounding_boxes\.json: cannot parse as JSON"):
        read_labels(tmp_path)
    (tmp_path / fmt.LABELS_FILE).unlink()
    with pytest.raises(DatasetFormatError, match=r"bounding_boxes\.json: label file is missing"):
        read_labels(tmp_path)


def test_videos_pair_by_name_and_unpaired_ones_are_named(tmp_path):
    make_dataset(tmp_path, videos={"b": "train", "a": "train"}, num_frames=2, events_per_video=10)
    assert list_videos(tmp_path, "train") == ["a", "b"]
    fmt.events_path(tmp_path, "train", "a").rename(fmt.events_path(tmp_path, "train", "c"))
    with pytest.raises(DatasetFormatError) as info:
        list_videos(tmp_path, "train")
    message = str(info.value)
    assert "c.h5: events file has no frame folder" in message and "frames/a: frame folder has no events file" in message
    with pytest.raises(DatasetFormatError, match=r"valid: split folder is missing"):
        list_videos(tmp_path, "valid")


def _with_polarity(path, index, value, num_events=20_000, num_frames=4):
    """A file written by hand (the writer refuses bad polarities) with ``p[index] = value``."""
    rng = np.random.default_rng([7])
    t = np.sort(rng.integers(0, fmt.frame_time_us(num_frames), num_events))
    p = rng.integers(0, 2, num_events).astype(np.uint8)
    p[index] = value
    with h5py.File(path, "w") as h5:
        h5[fmt.KEY_X] = h5[fmt.KEY_Y] = np.ones(num_events, np.uint16)
        h5[fmt.KEY_T], h5[fmt.KEY_P] = t, p
        h5[fmt.KEY_TIMEIDX] = fmt.expected_timeidx(t, num_frames)
    return t


def test_polarity_outside_0_1_is_caught_on_reading(tmp_path):
    path = tmp_path / "p.h5"
    t = _with_polarity(path, 10_000, 2)  # far from both ends: the opening check does not sample it
    reader = EventFile(path, num_frames=4)
    assert len(reader.window(0, int(t[9_000]))["p"]) == 9_000  # windows without it read normally
    match = r"p\.h5: events/p: values must be 0 or 1, found 2 at index 10000 \(in events 9990\.\.10009\)"
    with pytest.raises(DatasetFormatError, match=match):
        reader.read(9_990, 10_010)
    with pytest.raises(DatasetFormatError, match=r"p\.h5: events/p: values must be 0 or 1, found 2 at index 10000 "):
        reader.window(int(t[9_000]), int(t[11_000]))


@pytest.mark.parametrize("index", [5, 19_990])
def test_polarity_outside_0_1_near_either_end_is_caught_on_opening(tmp_path, index):
    _with_polarity(tmp_path / "p.h5", index, 2)
    with pytest.raises(DatasetFormatError, match=rf"p\.h5: events/p: values must be 0 or 1, found 2 at index {index} "):
        EventFile(tmp_path / "p.h5", num_frames=4)


@pytest.mark.parametrize("height,width,options", [
    (48, 64, {}), (1, 1, {}), (720, 1280, {"progressive": True}), (300, 17, {"quality": 20}),
    (37, 91, {"exif": b"Exif\x00\x00" + bytes(9000)}),  # metadata longer than the first read
])
def test_jpeg_size_reads_the_frame_header(tmp_path, height, width, options):
    path = tmp_path / "f.jpg"
    Image.fromarray(np.zeros((height, width, 3), np.uint8)).save(path, format="JPEG", **options)
    assert jpeg_size(path) == (height, width) == frame_size(path)
    Image.fromarray(np.zeros((height, width), np.uint8)).save(tmp_path / "g.jpg", format="JPEG")  # greyscale
    assert jpeg_size(tmp_path / "g.jpg") == (height, width)


def test_jpeg_size_refuses_what_is_not_a_whole_jpeg(tmp_path):
    path = write_frame(tmp_path / "frame_0.jpg", np.full((48, 64, 3), 100, np.uint8))
    data = path.read_bytes()
    cases = {"cut_in_header.jpg": (data[:120], r"file ends at byte \d+ before the frame header \(truncated header\)"),
             "cut_in_data.jpg": (data[: len(data) - 40], r"no end-of-image marker at the end \(truncated file\?\)"),
             "empty.jpg": (b"", "does not start with the JPEG start-of-image marker"),
             "no_sof.jpg": (b"\xff\xd8\xff\xda\x00\x02" + bytes(40) + b"\xff\xd9", "no frame header before marker 0xda"),
             "junk.jpg": (b"\xff\xd8\x12\x34" + bytes(40), "expected a marker at byte 2, found 0x12")}
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(DatasetFormatError, match=rf"{name}: not a readable JPEG: {message}"):
            jpeg_size(tmp_path / name)
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "png.jpg", format="PNG")
    with pytest.raises(DatasetFormatError, match=r"png\.jpg: not a readable JPEG: does not start with the JPEG"):
        jpeg_size(tmp_path / "png.jpg")
    with pytest.raises(DatasetFormatError, match=r"gone\.jpg: frame file is missing"):
        jpeg_size(tmp_path / "gone.jpg")


def test_a_blosc_event_file_reads_in_a_process_that_imports_only_the_reader(tmp_path):
    """The reader registers the Blosc filter itself (the writer, which also does, may never be imported)."""
    import subprocess
    import sys

    from dagr_lite.data.writer import EventFileWriter

    path = tmp_path / "v.h5"
    with EventFileWriter(path, num_frames=1, compression="blosc", height=4, width=4) as writer:
        writer.append(np.array([1]), np.array([2]), np.array([0]), np.array([1]))
    code = (f"from dagr_lite.data.events import EventFile; import sys; "
            f"e = EventFile({str(path)!r}).read(0, 1); sys.exit(0 if int(e['y'][0]) == 2 else 3)")
    assert "dagr_lite.data.writer" not in code
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-1500:]
