"""The sweep over image ages: matching and interpolating boxes, shared frames, outputs."""
import csv
import json
import math

import numpy as np
import pytest

from dagr_lite.config import ConfigError, compose_config
from dagr_lite.engine.train import train
from dagr_lite.apps.sweep import (SweepSamples, curve_points, interpolate_boxes, match_boxes, moved_recall, sweep,
                                  sweep_frames, sweep_points)
from dagr_lite.synth.stub import stub_root
from tests.settings import sample_set


def test_boxes_are_matched_one_to_one_by_overlap():
    a = np.array([[0, 0, 10, 10], [50, 50, 70, 70]], np.float32)
    b = np.array([[52, 51, 72, 71], [1, 0, 11, 10]], np.float32)  # the same hands, listed the other way round
    assert match_boxes(a, b).tolist() == [1, 0]
    assert match_boxes(a, b[:1]) is None  # a hand left: the frames do not match
    assert match_boxes(a, np.array([[0, 0, 10, 10], [90, 90, 99, 99]], np.float32)) is None  # no overlap
    assert match_boxes(np.zeros((0, 4)), np.zeros((0, 4))).tolist() == []


def test_interpolated_boxes_by_hand():
    a = np.array([[0, 0, 10, 10], [50, 50, 70, 70]], np.float32)
    b = np.array([[54, 52, 74, 76], [2, 0, 14, 10]], np.float32)
    # 0.25 of the way: first hand (0,0,10,10) -> (2,0,14,10); second (50,50,70,70) -> (54,52,74,76)
    expected = np.array([[0.5, 0, 11, 10], [51, 50.5, 71, 71.5]], np.float32)
    np.testing.assert_allclose(interpolate_boxes(a, b, 0.25), expected, atol=1e-6)
    np.testing.assert_allclose(interpolate_boxes(a, b, 0.0), a)
    with pytest.raises(ValueError, match="do not match"):
        interpolate_boxes(a, b[:1], 0.5)


def test_every_age_scores_the_same_frames_with_events_since_its_image():
    dataset = sample_set(stub_root(), "valid", image_age=7, first_frame=7, max_events=None)
    frames = sweep_frames(dataset, 7, between=0)
    assert frames and all(k >= 7 for _, k in frames)
    assert len(frames) == sum(dataset.num_frames(v) - 7 for v in range(len(dataset.videos)))
    named = None
    for age in (1, 3, 7):
        samples = SweepSamples(dataset, frames, age, 0.0, seed=0)
        got = [(s.video, s.frame, s.image_frame) for s in (samples[i] for i in range(0, len(samples), 9))]
        assert all(image == k - age for _, k, image in got)
        names = [(video, k) for video, k, _ in got]
        assert named is None or names == named
        named = names
    between = sweep_frames(dataset, 7, between=10)
    assert set(between) <= set(frames) and between  # only frames whose boxes match the next frame's
    sample = SweepSamples(dataset, between, 2, 0.5, seed=0)[0]
    v, k = between[0]
    t_k, t_next = dataset.frame_time_us(v, k), dataset.frame_time_us(v, k + 1)
    assert sample.t_end_us == t_k + round(0.5 * (t_next - t_k)) and sample.image_frame == k - 2
    assert sample.events[:, 2].max() + sample.t_image_us < sample.t_end_us
    assert sample.events[:, 2].max() + sample.t_image_us >= t_k  # events past frame k come in


def test_moved_and_still_recall_by_hand():
    truth = np.array([[0, 0, 10, 10], [50, 50, 60, 60], [100, 100, 110, 110]], np.float32)
    before = np.array([[1, 0, 11, 10], [80, 80, 90, 90]], np.float32)  # the first still (IoU 90/110), two moved
    boxes = np.array([[0, 0, 10, 10], [50, 52, 60, 62], [100, 100, 110, 110]], np.float32)  # IoU 1, 80/120, 1
    scores = np.array([0.9, 0.6, 0.2])  # the third under the operating score
    entries = [("a", 180, 320, truth, boxes, scores),
               ("b", 180, 320, truth[:1], boxes[:0], scores[:0]),  # no box in the image's frame: moved, not found
               ("c", 180, 320, truth[:0], boxes, scores)]  # no hand: counts nowhere
    images = [before, before[:0], before]
    assert moved_recall(entries, images, score=0.5) == {"recall_moved": 1 / 3, "recall_still": 1.0,
                                                        "num_moved": 3, "num_still": 1}
    assert moved_recall(entries[1:], images[1:], score=0.5) == {"recall_moved": 0.0, "recall_still": None,
                                                                "num_moved": 1, "num_still": 0}


