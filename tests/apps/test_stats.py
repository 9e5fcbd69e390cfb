"""Dataset statistics against a brute-force count on a written dataset, and the pictures' files."""
import json
import re

import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.apps.stats import BIN_US, SIZE_EDGES, dataset_stats, main, stale_labels
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
    assert stats["box_size_histogram"]["edges_px"] == [*SIZE_EDGES[:-1], None]  # the last bin open, not 1e9 px
    assert json.loads((tmp_path / "out" / "stats.json").read_text()) == json.loads(json.dumps(stats))


def test_stale_labels_by_hand():
    """A 20x20 box moving 4 px a frame: a frame old, it overlaps by 16x20 (IoU 320 / 480 = 2/3, a
    hit at 0.5, 0.55, 0.6 and 0.65 of the ten COCO thresholds); two frames old by 12x20 (IoU
    240 / 560 = 0.43, a miss)."""
    moving = {k: np.array([[4.0 * k, 10.0, 20.0, 20.0]]) for k in range(12)}
    still = {k: np.array([[100.0, 50.0, 30.0, 30.0]]) for k in range(12)}
    stale = stale_labels({"a": moving}, ["a"], ages=(1, 2))
    assert stale[1] == {"frames": 10, "AP50": 1.0, "mAP": pytest.approx(0.4)}
    assert stale[2]["AP50"] == 0.0 and stale[2]["mAP"] == 0.0
    both = stale_labels({"a": moving, "b": still}, ["a", "b"], ages=(2,))
    # every answer scores 1: recall reaches 0.5 only with all 20 answers, at precision 0.5, so of
    # COCO's 101 recall points the 51 up to 0.5 read 0.5 and the rest 0
    assert both[2]["frames"] == 20 and both[2]["AP50"] == pytest.approx(0.5 * 51 / 101)
    # the hand is hidden at frame 5 (labelled, no box): frame 4's box is a false answer there and
    # frame 6 gets none; in image order 4 hits, the false answer, 5 hits, so precision is 1 up to
    # recall 0.4 (41 of COCO's 101 points) and 0.9 up to 0.9 (50 points)
    hidden = {k: np.zeros((0, 4)) if k == 5 else moving[k] for k in range(12)}
    once = stale_labels({"a": hidden}, ["a"], ages=(1,))[1]
    assert once["frames"] == 11 and once["AP50"] == pytest.approx((41 + 0.9 * 50) / 101)


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


def test_a_missing_root_is_named_as_missing(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nothere"), "--out", str(tmp_path / "out")])
    assert capsys.readouterr().err == f"error: {tmp_path / 'nothere'}: no such dataset folder or recording file\n"
    assert not (tmp_path / "out").exists()
