import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.dataset import EventEgoHands
from dagr_lite.data.reader import read_labels
from dagr_lite.data.writer import write_frame
from dagr_lite.synth.build import BUILD_INFO, LABEL_SOURCES, VERSIONS, main
from tests.synth.test_egohands import write_metadata

CONF = Path(__file__).resolve().parents[2] / "conf" / "dataset"


def write_moving_square_videos(folder, names, *, num_frames=6, height=24, width=32, first_number=0, pad=0):
    """Frame folders of a bright square moving right over a dark background."""
    for v, name in enumerate(names):
        for k in range(num_frames):
            image = np.full((height, width, 3), 30, np.uint8)
            x = 2 + 3 * k + v
            image[6:14, x:x + 8] = 220
            write_frame(folder / name / f"frame_{k + first_number:0{pad}d}.jpg", image)


def test_versions_agree_with_the_dataset_configs():
    for version, settings in VERSIONS.items():
        conf = yaml.safe_load((CONF / f"{version}.yaml").read_text())
        assert {key: conf[key] for key in settings} == settings


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
    ds = EventEgoHands(out, "train", image_lag=0)
    assert ds.videos == ["a", "b"] and ds.image_size == (12, 16)
    sample = next(ds[i] for i in range(len(ds)) if ds.sample_name(i) == ("a", 3))
    np.testing.assert_allclose(sample.boxes.numpy(), [[5.5, 3, 9.5, 7]])  # (11, 6, 19, 14) / 2
    assert len(EventEgoHands(out, "test").videos) == 1
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


def test_egohands_input(tmp_path):
    names = ["CARDS_COURTYARD_B_T", "JENGA_OFFICE_S_T"]
    write_moving_square_videos(tmp_path / "frames", names, num_frames=8, height=36, width=64, first_number=1, pad=4)
    write_metadata(tmp_path / "metadata.mat", {
        names[0]: [(2, {"myleft": [[6, 7], [14, 14]]}), (6, {"myleft": [[18, 7], [26, 14]], "myright": [[1, 1], [3, 3]]})],
        names[1]: [(1, {"yourleft": [[2, 2], [10, 10]]})],
    })
    out = tmp_path / "out"
    assert main(["--egohands", str(tmp_path / "metadata.mat"), "--frames", str(tmp_path / "frames"),
                 "--out", str(out), "--version", "v3"]) == 0
    assert check_dataset(out) == []
    labels = read_labels(out)
    # v3 halves the resolution: frame_num 2 -> frame index 1, MATLAB (6, 7)..(14, 14) -> (5.5, 6.5)..(13.5, 13.5).
    np.testing.assert_allclose(labels[names[0]][1], [[2.75, 3.25, 4, 3.5]])
    assert sorted(labels[names[0]]) == [1, 2, 3, 4, 5]
    assert len(labels[names[0]][3]) == 1  # myright is only in one labelled frame: not interpolated
    sources = json.loads((out / LABEL_SOURCES).read_text())
    assert sources[fmt.label_key(names[0], 3)] == ["interpolated"]
    assert sources[fmt.label_key(names[0], 5)] == ["annotated", "annotated"]


def test_bad_arguments_are_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--frames", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "clean"])
    assert "missing: upsample, scale" in capsys.readouterr().err
    assert main(["--frames", str(tmp_path / "none"), "--out", str(tmp_path / "o"), "--version", "v1"]) == 2
    assert "frames folder is missing" in capsys.readouterr().err
    write_moving_square_videos(tmp_path / "frames", ["a"])
    assert main(["--frames", str(tmp_path / "frames"), "--out", str(tmp_path / "o"), "--version", "v1",
                 "--dvs", "sigma=1"]) == 2
    assert "unknown DVS parameters ['sigma']" in capsys.readouterr().err