def test_points_cover_ages_and_in_between_times():
    assert sweep_points([1, 3], 0) == [(1, 0.0), (3, 0.0)]
    assert sweep_points([2], 4) == [(2, 0.0), (2, 0.25), (2, 0.5), (2, 0.75)]


def test_the_sweep_writes_its_table_plot_and_rows(tmp_path, capsys, monkeypatch):
    ckpts = []
    for variant in ("image_only", "events_only"):
        train(compose_config("train", [f"run_dir={tmp_path / variant}", f"model={variant}", "trainer.max_steps=1", "trainer.schedule_by=steps",
                                       "loader.batch_size=4", "loader.num_workers=0", "data.window_us=15000",
                                       "trainer.image_every=0", "trainer.val_samples=4"]))
        ckpts.append(str(tmp_path / variant / "checkpoints" / "last.pt"))
    out = tmp_path / "sweep"
    result = sweep(compose_config("sweep", [f"ckpt=[{ckpts[0]},{ckpts[1]}]", "split=valid", "ages=[1,4]",
                                            "between=2", f"out={out}", "loader.num_workers=0"]))
    rows = json.loads((out / "sweep.json").read_text())["results"]
    assert len(rows) == 2 * 2 * 2 and rows == result["results"]
    assert {r["model"] for r in rows} == {"image_only", "events_only"}
    assert sorted({r["age_frames"] for r in rows}) == [1, 1.5, 4, 4.5]
    assert {type(r["age_frames"]) for r in rows if r["age_frames"] in (1, 4)} == {int}  # a label frame's age is whole
    assert [r["age_ms"] for r in rows if r["age_frames"] == 1.5] == [50.0] * 2
    assert {r["age_ms"] for r in rows if r["age_frames"] == 1} == {33.333}  # rounded to the microsecond
    assert len({r["num_images"] for r in rows}) == 1  # the same frames everywhere
    for r in rows:  # every hand is moved or still since the image, and found or not
        assert r["num_moved"] + r["num_still"] > 0
        assert all(r[key] is None or 0 <= r[key] <= 1 for key in ("recall_moved", "recall_still"))
    with open(out / "sweep.csv") as handle:
        assert len(list(csv.DictReader(handle))) == len(rows)
    assert (out / "sweep.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "AP50" in printed and "image_only image_only/last.pt" in printed  # each run named by its folder
    assert f"wrote {out / 'sweep.json'}, sweep.csv and sweep.png" in printed
    assert json.loads((out / "sweep.json").read_text())["overrides"] == {}
    with pytest.raises(FileExistsError, match="earlier sweep"):
        sweep(compose_config("sweep", [f"ckpt=[{ckpts[0]}]", f"out={out}"]))
    # a sweep that fails on its plot leaves no sweep.json: the rerun into the same folder is not refused
    import dagr_lite.apps.sweep as sweep_module

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sweep_module, "plot_sweep", full_disk)
    again_args = [f"ckpt={ckpts[0]}", "split=valid", "ages=[1]", f"out={tmp_path / 'again'}", "loader.num_workers=0"]
    # (one checkpoint without brackets: a list of one)
    with pytest.raises(OSError, match="No space"):
        sweep(compose_config("sweep", again_args))
    assert not (tmp_path / "again" / "sweep.json").exists()
    monkeypatch.undo()
    sweep(compose_config("sweep", again_args))
    assert (tmp_path / "again" / "sweep.json").is_file()
    # nothing to score: refused with the frames that exist, and nothing written
    with pytest.raises(ConfigError, match=r"no label frame k >= 100 \(the largest of ages=\[1, 100\]\) in split "
                                          r"valid: its videos have \d+ to \d+ frames; give smaller ages"):
        sweep(compose_config("sweep", [f"ckpt=[{ckpts[0]}]", "split=valid", "ages=[1,100]", f"out={tmp_path / 'none'}",
                                       "loader.num_workers=0"]))
    assert not (tmp_path / "none").exists()
    # a picture the model was not trained on: refused by its key before anything is written
    with pytest.raises(ConfigError, match=r"data\.carry_picture=True changes the model's input"):
        sweep(compose_config("sweep", [f"ckpt=[{ckpts[0]}]", "split=valid", "ages=[1]", f"out={tmp_path / 'pic'}",
                                       "loader.num_workers=0", "data.carry_picture=true"]))
    assert not (tmp_path / "pic").exists()
    # a truncated checkpoint after a good one: refused by name before anything is scored
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(open(ckpts[1], "rb").read()[:5000])
    scored = []
    monkeypatch.setattr(sweep_module, "score_point", lambda *args, **kwargs: scored.append(1))
    with pytest.raises(ValueError, match=f"{truncated}: cannot read as a dagr_lite checkpoint"):
        sweep(compose_config("sweep", [f"ckpt=[{ckpts[0]},{truncated}]", "split=valid", "ages=[1]",
                                       f"out={tmp_path / 'truncated'}", "loader.num_workers=0"]))
    assert scored == [] and not (tmp_path / "truncated").exists()
    monkeypatch.undo()
    # data.* given on the command line replace a checkpoint's own settings, printed and recorded.
    capsys.readouterr()
    built, real_build = [], sweep_module.build_dataset

    def recording_build(cfg, *args, **kwargs):
        dataset = real_build(cfg, *args, **kwargs)
        built.append(dataset.window_us)
        return dataset

    monkeypatch.setattr(sweep_module, "build_dataset", recording_build)
    again = sweep(compose_config("sweep", [f"ckpt=[{ckpts[1]}]", "split=valid", "ages=[1]", f"out={tmp_path / 'cap'}",
                                           "loader.num_workers=0", "data.window_us=10000", "data.context_us=10000"]))
    expected = {ckpts[1]: {"data.window_us": {"checkpoint": 15000, "used": 10000}}}  # context_us: the same as trained
    assert again["overrides"] == expected
    assert json.loads((tmp_path / "cap" / "sweep.json").read_text())["overrides"] == expected
    assert "window_us=10000 (trained with 15000)" in capsys.readouterr().out
    assert built == [10000]  # the samples were made with the override


