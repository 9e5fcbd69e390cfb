import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.events import EventFile
from dagr_lite.data.writer import VideoWriter, write_frame, write_labels
from dagr_lite.synth.dvs import preset
from dagr_lite.synth.video import (FolderSource, choose_dvs_model, downscale_area, emulate_video, linear_interpolate,
                                   list_frame_files, scale_boxes)


class RampSource:
    """A uniform frame brightening exponentially: log intensity rises by ``rate`` per frame."""

    def __init__(self, num_frames=5, rate=0.5, height=4, width=6):
        self.num_frames, self.rate, self.height, self.width = num_frames, rate, height, width
        self.calls = 0

    def _at(self, position):
        self.calls += 1
        return np.full((self.height, self.width, 3), 40.0 * np.exp(self.rate * position))

    def frame(self, k):
        return self._at(k)

    def between(self, k, alpha):
        return self._at(k + alpha)


class CountingWriter:
    def __init__(self):
        self.frames, self.events = [], []

    def add_frame(self, image):
        self.frames.append(image)

    def add_events(self, x, y, t, p):
        self.events.append(np.asarray(t))


@pytest.mark.parametrize("upsample", [1, 4, 41])
def test_upsampling_multiplies_emulator_steps(upsample):
    source, writer = RampSource(num_frames=5), CountingWriter()
    emulate_video(source, writer, params=preset("clean", sigma_threshold=0.0), upsample=upsample)
    assert len(writer.events) == 4 * upsample  # one emulator step per in-between frame and per frame
    assert len(writer.frames) == 5
    t = np.concatenate(writer.events)
    assert np.all(np.diff(t) >= 0) and t.min() >= 0 and t.max() < fmt.frame_time_us(4)
    # The same total change gives about the same number of events whatever the upsampling.
    assert len(t) == pytest.approx(4 * 0.5 / 0.2 * 24, rel=0.2)


def test_upsampled_video_is_time_sorted_with_consistent_timeidx(tmp_path):
    source = RampSource(num_frames=6, rate=0.3)
    with VideoWriter(tmp_path, "train", "ramp", num_frames=6, height=4, width=6) as writer:
        emulate_video(source, writer, params=preset("noisy"), upsample=7, seed=1)
    write_labels(tmp_path, {"ramp": {}})
    assert check_dataset(tmp_path) == []
    events = EventFile(fmt.events_path(tmp_path, "train", "ramp"), num_frames=6)
    t = events.read(0, events.num_events)["t"]
    np.testing.assert_array_equal(events.timeidx, fmt.expected_timeidx(t, 6))


def test_area_downscaling_and_box_scaling():
    frame = np.arange(4 * 6, dtype=float).reshape(4, 6)[..., None].repeat(3, axis=2)
    small = downscale_area(frame, 2)
    assert small.shape == (2, 3, 3)
    assert small[0, 0, 0] == np.mean([0, 1, 6, 7]) and small[1, 2, 1] == np.mean([16, 17, 22, 23])
    assert downscale_area(frame[:, :5], 2).shape == (2, 2, 3)  # the odd column is dropped
    boxes, kept = scale_boxes(np.array([[10, 20, 40, 8], [330, 10, 40, 40], [300, 10, 40, 40]]), 4, 30, 80)
    assert kept.tolist() == [True, False, True]
    np.testing.assert_allclose(boxes, [[2.5, 5, 10, 2], [75, 2.5, 5, 10]])  # the second falls outside: dropped; the third is clipped
    with pytest.raises(ValueError, match="scale"):
        downscale_area(frame, 0)


def test_linear_interpolation_and_folder_source(tmp_path):
    a, b = np.full((2, 2, 3), 10.0), np.full((2, 2, 3), 30.0)
    np.testing.assert_allclose(linear_interpolate(a, b, 0.25), np.full((2, 2, 3), 15.0))
    for number, value in ((1, 40), (2, 120), (3, 200)):
        write_frame(tmp_path / "v" / f"frame_{number:04d}.jpg", np.full((8, 12, 3), value, np.uint8))
    source = FolderSource(tmp_path / "v", scale=2)
    assert (source.num_frames, source.height, source.width) == (3, 4, 6)
    np.testing.assert_allclose(source.frame(1), 120, atol=2)
    np.testing.assert_allclose(source.between(0, 0.5), 80, atol=2)


def test_frame_folders_with_gaps_or_no_frames_are_refused(tmp_path):
    for number in (1, 2, 4):
        write_frame(tmp_path / "v" / f"frame_{number}.jpg", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DatasetFormatError, match="frame 3 is missing"):
        list_frame_files(tmp_path / "v")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetFormatError, match="no frames"):
        list_frame_files(tmp_path / "empty")


def test_mixed_model_draw_is_per_video_seeded_and_proportional():
    names = [f"video_{i}" for i in range(2000)]
    models = [choose_dvs_model(n, seed=0, clean_fraction=0.3) for n in names]
    assert models == [choose_dvs_model(n, seed=0, clean_fraction=0.3) for n in reversed(names)][::-1]
    assert models.count("clean") / len(models) == pytest.approx(0.3, abs=0.04)
    assert models != [choose_dvs_model(n, seed=1, clean_fraction=0.3) for n in names]
    assert {choose_dvs_model(n, clean_fraction=1.0) for n in names[:50]} == {"clean"}
