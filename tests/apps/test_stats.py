"""Dataset statistics against a brute-force count on a written dataset, and the pictures' files."""
import json
import re

import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.apps.stats import BIN_US, SIZE_EDGES, dataset_stats, main
from tests.conftest import make_dataset


def test_statistics_equal_a_brute_force_count(tmp_path):
    written = make_dataset(tmp_path / "data", num_frames=12, events_per_video=3000)
    stats = dataset_stats(written.root, tmp_path / "out", pictures=False)
    frame_end = fmt.frame_time_us(11) + int(1e6 / fmt.DEFAULT_FPS)
    for video, events in written.events.items():
        row = stats["videos"][video]
        inside = events["t"] < frame_end
        assert row["split"] == written.splits[video]
        assert row["events"] == int(inside.sum())
        assert row["events_after_last_frame"] == int((~inside).sum())
        assert row["on_fraction"] == pytest.approx(float(events["p"][inside].mean()))
        assert row["duration_s"] == pytest.approx(frame_end / 1e6)
        assert row["mean_rate"] == pytest.approx(inside.sum() / (frame_end / 1e6))
        peak = np.bincount(events["t"][inside] // BIN_US).max() / (BIN_US / 1e6)
        assert row["peak_rate"] == pytest.approx(peak)
        labels = written.labels[video]
        assert row["frames"] == 12 and row["labelled_frames"] == len(labels)
        assert row["boxes"] == sum(len(b) for b in labels.values())
    train = [v for v, s in written.splits.items() if s == "train"]
    assert stats["splits"]["train"]["events"] == sum(stats["videos"][v]["events"] for v in train)
    sizes = np.concatenate([np.sqrt(b[:, 2] * b[:, 3]) for v in written.labels for b in written.labels[v].values()
                            if len(b)])
    assert stats["box_size_histogram"]["counts"] == np.histogram(sizes, bins=SIZE_EDGES)[0].tolist()
    assert json.loads((tmp_path / "out" / "stats.json").read_text()) == json.loads(json.dumps(stats))


def test_pictures_and_index_for_chosen_videos(tmp_path):
    written = make_dataset(tmp_path / "data", num_frames=8, events_per_video=2000)
    video = sorted(written.events)[0]
    dataset_stats(written.root, tmp_path / "out", videos=[video], frame=4)
    names = [f"event_rate_{video}.png", f"event_frame_{video}_4.png", f"overlay_{video}_4.png",
             f"presets_{video}_4.png"]
    index = (tmp_path / "out" / "index.html").read_text()
    for name in names:
        assert (tmp_path / "out" / name).stat().st_size > 1000 and name in index
    with pytest.raises(ValueError, match="not in the dataset"):
        dataset_stats(written.root, tmp_path / "other", videos=["nope"])


def test_a_frame_past_the_video_or_an_earlier_out_is_refused_before_writing(tmp_path, capsys):
    written = make_dataset(tmp_path / "data", num_frames=8, events_per_video=2000)
    video = sorted(written.events)[0]
    with pytest.raises(SystemExit):
        main([str(written.root), "--out", str(tmp_path / "late"), "--videos", video, "--frame", "500"])
    assert re.fullmatch(rf"error: --frame 500: past the end of {video} \(8 frames\); give a frame below 8",
                        capsys.readouterr().err.splitlines()[-1])  # after the progress bar
    assert not (tmp_path / "late").exists()
    main([str(written.root), "--out", str(tmp_path / "out"), "--videos", video, "--frame", "4"])
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out").iterdir()}
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main([str(written.root), "--out", str(tmp_path / "out"), "--videos", video, "--frame", "2"])
    assert re.search(r"holds earlier statistics \(stats\.json\); choose a new --out", capsys.readouterr().err)
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out").iterdir()} == before