def test_a_curve_is_broken_where_nothing_was_measured():
    """With in-between points, ages that are not next to each other are not joined by a line (a NaN
    between them); next ones are; a recall of None (no such hand) is NaN; rows come in age order."""
    def row(frames, value):
        return {"age_frames": frames, "age_ms": round(frames * 100 / 3, 3), "AP50": value, "recall_moved": None}

    rows = [row(4.5, 0.3), row(1, 0.6), row(1.5, 0.5), row(4, 0.4), row(2, 0.45)]
    xs, ys = curve_points(rows, "AP50", between=2)
    assert [None if math.isnan(y) else y for y in ys] == [0.6, 0.5, 0.45, None, 0.4, 0.3]  # 2 -> 4: broken
    assert math.isnan(xs[3]) and xs[:3] == [33.333, 50.0, 66.667] and xs[4:] == [133.333, 150.0]
    assert curve_points(rows, "AP50", between=0)[1] == [0.6, 0.5, 0.45, 0.4, 0.3]  # whole ages only: one line
    assert all(math.isnan(y) for y in curve_points(rows, "recall_moved", between=2)[1])
    assert curve_points([row(1, -1.0)], "AP50", between=0) == ([33.333], [0.0])  # COCO's -1 drawn at 0
    thirds = [row(round(a + j / 3, 6), 0.5) for a in (1, 2, 4) for j in range(3)]  # ages rounded as the sweep's
    assert sum(math.isnan(x) for x in curve_points(thirds, "AP50", between=3)[0]) == 1  # only 2.67 -> 4
