import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset, main
from dagr_lite.data.writer import write_frame


def messages(problems):
    return [str(p) for p in problems]


def test_a_written_dataset_has_no_problems(dataset, capsys):
    assert check_dataset(dataset.root, decode_frames=True) == []
    assert main([str(dataset.root)]) == 0
    out = capsys.readouterr().out
    assert "no problems found" in out and "note:" not in out and "a mix" not in out  # every split, labelled


def test_a_dataset_without_problems_says_what_training_still_needs(tmp_path, capsys):
    from tests.conftest import make_dataset
    make_dataset(tmp_path, videos={"a": "train"}, num_frames=6, events_per_video=100)
    labels = json.loads(fmt.labels_path(tmp_path).read_text())
    fmt.labels_path(tmp_path).write_text(json.dumps({key: [] for key in labels}))  # frames without hands count
    assert main([str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("note: no valid or test split: train.py reads")
    fmt.labels_path(tmp_path).write_text("{}")
    assert main([str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("note: no valid or test split; no labelled frame: ")


def edit_h5(path, fn):
    with h5py.File(path, "a") as h5:
        fn(h5)


def replace(h5, key, values):
    del h5[key]
    h5[key] = values


def _drop_p(h5):
    del h5[fmt.KEY_P]


def _shorten_x(h5):
    replace(h5, fmt.KEY_X, h5[fmt.KEY_X][:-1])


def _unsort_t(h5):
    t = h5[fmt.KEY_T][()]
    t[10], t[11] = t[11] + 1, t[10]
    replace(h5, fmt.KEY_T, t)


def _shift_timeidx(h5):
    timeidx = h5[fmt.KEY_TIMEIDX][()]
    timeidx[3] += 1  # a middle entry: the dataset's cheap check does not see it, the full check does
    replace(h5, fmt.KEY_TIMEIDX, timeidx)


def _bad_polarity(h5):
    p = h5[fmt.KEY_P][()]
    p[5] = 3
    replace(h5, fmt.KEY_P, p)


def _x_outside(h5):
    x = h5[fmt.KEY_X][()]
    x[7] = 500
    replace(h5, fmt.KEY_X, x)


@pytest.mark.parametrize("edit,key,text", [
    (_drop_p, "events/p", "key is missing"),
    (_shorten_x, "events/x", "differs from events/t length"),
    (_unsort_t, "events/t", "not sorted ascending at index 11"),
    (_shift_timeidx, "timeidx", "entry 3 = "),
    (_bad_polarity, "events/p", "values must be 0 or 1"),
    (_x_outside, "events/x", "values must lie in [0, 64)"),
])
def test_event_file_problems_name_file_and_key(dataset_copy, edit, key, text):
    path = fmt.events_path(dataset_copy.root, "train", "vid_b")
    edit_h5(path, edit)
    found = messages(check_dataset(dataset_copy.root))
    on_key = [m for m in found if m.startswith(f"{path}: {key}: ")]
    assert len(on_key) == 1 and text in on_key[0], found  # reported once, by the header or the full check
    assert main([str(dataset_copy.root)]) == 1


def test_frame_problems(dataset_copy):
    root = dataset_copy.root
    frames = fmt.frames_dir(root, "valid", "vid_c")
    (frames / "frame_4.jpg").unlink()
    (frames / "frame_6.jpg").unlink()
    write_frame(frames / "frame_6.jpg", np.zeros((10, 10, 3), np.uint8))
    write_frame(frames / "frame_12.jpg", np.zeros((48, 64, 3), np.uint8))
    write_frame(frames / "frame_13.jpg", np.zeros((48, 64, 3), np.uint8))
    (fmt.frames_dir(root, "test", "vid_d") / "frame_2.jpg").write_bytes(b"\xff\xd8\xff\xe0 broken")
    found = messages(check_dataset(root))
    assert f"{frames}: 1 frames missing, first frame_4.jpg" in found
    assert f"{frames / 'frame_6.jpg'}: frame is 10x10 (WxH), expected 64x48 as frame_0.jpg" in found
    assert f"{frames}: 2 frames beyond the 12 frames of timeidx, first frame_12.jpg" in found
    assert any(m.startswith(f"{fmt.frames_dir(root, 'test', 'vid_d') / 'frame_2.jpg'}: not a readable JPEG")
               for m in found)
    # The frame count then disagrees with timeidx.
    assert any("timeidx: has 12 entries but 13 frames exist" in m for m in found)


def test_label_problems(dataset_copy):
    root = dataset_copy.root
    path = fmt.labels_path(root)
    labels = json.loads(path.read_text())
    labels["vid_b_frame_0"] = [[60, 40, 10, 10]]  # leaves the 64x48 image
    labels["vid_b_frame_2"] = [[1, 1, 0, 5]]  # zero width
    labels["vid_b_frame_99"] = []  # the video has 12 frames
    labels["ghost_frame_0"] = []  # no such video
    labels["vid_b_frame_4"] = [[1, 2, 3]]  # malformed
    path.write_text(json.dumps(labels))
    found = messages(check_dataset(root))
    assert f"{path}: vid_b_frame_0: box [60.0, 40.0, 10.0, 10.0] leaves the 64x48 image" in found
    assert f"{path}: vid_b_frame_2: box [1.0, 1.0, 0.0, 5.0] has non-positive size (expected w > 0 and h > 0)" in found
    assert f"{path}: vid_b_frame_99: label for frame 99, but the video has 12 frames" in found
    assert f"{path}: ghost_frame_0: label for video 'ghost', which no split holds" in found
    assert any(m.startswith(f"{path}: vid_b_frame_4: expected a box") for m in found)
    assert len(found) == 5


def test_missing_pieces(tmp_path, dataset_copy):
    assert messages(check_dataset(tmp_path / "nothing")) == [f"{tmp_path / 'nothing'}: dataset folder is missing"]
    (tmp_path / "empty").mkdir()
    assert "no split folder found" in messages(check_dataset(tmp_path / "empty"))[0]
    root = dataset_copy.root
    fmt.events_path(root, "test", "vid_d").unlink()
    fmt.labels_path(root).unlink()
    found = messages(check_dataset(root))
    assert any("frames/vid_d: frame folder has no events file" in m for m in found)
    assert f"{fmt.labels_path(root)}: label file is missing" in found


def test_command_line_reports_and_exits_non_zero(dataset_copy):
    fmt.labels_path(dataset_copy.root).write_text(json.dumps({"vid_b_frame_50": []}))
    run = subprocess.run([sys.executable, "-m", "dagr_lite.data.check", str(dataset_copy.root)],
                         capture_output=True, text=True)
    assert run.returncode == 1
    assert "vid_b_frame_50: label for frame 50, but the video has 12 frames" in run.stdout


def test_unsigned_unsorted_timestamps_are_reported(dataset_copy):
    path = fmt.events_path(dataset_copy.root, "train", "vid_b")

    def to_unsorted_uint32(h5):
        t = h5[fmt.KEY_T][()].astype(np.uint32)
        t[20], t[21] = t[21] + 1, t[20]
        replace(h5, fmt.KEY_T, t)

    edit_h5(path, to_unsorted_uint32)
    assert f"{path}: events/t: not sorted ascending at index 21" in messages(check_dataset(dataset_copy.root))


def test_unreadable_chunks_are_reported_not_raised(tmp_path):
    from tests.conftest import make_dataset
    written = make_dataset(tmp_path / "ds", compression="gzip", events_per_video=20_000)
    path = fmt.events_path(written.root, "test", "vid_d")
    with h5py.File(path, "r") as h5:
        info = h5[fmt.KEY_Y].id.get_chunk_info(1)
    with open(path, "r+b") as f:
        f.seek(info.byte_offset)
        f.write(b"\x00garbage" * (info.size // 8))
    found = messages(check_dataset(written.root))
    assert any(m.startswith(f"{path}: cannot read the events") for m in found), found
