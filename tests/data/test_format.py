import numpy as np
import pytest

from dagr_lite.data import format as fmt


def test_frame_time_formula_hand_computed():
    assert fmt.frame_time_us(0) == 0
    assert fmt.frame_time_us(1) == 33333  # 33333.33 rounds down
    assert fmt.frame_time_us(2) == 66667  # 66666.67 rounds up
    assert fmt.frame_time_us(3) == 100000
    assert fmt.frame_time_us(2699) == 89966667
    assert fmt.frame_time_us(5, fps=25) == 200000
    np.testing.assert_array_equal(fmt.frame_time_us(np.arange(4)), [0, 33333, 66667, 100000])
    assert isinstance(fmt.frame_time_us(7), int)


def test_expected_timeidx_is_first_event_at_or_after_frame_time():
    t = np.array([0, 0, 10, 33332, 33333, 33333, 70000])
    np.testing.assert_array_equal(fmt.expected_timeidx(t, 4), [0, 4, 6, 7])


def test_frame_names_have_no_zero_padding():
    assert fmt.frame_name(7) == "frame_7.jpg"
    assert fmt.parse_frame_name("frame_12.jpg") == 12
    assert fmt.parse_frame_name("frame_0.jpg") == 0
    for bad in ("frame_012.jpg", "frame_1.png", "frame_.jpg", "frame_1.jpg.tmp", "xframe_1.jpg"):
        assert fmt.parse_frame_name(bad) is None


def test_label_keys_round_trip_with_underscores_in_video_names():
    key = fmt.label_key("CARDS_COURTYARD_B_T", 41)
    assert key == "CARDS_COURTYARD_B_T_frame_41"
    assert fmt.parse_label_key(key) == ("CARDS_COURTYARD_B_T", 41)
    assert fmt.parse_label_key("a_frame_b_frame_3") == ("a_frame_b", 3)
    assert fmt.parse_label_key("CARDS_frame_03") is None
    assert fmt.parse_label_key("CARDS") is None


def test_paths_follow_the_release_layout(tmp_path):
    assert fmt.events_path(tmp_path, "train", "v") == tmp_path / "train" / "events" / "v.h5"
    assert fmt.frame_path(tmp_path, "test", "v", 3) == tmp_path / "test" / "frames" / "v" / "frame_3.jpg"
    assert fmt.labels_path(tmp_path) == tmp_path / "bounding_boxes.json"


@pytest.mark.parametrize("xywh,xyxy", [([[1, 2, 3, 4]], [[1, 2, 4, 6]]), ([[0.5, 0, 10, 0.25]], [[0.5, 0, 10.5, 0.25]])])
def test_box_conversions(xywh, xyxy):
    np.testing.assert_allclose(fmt.xywh_to_xyxy(xywh), xyxy)
    np.testing.assert_allclose(fmt.xyxy_to_xywh(xyxy), xywh)
    assert fmt.xywh_to_xyxy(np.zeros((0, 4))).shape == (0, 4)


def test_truncating_frame_times_are_the_reference_loaders_expression():
    k = np.arange(2700)
    reference = np.array([int(1e6 * ((1 / 30) * int(i))) for i in k])
    truncated = fmt.frame_time_us(k, 30, "truncate")
    np.testing.assert_array_equal(truncated, reference)
    assert all(fmt.frame_time_us(int(i), 30, "truncate") == reference[i] for i in (0, 1, 2, 1349, 2699))
    assert isinstance(fmt.frame_time_us(7, 30, "truncate"), int)
    rounded = fmt.frame_time_us(k, 30, "round")
    differing = np.flatnonzero(rounded != truncated)
    assert len(differing) == 960 and differing[-1] == 2699
    assert set((rounded - truncated).tolist()) == {0, 1}
    assert (rounded[2699], truncated[2699]) == (89966667, 89966666)
    np.testing.assert_array_equal(fmt.differing_frames(2700, 30), differing)
    np.testing.assert_array_equal(fmt.frame_time_us(k), rounded)  # round is the default, the one written
    assert fmt.WRITTEN_CONVENTION == "round" and fmt.FRAME_TIME_CONVENTIONS == ("round", "truncate")
    with pytest.raises(ValueError, match="convention must be one of"):
        fmt.frame_time_us(3, 30, "floor")


def test_expected_timeidx_follows_the_convention():
    t = np.array([0, 33333, 66666, 66666, 66667, 99999, 100000])  # frame 2: 66667 (round), 66666 (truncate)
    np.testing.assert_array_equal(fmt.expected_timeidx(t, 4), [0, 1, 4, 6])
    np.testing.assert_array_equal(fmt.expected_timeidx(t, 4, convention="round"), [0, 1, 4, 6])
    np.testing.assert_array_equal(fmt.expected_timeidx(t, 4, convention="truncate"), [0, 1, 2, 6])
