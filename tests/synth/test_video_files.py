"""Video files in: decoded with PyAV as they are emulated, frame rate from the container."""
import json

import av
import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.synth.build import BUILD_INFO, main
from dagr_lite.synth.video import VideoFileSource
from tests.settings import sample_set


def moving_square(k: int, height: int = 48, width: int = 64) -> np.ndarray:
    frame = np.full((height, width, 3), 40, np.uint8)
    x = 4 + 3 * k
    frame[14:30, x:x + 14] = (230, 190, 150)
    return frame


def write_video(path, frames: int, fps: int = 25) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=fps)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.options = {"qscale": "2"}
        for k in range(frames):
            for packet in stream.encode(av.VideoFrame.from_ndarray(moving_square(k), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_frames_are_decoded_in_order_and_on_demand(tmp_path):
    write_video(tmp_path / "clip.mp4", frames=10)
    source = VideoFileSource(tmp_path / "clip.mp4")
    assert source.num_frames == 10 and (source.height, source.width) == (48, 64)
    for k in (0, 1, 5, 9, 2):  # forward, then back (decoding starts again)
        assert np.abs(source.frame(k).astype(int) - moving_square(k)).mean() < 6  # a lossy codec
    halfway = source.between(2, 0.5)
    assert np.allclose(halfway, (source.frame(2).astype(float) + source.frame(3)) / 2, atol=1)
    source.close()


def test_build_from_video_files_takes_their_frame_rate(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    write_video(videos / "clip_a.mp4", frames=12)
    write_video(videos / "clip_b.avi", frames=9)
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps({"clip_a_frame_3": [[10, 14, 14, 16]]}))
    out = tmp_path / "out"
    assert main(["--video", str(videos / "clip_a.mp4"), str(videos / "clip_b.avi"), "--out", str(out),
                 "--preset", "clean", "--upsample", "3", "--scale", "1", "--labels", str(labels)]) == 0
    info = json.loads((out / BUILD_INFO).read_text())
    assert info["settings"]["fps"] == 25 and set(info["videos"]) == {"clip_a", "clip_b"}
    assert check_dataset(out, fps=25) == []
    dataset = sample_set(out, "train", fps=25, image_age=1)
    assert len(dataset) == (12 - 1) + (9 - 1)
    assert dataset.frame_time_us(0, 5) == fmt.frame_time_us(5, 25)
    sample = dataset[2]  # clip_a, label frame 3
    assert sample.boxes.tolist() == [[10, 14, 24, 30]] and len(sample.events) > 0


def test_a_file_that_is_no_video_is_named(tmp_path, capsys):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"this is not a video" * 50)
    with pytest.raises(DatasetFormatError, match="broken.mp4"):
        VideoFileSource(bad)
    assert main(["--video", str(bad), "--out", str(tmp_path / "out"), "--version", "v2"]) == 2
    assert "broken.mp4" in capsys.readouterr().err
