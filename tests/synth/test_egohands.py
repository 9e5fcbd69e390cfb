import numpy as np
import pytest
import scipy.io

from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.synth.egohands import (default_split, interpolate_labels, load_metadata, polygon_to_box,
                                      VideoAnnotations)


def test_polygon_to_box_converts_matlab_coordinates_and_clips():
    # MATLAB pixel centres (1, 1)..(11, 21) -> continuous 0.5..10.5 and 0.5..20.5.
    box = polygon_to_box([[1, 1], [11, 5], [4, 21]], height=720, width=1280)
    np.testing.assert_allclose(box, [0.5, 0.5, 10, 20])
    np.testing.assert_allclose(polygon_to_box([[1270, 700], [1300, 800]], 720, 1280), [1269.5, 699.5, 10.5, 20.5])
    assert polygon_to_box(np.zeros((0, 2))) is None
    assert polygon_to_box([[2000, 5], [2100, 9]], 720, 1280) is None  # wholly outside


def write_metadata(path, videos):
    """videos: {video_id: [(frame_num, {hand: (N, 2) points})]} in EgoHands' metadata.mat structure."""
    hands = ("myleft", "myright", "yourleft", "yourright")
    video = np.empty((1, len(videos)), dtype=[("video_id", "O"), ("labelled_frames", "O")])
    for i, (vid, frames) in enumerate(videos.items()):
        labelled = np.empty((1, len(frames)), dtype=[("frame_num", "O")] + [(h, "O") for h in hands])
        for j, (num, polys) in enumerate(frames):
            labelled[0, j]["frame_num"] = num
            for h in hands:
                labelled[0, j][h] = np.asarray(polys.get(h, np.zeros((0, 2))), dtype=float)
        video[0, i]["video_id"] = vid
        video[0, i]["labelled_frames"] = labelled
    scipy.io.savemat(path, {"video": video})


def test_metadata_parsing(tmp_path):
    path = tmp_path / "metadata.mat"
    write_metadata(path, {
        "CARDS_COURTYARD_B_T": [(11, {"myleft": [[101, 201], [151, 261]], "yourright": [[501, 101], [601, 141]]}),
                                (36, {})],
        "CHESS_OFFICE_H_S": [(1, {"myright": [[11, 11], [21, 31], [15, 41]]})],
    })
    videos = load_metadata(path)
    assert sorted(videos) == ["CARDS_COURTYARD_B_T", "CHESS_OFFICE_H_S"]
    cards = videos["CARDS_COURTYARD_B_T"].frames
    assert sorted(cards) == [10, 35]  # 1-based frame_num -> 0-based frame index
    np.testing.assert_allclose(cards[10]["myleft"], [100.5, 200.5, 50, 60])
    np.testing.assert_allclose(cards[10]["yourright"], [500.5, 100.5, 100, 40])
    assert cards[35] == {}
    np.testing.assert_allclose(videos["CHESS_OFFICE_H_S"].frames[0]["myright"], [10.5, 10.5, 10, 30])


def test_metadata_errors_name_the_file_and_key(tmp_path):
    with pytest.raises(DatasetFormatError, match="metadata file is missing"):
        load_metadata(tmp_path / "none.mat")
    scipy.io.savemat(tmp_path / "other.mat", {"something": np.zeros(3)})
    with pytest.raises(DatasetFormatError, match=r"other\.mat: video: expected a struct array"):
        load_metadata(tmp_path / "other.mat")


def test_interpolation_only_between_frames_where_the_hand_is_in_both():
    a = {"myleft": np.array([0.0, 0, 10, 10]), "myright": np.array([50.0, 50, 10, 10])}
    b = {"myleft": np.array([10.0, 20, 20, 10])}
    labels = interpolate_labels(VideoAnnotations("v", {2: a, 6: b}), num_frames=10)
    assert sorted(labels) == [2, 3, 4, 5, 6]  # nothing before the first or after the last labelled frame
    boxes, sources = labels[2]
    assert len(boxes) == 2 and sources == ["annotated", "annotated"]
    boxes, sources = labels[4]  # halfway: corners (0,0)-(10,10) and (10,20)-(30,30)
    np.testing.assert_allclose(boxes, [[5, 10, 15, 10]])
    assert sources == ["interpolated"]
    assert labels[6][1] == ["annotated"]


def test_default_split_is_30_10_8_and_fixed():
    names = [f"V{i:02d}" for i in range(48)]
    split = default_split(names)
    assert [len(split[s]) for s in ("train", "valid", "test")] == [30, 10, 8]
    assert sorted(sum(split.values(), [])) == names
    assert default_split(list(reversed(names))) == split
    with pytest.raises(ValueError, match="add up"):
        default_split(names[:10])


def test_default_split_of_the_48_videos_is_pinned():
    # The split of a built dataset must never change: these are the videos of seed 0.
    split = default_split([f"V{i:02d}" for i in range(48)])
    assert split["valid"] == ["V07", "V09", "V12", "V13", "V26", "V32", "V38", "V39", "V40", "V42"]
    assert split["test"] == ["V05", "V14", "V15", "V29", "V31", "V33", "V41", "V47"]
