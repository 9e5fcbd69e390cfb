import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.labels import read_labels
from dagr_lite.data.writer import write_frame
from dagr_lite.synth.build import BUILD_INFO, LABEL_SOURCES, VERSIONS, main
from tests.synth.test_egohands import write_metadata
from tests.settings import sample_set

CONF = Path(__file__).resolve().parents[2] / "conf" / "dataset"


def write_moving_square_videos(folder, names, *, num_frames=6, height=24, width=32, first_number=0, pad=0,
                               size=8, step=3):
    """Frame folders of a bright square moving right over a dark background."""
    for v, name in enumerate(names):
        for k in range(num_frames):
            image = np.full((height, width, 3), 30, np.uint8)
            x = 2 + step * k + v
            image[6:6 + size, x:x + size] = 220
            write_frame(folder / name / f"frame_{k + first_number:0{pad}d}.jpg", image)


def test_how_each_version_is_made_has_one_owner():
    """The builder's table says how a version is made; its dataset config only reads it (the
    resolution its scale gives: tests/test_config.py)."""
    for version, settings in VERSIONS.items():
        conf = yaml.safe_load((CONF / f"{version}.yaml").read_text())
        assert not set(settings) & set(conf), version


def test_folder_input_builds_a_valid_dataset_with_scaled_labels(tmp_path):
    write_moving_square_videos(tmp_path / "frames", ["a", "b", "c"])
    labels = {fmt.label_key("a", k): [[2 + 3 * k, 6, 8, 8]] for k in range(6)}
    labels[fmt.label_key("b", 0)] = []
    (tmp_path / "labels.json").write_text(json.dumps(labels))
    (tmp_path / "splits.json").write_text(json.dumps({"train": ["a", "b"], "test": ["c"]}))
    out = tmp_path / "out"
    args = ["--frames", str(tmp_path / "frames"), "--out", str(out), "--preset", "mixed", "--upsample", "5",
            "--scale", "2", "--labels", str(tmp_path / "labels.json"), "--splits", str(tmp_path / "splits.json")]
    assert main(args) == 0
    assert check_dataset(out, decode_frames=True) == []
    ds = sample_set(out, "train", image_age=0, event_span="window")
    assert ds.videos == ["a", "b"] and ds.image_size == (12, 16)
    sample = next(ds[i] for i in range(len(ds)) if ds.sample_name(i) == ("a", 3))
    np.testing.assert_allclose(sample.boxes.numpy(), [[5.5, 3, 9.5, 7]])  # (11, 6, 19, 14) / 2
    assert len(sample_set(out, "test").videos) == 1
    info = json.loads((out / BUILD_INFO).read_text())
    assert {v["dvs_model"] for v in info["videos"].values()} <= {"clean", "noisy"}
    assert info["settings"]["upsample"] == 5 and info["videos"]["a"]["events"] > 0
    assert json.loads((out / LABEL_SOURCES).read_text())["a_frame_3"] == ["given"]
    # Events follow the moving square: between frames 2 and 3 it spans x 4..9.5, y 3..7 (scaled).
    events = sample.events.numpy()
    x, y = events[:, 0], events[:, 1]
    assert len(events) > 10
    region = (x >= 3) & (x <= 10) & (y >= 2) & (y <= 8)  # 8 x 7 of the 16 x 12 pixels
    assert region.mean() > 2 * (8 * 7) / (16 * 12)  # far denser than noise alone would be


def test_build_resumes_and_refuses_other_settings(tmp_path):
    write_moving_square_videos(tmp_path / "frames", ["a", "b"])
    out = tmp_path / "out"
    args = ["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v4", "--scale", "1"]
    assert main(args) == 0
    events_a = fmt.events_path(out, "train", "a")
    stamp = events_a.stat().st_mtime_ns
    fmt.events_path(out, "train", "b").unlink()  # as if the build had stopped inside video b
    (fmt.frames_dir(out, "train", "b") / "frame_5.jpg").unlink()
    assert main(args) == 0
    assert events_a.stat().st_mtime_ns == stamp  # a finished video is not redone
    assert check_dataset(out) == []
    assert main(args[:-2] + ["--scale", "2"]) == 2  # different settings: refused, nothing changed
    assert events_a.stat().st_mtime_ns == stamp


def test_the_builder_refuses_a_dataset_it_did_not_make_and_check_names_mixed_sizes(tmp_path, capsys):
    """An --out holding a release-format dataset without build_info.json is refused with nothing
    written; two datasets of different frame sizes put together are reported by check."""
    write_moving_square_videos(tmp_path / "frames", ["a"])
    out = tmp_path / "out"
    assert main(["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v4", "--scale", "1"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith(
        "note: no valid or test split; no labelled frame: train.py reads train and valid, evaluate.py test")
    (out / BUILD_INFO).unlink()  # as a dataset made elsewhere
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    write_moving_square_videos(tmp_path / "other", ["c"], height=12, width=16)
    assert main(["--frames", str(tmp_path / "other"), "--out", str(out), "--version", "v4", "--scale", "1"]) == 2
    assert f"{out}: holds a dataset this builder did not make (train, bounding_boxes.json, no {BUILD_INFO})" \
        in capsys.readouterr().err
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    mixed = tmp_path / "mixed"
    assert main(["--frames", str(tmp_path / "other"), "--out", str(mixed), "--version", "v4", "--scale", "1"]) == 0
    for video in ("a",):  # the 32x24 video joins the 16x12 one
        for part in (fmt.events_path(out, "train", video), fmt.frames_dir(out, "train", video)):
            target = mixed / part.relative_to(out)
            target.parent.mkdir(parents=True, exist_ok=True)
            part.rename(target)
    messages = [str(p) for p in check_dataset(mixed)]
    assert f"{mixed}: frames of 2 sizes (WxH): " in "".join(messages)
    assert any("32x24 (a)" in m and "16x12 (c)" in m for m in messages)


def test_egohands_input(tmp_path):
    names = ["CARDS_COURTYARD_B_T", "JENGA_OFFICE_S_T"]
    write_moving_square_videos(tmp_path / "frames", names, num_frames=8, height=720, width=1280, first_number=1,
                               pad=4, size=80, step=40)
    write_metadata(tmp_path / "metadata.mat", {
        names[0]: [(2, {"myleft": [[6, 7], [14, 14]]}), (6, {"myleft": [[18, 7], [26, 14]], "myright": [[1, 1], [3, 3]]})],
        names[1]: [(1, {"yourleft": [[2, 2], [10, 10]]})],
    })
    out = tmp_path / "out"
    assert main(["--egohands", str(tmp_path / "metadata.mat"), "--frames", str(tmp_path / "frames"),
                 "--out", str(out), "--version", "v2"]) == 0
    assert check_dataset(out) == []
    labels = read_labels(out)
    # v2 divides by 4: frame_num 2 -> frame index 1, MATLAB (6, 7)..(14, 14) -> (5.5, 6.5)..(13.5, 13.5) -> / 4.
    np.testing.assert_allclose(labels[names[0]][1], [[1.375, 1.625, 2, 1.75]])
    assert sorted(labels[names[0]]) == [1, 2, 3, 4, 5]
    assert len(labels[names[0]][3]) == 1  # myright is only in one labelled frame: not interpolated
    sources = json.loads((out / LABEL_SOURCES).read_text())
    assert sources[fmt.label_key(names[0], 3)] == ["interpolated"]
    assert sources[fmt.label_key(names[0], 5)] == ["annotated", "annotated"]


def test_bad_arguments_are_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--frames", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "clean"])
    assert "missing: --upsample, --scale" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a video")
    assert main(["--video", str(tmp_path / "notes.txt"), "--out", str(tmp_path / "o"), "--version", "v1"]) == 2
    assert "notes.txt: is not a video file the builder reads (by its suffix: .mp4," in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing written: a rerun with the right file is not refused
    assert main(["--frames", str(tmp_path / "none"), "--out", str(tmp_path / "o"), "--version", "v1"]) == 2
    assert "frames folder is missing" in capsys.readouterr().err
    write_moving_square_videos(tmp_path / "frames", ["a"])
    assert main(["--frames", str(tmp_path / "frames"), "--out", str(tmp_path / "o"), "--version", "v1",
                 "--dvs", "sigma=1"]) == 2
    assert "unknown DVS parameters ['sigma']" in capsys.readouterr().err
    for flag, value, message in (("--fps", "-30", "--fps must be a positive number"),
                                 ("--clean-fraction", "1.5", "--clean-fraction must lie in [0, 1]")):
        assert main(["--frames", str(tmp_path / "frames"), "--out", str(tmp_path / "bad"), "--version", "v1",
                     flag, value]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()  # nothing recorded before the settings are checked


def test_videos_without_events_are_left_out_with_a_warning(tmp_path):
    write_moving_square_videos(tmp_path / "frames", ["moving"])
    for k in range(4):  # a static video: the clean preset gives no events
        write_frame(tmp_path / "frames" / "static" / f"frame_{k}.jpg", np.full((24, 32, 3), 90, np.uint8))
    write_frame(tmp_path / "frames" / "single" / "frame_0.jpg", np.full((24, 32, 3), 90, np.uint8))
    labels = {fmt.label_key("static", 1): [[1, 1, 5, 5]], fmt.label_key("moving", 1): [[5, 6, 8, 8]]}
    (tmp_path / "labels.json").write_text(json.dumps(labels))
    out = tmp_path / "out"
    args = ["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v1",
            "--labels", str(tmp_path / "labels.json")]
    with pytest.warns(UserWarning) as caught:
        assert main(args) == 0
    assert {"no events", "frame(s)"} <= {w for m in caught for w in ("no events", "frame(s)") if w in str(m.message)}
    assert check_dataset(out) == []  # no leftover frames or labels of the skipped videos
    assert sample_set(out, "train").videos == ["moving"]
    info = json.loads((out / BUILD_INFO).read_text())
    assert set(info["skipped"]) == {"static", "single"}


def test_resume_refuses_a_new_split_and_replaces_stale_labels(tmp_path):
    write_moving_square_videos(tmp_path / "frames", ["a", "b"])
    out = tmp_path / "out"
    base = ["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v1"]
    first = {fmt.label_key("a", 2): [[5, 6, 8, 8]], fmt.label_key("b", 2): [[6, 6, 8, 8]]}
    (tmp_path / "l1.json").write_text(json.dumps(first))
    assert main(base + ["--labels", str(tmp_path / "l1.json")]) == 0
    fmt.events_path(out, "train", "b").unlink()  # b stopped half-way
    second = {fmt.label_key("a", 2): [[5, 6, 8, 8]], fmt.label_key("b", 4): [[12, 6, 8, 8]]}
    (tmp_path / "l2.json").write_text(json.dumps(second))
    assert main(base + ["--labels", str(tmp_path / "l2.json")]) == 0
    labels = read_labels(out)
    assert sorted(labels["b"]) == [4]  # b's old frame-2 label is gone
    sources = json.loads((out / LABEL_SOURCES).read_text())
    assert fmt.label_key("b", 2) not in sources and fmt.label_key("b", 4) in sources
    (tmp_path / "splits.json").write_text(json.dumps({"train": ["b"], "test": ["a"]}))
    assert main(base + ["--splits", str(tmp_path / "splits.json")]) == 2
    assert not fmt.frames_dir(out, "test", "a").exists()


def test_settings_are_recorded_before_the_first_video(tmp_path):
    write_moving_square_videos(tmp_path / "frames", ["a"])
    (tmp_path / "frames" / "a" / "frame_3.jpg").write_bytes(b"not a jpeg")
    out = tmp_path / "out"
    args = ["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v1"]
    assert main(args) == 2  # the corrupt frame stops the build, naming the file
    assert json.loads((out / BUILD_INFO).read_text())["settings"]["upsample"] == 1
    assert main(args[:-1] + ["v4"]) == 2  # nothing finished, yet other settings are refused


def test_label_sources_follow_the_boxes_that_survive_scaling(tmp_path):
    from dagr_lite.synth.build import VideoJob, _labels_at_scale
    from dagr_lite.synth.video import FolderSource
    write_moving_square_videos(tmp_path / "frames", ["a"])
    labels = {1: (np.array([[100.0, 0, 5, 5], [2, 2, 6, 6]]), ["annotated", "interpolated"])}
    job = VideoJob("a", "train", tmp_path / "frames" / "a", labels)
    boxes, sources = _labels_at_scale(job, FolderSource(job.frames, scale=2), 2)
    np.testing.assert_allclose(boxes[1], [[1, 1, 3, 3]])
    assert sources == {"a_frame_1": ["interpolated"]}


def test_egohands_frame_folders_must_count_from_one_at_full_size(tmp_path):
    write_metadata(tmp_path / "metadata.mat", {"V": [(1, {"myleft": [[6, 7], [14, 14]]})]})
    write_moving_square_videos(tmp_path / "f0", ["V"], num_frames=3, height=720, width=1280, first_number=0, pad=4)
    args = ["--egohands", str(tmp_path / "metadata.mat"), "--out", str(tmp_path / "o"), "--version", "v2"]
    assert main(args + ["--frames", str(tmp_path / "f0")]) == 2
    write_moving_square_videos(tmp_path / "small", ["V"], num_frames=3, height=36, width=64, first_number=1, pad=4)
    assert main(args + ["--frames", str(tmp_path / "small")]) == 2


def test_label_file_is_read_by_the_dataset_parser_and_errors_name_file_and_key(tmp_path):
    from dagr_lite.data.errors import DatasetFormatError
    from dagr_lite.data.labels import read_label_file
    from dagr_lite.synth.build import folder_jobs
    write_moving_square_videos(tmp_path / "frames", ["a", "b"])
    path = tmp_path / "labels.json"
    path.write_text(json.dumps({"a_frame_1": [[1, 2, 3, 4]], "a_frame_3": [], "b_frame_0": [[5, 5, 2.5, 2]]}))
    jobs = {job.name: job for job in folder_jobs(tmp_path / "frames", labels=path)}
    parsed = read_label_file(path)
    for video in ("a", "b"):
        assert sorted(jobs[video].labels) == sorted(parsed[video])
        for k, (boxes, sources) in jobs[video].labels.items():
            np.testing.assert_array_equal(boxes, parsed[video][k])
            assert sources == ["given"] * len(boxes)
    cases = [({"zz_frame_2": []}, r"labels\.json: zz_frame_2: key names no video of the frames folder"),
             ({"a_frame_1": [[1, 2, 3]]}, r"labels\.json: a_frame_1: expected a box \[x_tl, y_tl, w, h\] of 4 numbers"),
             ({"a_frame_01": []}, r"labels\.json: a_frame_01: key is not of the form <video>_frame_<k>"),
             ([1, 2], r"labels\.json: expected a JSON object keyed <video>_frame_<k>, found list")]
    for content, match in cases:
        path.write_text(json.dumps(content))
        with pytest.raises(DatasetFormatError, match=match):
            folder_jobs(tmp_path / "frames", labels=path)
    path.write_text("{oops")
    with pytest.raises(DatasetFormatError, match=r"labels\.json: cannot parse as JSON"):
        folder_jobs(tmp_path / "frames", labels=path)
    with pytest.raises(DatasetFormatError, match=r"none\.json: label file is missing"):
        folder_jobs(tmp_path / "frames", labels=tmp_path / "none.json")


def test_a_damaged_build_record_is_named(tmp_path, capsys):
    write_moving_square_videos(tmp_path / "frames", ["a"])
    out = tmp_path / "out"
    out.mkdir()
    (out / BUILD_INFO).write_text('{"settings": ')
    assert main(["--frames", str(tmp_path / "frames"), "--out", str(out), "--version", "v1"]) == 2
    assert f"{out / BUILD_INFO}: cannot parse as JSON" in capsys.readouterr().err
    (tmp_path / "splits.json").write_text("[]")
    assert main(["--frames", str(tmp_path / "frames"), "--out", str(tmp_path / "o2"), "--version", "v1",
                 "--splits", str(tmp_path / "splits.json")]) == 2
    assert "splits.json: expected a JSON object" in capsys.readouterr().err
