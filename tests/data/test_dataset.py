import json

import h5py
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from dagr_lite.data import format as fmt
from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import SampleTooLarge, draw_age, ramped_high, refractory_keep, sample_start_us
from dagr_lite.data.denoise import support_keep_reference
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.frames import read_frame
from dagr_lite.data.writer import write_frame
from tests.conftest import make_dataset
from tests.settings import sample_set


def test_sample_matches_brute_force(dataset):
    ds = sample_set(dataset.root, "train", image_age=2, event_span="window", window_us=50_000)
    assert ds.videos == ["CARDS_COURTYARD_B_T", "vid_b"]
    assert len(ds) == 2 * (12 - 2)  # frames k < image_age give no sample
    for index in range(len(ds)):
        sample = ds[index]
        video, k = ds.sample_name(index)
        assert (sample.video, sample.frame, sample.image_frame) == (video, k, k - 2)
        raw = dataset.events[video]
        t_end = fmt.frame_time_us(k)
        mask = (raw["t"] >= t_end - 50_000) & (raw["t"] < t_end)
        t_image = fmt.frame_time_us(k - 2)
        expected = np.stack([raw["x"][mask], raw["y"][mask], raw["t"][mask] - t_image, raw["p"][mask]], 1)
        np.testing.assert_array_equal(sample.events.numpy(), expected.astype(np.float32))
        assert (sample.t_start_us, sample.t_end_us, sample.t_image_us) == (t_end - 50_000, t_end, t_image)
        image = read_frame(fmt.frame_path(dataset.root, "train", video, k - 2))
        np.testing.assert_array_equal(sample.image.permute(1, 2, 0).numpy(), image)
        boxes = dataset.labels[video].get(k, np.zeros((0, 4))).reshape(-1, 4)
        np.testing.assert_allclose(sample.boxes.numpy(), fmt.xywh_to_xyxy(boxes), atol=1e-3)
        assert sample.boxes.dtype == torch.float32 and sample.labels.tolist() == [0] * len(boxes)


@pytest.mark.parametrize("event_span", ["window", "image"])
def test_a_graph_context_adds_the_earlier_events_which_the_batch_marks_not_pooled(dataset, event_span):
    ds = sample_set(dataset.root, "train", image_age=3, event_span=event_span, window_us=20_000, context_us=30_000,
                    graph_context_us=25_000)
    assert ds.sample.graph_context_us == 25_000
    for index in (0, 5, 9):
        sample = ds[index]
        video, k = ds.sample_name(index)
        raw, t_end, t_image = dataset.events[video], fmt.frame_time_us(k), fmt.frame_time_us(k - 3)
        image_floor = t_image - 30_000 if event_span == "image" else -np.inf  # by hand: none from before it
        start = max(t_end - 20_000, image_floor)
        graph = max(t_end - 45_000, image_floor)
        mask = (raw["t"] >= graph) & (raw["t"] < t_end)
        np.testing.assert_array_equal(sample.events[:, 2].numpy(), (raw["t"][mask] - t_image).astype(np.float32))
        assert sample.t_start_us == start
        pooled = collate([sample]).pooled()
        own = raw["t"][mask] >= start
        assert own.all() if pooled is None else np.array_equal(pooled.numpy(), own)
        assert not own.all() or event_span == "image"  # the window-span samples hold a context


def test_frames_without_boxes_are_samples_with_zero_boxes(dataset):
    ds = sample_set(dataset.root, "valid", image_age=0)
    by_frame = {ds.sample_name(i)[1]: ds[i] for i in range(len(ds))}
    assert set(by_frame) == set(range(12))
    assert by_frame[1].boxes.shape == (0, 4)  # labelled with an empty list
    assert by_frame[3].boxes.shape == (0, 4)  # no key at all
    assert by_frame[2].boxes.shape[0] >= 1


def test_max_events_guards_and_never_thins(dataset):
    full = sample_set(dataset.root, "train", image_age=3)
    sizes = [len(full[i].events) for i in range(len(full))]
    limit = sorted(sizes)[len(sizes) // 2]
    guarded = sample_set(dataset.root, "train", image_age=3, max_events=limit)
    for index, size in enumerate(sizes):
        if size <= limit:
            assert torch.equal(guarded[index].events, full[index].events)  # whole, never thinned
        else:
            video, k = guarded.sample_name(index)
            with pytest.raises(SampleTooLarge, match=rf"{video}\.h5: the sample of frame {k} \(image frame {k - 3}\) "
                                                     rf"holds {size} events in .* more than max_events={limit}; "
                                                     r"shorten the horizon \(data\.window_us\)"):
                guarded[index]


def brute_refractory(x, y, t, refractory_us):
    """Each event against every earlier one at its pixel (hand-written, quadratic)."""
    return np.array([not np.any((x[:i] == x[i]) & (y[:i] == y[i]) & (t[:i] > t[i] - refractory_us))
                     for i in range(len(t))], dtype=bool)


def test_the_refractory_filter_matches_brute_force_whole_and_in_chunks():
    rng = np.random.default_rng(0)
    n = 3000
    x, y = rng.integers(0, 5, n), rng.integers(0, 4, n)
    t = np.sort(rng.integers(0, 40_000, n)) // 7 * 7  # several events per pixel and microsecond
    for refractory_us in (1, 100, 1000):
        expected = brute_refractory(x, y, t, refractory_us)
        assert 0 < expected.sum() < n
        np.testing.assert_array_equal(refractory_keep(x, y, t, refractory_us, width=5), expected)
        last = np.full(5 * 4, -np.inf)
        cuts = np.sort(rng.integers(0, n, 12))
        chunks = [refractory_keep(x[a:b], y[a:b], t[a:b], refractory_us, 5, last)
                  for a, b in zip([0, *cuts], [*cuts, n])]
        np.testing.assert_array_equal(np.concatenate(chunks), expected)  # a stream's state, chunk by chunk
    # by hand: pixel (0, 0) at 0, 0 (same microsecond), 50, 100 and 260 with a period of 100
    keep = refractory_keep(np.zeros(5, int), np.zeros(5, int), np.array([0, 0, 50, 100, 260]), 100, width=1)
    assert keep.tolist() == [True, False, False, False, True]  # 100 - 50 < 100: the dropped event counts
    assert refractory_keep(np.zeros(0, int), np.zeros(0, int), np.zeros(0), 10, width=1).shape == (0,)


@pytest.mark.parametrize("age", [1, 4])
@pytest.mark.parametrize(("refractory_us", "support_us"), [(2_000, 0), (500, 3_000)])
def test_a_filtered_sample_is_the_filtered_stream_in_its_horizon(tmp_path, age, refractory_us, support_us):
    """The arrival filters (the refractory period; with it the background-activity filter) each decide
    on every event of the stream, and a sample holds the events they keep in its horizon (read
    from the longer period before it)."""
    written = make_dataset(tmp_path, videos={"v": "train"}, events_per_video=20_000, compression=None)
    raw = written.events["v"]
    whole = brute_refractory(raw["x"], raw["y"], raw["t"], refractory_us)  # the filters over the whole stream
    if support_us:
        whole &= support_keep_reference(raw["x"], raw["y"], raw["t"], support_us, 64, 48)  # the written frames' size
    assert 0 < whole.sum() < len(whole)
    ds = sample_set(tmp_path, "train", image_age=age, refractory_us=refractory_us, support_us=support_us,
                    context_us=5_000)
    assert ds.sample.support_us == support_us
    for index in range(len(ds)):
        sample = ds[index]
        _, k = ds.sample_name(index)
        t_image, t_end = fmt.frame_time_us(k - age), fmt.frame_time_us(k)
        mask = whole & (raw["t"] >= sample_start_us(t_end, 33_333, t_image, 5_000)) & (raw["t"] < t_end)
        expected = np.stack([raw["x"][mask], raw["y"][mask], raw["t"][mask] - t_image, raw["p"][mask]], 1)
        np.testing.assert_array_equal(sample.events.numpy(), expected.astype(np.float32))
    for key in ("refractory_us", "support_us"):
        with pytest.raises(ValueError, match=f"{key} must be >= 0"):
            sample_set(tmp_path, "train", **{key: -1})


def test_the_sample_start_by_hand():
    # every model: the last window_us; with an image, nothing from before t_image - context_us
    assert sample_start_us(100_000, 33_333) == 66_667
    assert sample_start_us(100_000, 33_333, t_image_us=90_000, context_us=10_000) == 80_000  # image 10 ms old
    assert sample_start_us(100_000, 33_333, t_image_us=30_000, context_us=10_000) == 66_667  # image 70 ms old
    assert sample_start_us(100_000, 33_333, t_image_us=100_000, context_us=0) == 100_000  # age 0, no context


def test_window_with_no_events_gives_zero_events(tmp_path):
    written = make_dataset(tmp_path, videos={"v": "train"}, num_frames=6, events_per_video=1)
    t_event = int(written.events["v"]["t"][0])
    ds = sample_set(tmp_path, "train", image_age=0, event_span="window", window_us=1000)
    for i in range(len(ds)):
        sample = ds[i]
        inside = sample.t_start_us <= t_event < sample.t_end_us
        assert sample.events.shape == ((1, 4) if inside else (0, 4))


def test_a_frameless_set_holds_the_same_samples_without_the_frame(dataset):
    framed = sample_set(dataset.root, "train", image_age=(1, 3))
    frameless = sample_set(dataset.root, "train", image_age=(1, 3), frames=False)
    for index in range(0, len(framed), 3):
        a, b = framed[index], frameless[index]
        assert b.image.shape == (0, *a.image.shape[1:]) and (b.height, b.width) == (a.height, a.width)
        assert torch.equal(a.events, b.events) and torch.equal(a.boxes, b.boxes)
        assert (a.image_frame, a.t_start_us, a.t_end_us, a.t_image_us) == (b.image_frame, b.t_start_us, b.t_end_us,
                                                                            b.t_image_us)


def test_build_dataset_skips_the_frames_for_a_frameless_model_in_training_alone():
    from dagr_lite.config import build_dataset, compose_config

    cfg = compose_config("train", ["model=events_only"])
    assert not build_dataset(cfg, "valid", train=True, with_image=False).frames
    assert build_dataset(cfg, "valid", train=False, with_image=False).frames  # evaluation draws the frame
    assert build_dataset(compose_config("train", []), "valid", train=True, with_image=True).frames


def test_loader_workers_reopen_files(dataset):
    ds = sample_set(dataset.root, "train")
    ds[0]  # open the file in the main process first: workers must not reuse that handle
    loader = DataLoader(ds, batch_size=4, num_workers=2, collate_fn=collate)
    batches = list(loader)
    assert sum(len(b) for b in batches) == len(ds)
    first = collate([ds[i] for i in range(4)])
    assert torch.equal(batches[0].events, first.events)


def test_an_event_file_reads_the_same_through_its_kept_arrays_and_after_pickling(dataset):
    import pickle

    ds = sample_set(dataset.root, "train")
    first = ds[3]
    again = pickle.loads(pickle.dumps(ds))[3]  # a worker's copy opens the file afresh
    assert torch.equal(first.events, again.events) and torch.equal(ds[3].events, first.events)
    ds._events[0].close()
    assert torch.equal(ds[3].events, first.events)  # reopened after a close


def test_new_epochs_reach_loader_workers(dataset):
    from dagr_lite.engine.loading import make_loader
    ds = sample_set(dataset.root, "train", image_age=(1, 4), seed=0)  # the epoch draws the image ages
    loader = make_loader(ds, batch_size=8, num_workers=2)
    first = next(iter(loader)).events
    assert torch.equal(next(iter(loader)).events, first)
    ds.set_epoch(1)
    assert not torch.equal(next(iter(loader)).events, first)


def test_epoch_index_pairs_draw_as_that_epoch(dataset):
    """``ds[(epoch, i)]`` is ``ds[i]`` after ``set_epoch(epoch)``, through loader workers too."""
    from dagr_lite.engine.loading import make_loader
    ds = sample_set(dataset.root, "train", image_age=(1, 4), seed=0)
    for epoch in (0, 3):
        for i in range(len(ds)):
            ds.set_epoch(epoch)
            by_epoch = ds[i]
            ds.set_epoch(5)  # the pair's epoch wins over the shared one
            by_pair = ds[(epoch, i)]
            assert by_pair.image_frame == by_epoch.image_frame
            assert np.array_equal(by_pair.events, by_epoch.events)
    pairs = [(epoch, i) for epoch in (0, 3) for i in range(4)]
    loaded = list(make_loader(ds, batch_size=4, num_workers=2, sampler=pairs))
    for b, epoch in enumerate((0, 3)):
        assert torch.equal(loaded[b].events, collate([ds[(epoch, i)] for i in range(4)]).events)
    assert not torch.equal(loaded[0].events, loaded[1].events)


def test_missing_split_folder(dataset):
    with pytest.raises(DatasetFormatError, match=r"valid: split folder is missing"):
        sample_set(dataset.root / "nowhere", "valid")


def test_frame_count_disagreeing_with_timeidx(dataset_copy):
    frames = fmt.frames_dir(dataset_copy.root, "train", "vid_b")
    (frames / "frame_11.jpg").unlink()
    with pytest.raises(DatasetFormatError, match=r"vid_b\.h5: timeidx: has 12 entries but 11 frames exist on disk"):
        sample_set(dataset_copy.root, "train")
    (frames / "frame_5.jpg").unlink()
    with pytest.raises(DatasetFormatError, match=r"frames/vid_b: frames are not numbered 0\.\.9: frame_5\.jpg is missing"):
        sample_set(dataset_copy.root, "train")


def test_events_file_with_no_events(dataset_copy):
    path = fmt.events_path(dataset_copy.root, "test", "vid_d")
    with h5py.File(path, "a") as h5:
        for key in fmt.EVENT_KEYS:
            del h5[key]
            h5[key] = np.zeros(0, np.int64)
        h5[fmt.KEY_TIMEIDX][...] = 0
    with pytest.raises(DatasetFormatError, match=r"vid_d\.h5: events/t: the file holds no events"):
        sample_set(dataset_copy.root, "test")


def test_corrupt_jpeg_names_the_file(dataset_copy):
    ds = sample_set(dataset_copy.root, "valid", image_age=1)
    path = fmt.frame_path(dataset_copy.root, "valid", "vid_c", 4)
    path.write_bytes(path.read_bytes()[:200])
    index = [ds.sample_name(i)[1] for i in range(len(ds))].index(5)
    with pytest.raises(DatasetFormatError, match=r"vid_c/frame_4\.jpg: cannot decode image"):
        ds[index]


def test_configured_size_must_match_the_frames(dataset):
    with pytest.raises(DatasetFormatError, match=r"frame_0\.jpg: frame is 64x48 \(WxH\), expected 640x360 as the dataset is configured"):
        sample_set(dataset.root, "train", image_size=(360, 640))
    assert sample_set(dataset.root, "train").image_size == (48, 64)


def test_bad_boxes_are_refused_or_clipped(dataset_copy):
    path = fmt.labels_path(dataset_copy.root)
    labels = json.loads(path.read_text())
    labels["vid_c_frame_2"] = [[60, 40, 10, 10], [5, 5, -1, 3]]
    path.write_text(json.dumps(labels))
    with pytest.raises(DatasetFormatError, match=r"vid_c_frame_2: box \[60.0, 40.0, 10.0, 10.0\] leaves the 64x48 image"):
        sample_set(dataset_copy.root, "valid")
    ds = sample_set(dataset_copy.root, "valid", image_age=0, clip_boxes=True)
    sample = ds[2]
    assert sample.frame == 2
    np.testing.assert_allclose(sample.boxes.numpy(), [[60, 40, 64, 48]])


@pytest.mark.parametrize("kwargs,match", [(dict(image_age=-1), "image_age"), (dict(window_us=0), "window_us"),
                                          (dict(max_events=0), "max_events"), (dict(videos=["nope"]), "nope")])
def test_bad_arguments(dataset, kwargs, match):
    with pytest.raises(ValueError, match=match):
        sample_set(dataset.root, "train", **kwargs)


def test_polarity_outside_0_1_stops_the_dataset(tmp_path):
    written = make_dataset(tmp_path / "small", compression=None)
    path = fmt.events_path(written.root, "train", "vid_b")
    with h5py.File(path, "a") as h5:
        h5[fmt.KEY_P][100] = 2
    with pytest.raises(DatasetFormatError, match=r"vid_b\.h5: events/p: values must be 0 or 1, found 2 at index 100 "):
        sample_set(written.root, "train")
    # In a longer file the opening check samples only the ends; the window holding the value raises.
    written = make_dataset(tmp_path / "long", videos={"v": "train"}, events_per_video=30_000, compression=None)
    path = fmt.events_path(written.root, "train", "v")
    with h5py.File(path, "a") as h5:
        h5[fmt.KEY_P][15_000] = 2
    ds = sample_set(written.root, "train", image_age=0, event_span="window")
    with pytest.raises(DatasetFormatError, match=r"v\.h5: events/p: values must be 0 or 1, found 2 at index 15000 "):
        for index in range(len(ds)):
            ds[index]


def test_frame_problems_stop_the_dataset_when_it_opens(dataset_copy):
    root = dataset_copy.root
    frame = fmt.frame_path(root, "valid", "vid_c", 7)
    frame.write_bytes(frame.read_bytes()[:300])  # cut inside the image data
    with pytest.raises(DatasetFormatError, match=r"vid_c/frame_7\.jpg: not a readable JPEG: no end-of-image marker"):
        sample_set(root, "valid")
    small = fmt.frame_path(root, "test", "vid_d", 9)
    small.unlink()
    write_frame(small, np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(DatasetFormatError, match=r"vid_d/frame_9\.jpg: frame is 10x10 \(WxH\), expected 64x48 as "
                                                 r"frame_0\.jpg$"):
        sample_set(root, "test")
    with pytest.raises(DatasetFormatError, match=r"vid_d/frame_0\.jpg: frame is 64x48 \(WxH\), expected 10x10 as the "
                                                 r"dataset is configured"):
        sample_set(root, "test", image_size=(10, 10))
    header = fmt.frame_path(root, "train", "vid_b", 3)
    header.write_bytes(header.read_bytes()[:100])
    with pytest.raises(DatasetFormatError, match=r"vid_b/frame_3\.jpg: not a readable JPEG: .*truncated header"):
        sample_set(root, "train")
    assert len(sample_set(root, "train", videos=["CARDS_COURTYARD_B_T"])) == 11  # the other video opens


def test_frame_size_must_agree_across_videos(dataset_copy):
    root = dataset_copy.root
    for k in range(12):
        path = fmt.frame_path(root, "train", "vid_b", k)
        path.unlink()
        write_frame(path, np.zeros((48, 60, 3), np.uint8))
    first = fmt.frame_path(root, "train", "CARDS_COURTYARD_B_T", 0)
    with pytest.raises(DatasetFormatError) as info:
        sample_set(root, "train")
    lines = str(info.value).splitlines()
    assert lines[0] == f"{fmt.frame_path(root, 'train', 'vid_b', 0)}: frame is 60x48 (WxH), expected 64x48 as {first}"
    assert len(lines) == 11 and lines[-1].endswith("vid_b: ... and 2 more frame problems in this folder")


@pytest.mark.parametrize("age,window_us", [(1, 33_333), (3, 33_333), (5, 33_333), (3, 200_000), (1, 35_000)])
def test_events_of_the_horizon_since_the_image_match_a_brute_force_time_mask(dataset, age, window_us):
    ds = sample_set(dataset.root, "train", image_age=age, context_us=7_000, window_us=window_us)
    assert len(ds) == 2 * (12 - age)
    for index in range(len(ds)):
        sample = ds[index]
        video, k = ds.sample_name(index)
        t_image, t_end = fmt.frame_time_us(k - age), fmt.frame_time_us(k)
        raw = dataset.events[video]
        # hand-written: not older than the horizon, nor than 7 ms before the image
        mask = (raw["t"] >= t_image - 7_000) & (raw["t"] >= t_end - window_us) & (raw["t"] < t_end)
        expected = np.stack([raw["x"][mask], raw["y"][mask], raw["t"][mask] - t_image, raw["p"][mask]], 1)
        np.testing.assert_array_equal(sample.events.numpy(), expected.astype(np.float32))
        assert (sample.image_frame, sample.t_image_us, sample.t_end_us) == (k - age, t_image, t_end)
        assert sample.age_us == t_end - t_image


def test_training_draws_ages_from_the_range_per_sample(dataset):
    ds = sample_set(dataset.root, "train", image_age=(1, 4))
    assert len(ds) == 2 * (12 - 1)  # a frame k draws from [1, min(4, k)]
    drawn = {}
    for epoch in range(6):
        ds.set_epoch(epoch)
        for index in range(len(ds)):
            sample = ds[index]
            age = sample.frame - sample.image_frame
            assert 1 <= age <= min(4, sample.frame)
            drawn.setdefault(sample.frame, set()).add(age)
    assert drawn[11] == {1, 2, 3, 4} and drawn[1] == {1}
    ds.set_epoch(2)
    again = [ds[i].image_frame for i in range(len(ds))]
    assert again == [ds[i].image_frame for i in range(len(ds))]  # same seed and epoch, same ages


@pytest.mark.parametrize("power", [1.0, 2.5])
def test_weighted_ages_follow_their_weights(power):
    low, high, draws = 2, 7, 60_000
    rng = np.random.default_rng(3)
    counts = np.bincount([draw_age(rng, low, high, power) for _ in range(draws)], minlength=high + 1)
    weights = np.array([(a - low + 1) ** power for a in range(low, high + 1)])  # hand-written law
    expected = draws * weights / weights.sum()
    assert counts[:low].sum() == 0
    # each count within 5 standard deviations of its binomial expectation (seeded: no flakes)
    sd = np.sqrt(expected * (1 - weights / weights.sum()))
    assert np.all(np.abs(counts[low:] - expected) < 5 * sd)
    assert draw_age(rng, 4, 4, power) == 4 and draw_age(rng, 4, 3, power) == 4


def test_unweighted_ages_are_the_uniform_draws(dataset):
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    assert [draw_age(a, 1, 10) for _ in range(50)] == b.integers(1, 11, 50).tolist()
    uniform = sample_set(dataset.root, "train", image_age=(1, 6))
    linear = sample_set(dataset.root, "train", image_age=(1, 6), age_power=1.0)
    ages = [[ds[i].frame - ds[i].image_frame for i in range(len(ds))] for ds in (uniform, linear)]
    assert ages[0] != ages[1] and all(1 <= a <= 6 for a in ages[1])
    with pytest.raises(ValueError, match="age_power must be a number >= 0, got -1"):
        sample_set(dataset.root, "train", image_age=(1, 6), age_power=-1)


def test_an_age_ramp_lets_the_long_ages_in_epoch_by_epoch(dataset):
    assert [ramped_high(1, 6, 2, e) for e in range(4)] == [3, 5, 6, 6]  # hand-computed
    assert ramped_high(1, 6, 0, 0) == 6 and ramped_high(2, 2, 3, 0) == 2
    ramped = sample_set(dataset.root, "train", image_age=(1, 6), age_ramp=2)
    plain = sample_set(dataset.root, "train", image_age=(1, 6))
    for epoch, top in enumerate([3, 5, 6]):
        ages = [ramped[(epoch, i)].frame - ramped[(epoch, i)].image_frame for i in range(len(ramped))]
        assert 1 <= min(ages) and max(ages) == top  # the epoch's top is drawn, no age above it
    # once the ramp is over, the ramped set draws exactly what the plain one draws
    assert ([ramped[(2, i)].image_frame for i in range(len(ramped))]
            == [plain[(2, i)].image_frame for i in range(len(plain))])
    with pytest.raises(ValueError, match=r"age_ramp must be an integer >= 0 \(frames an epoch; 0: no ramp\), got -1"):
        sample_set(dataset.root, "train", image_age=(1, 6), age_ramp=-1)


@pytest.mark.parametrize("image_age", [-1, (3, 1), (1, 2, 3), 1.5])
def test_bad_image_ages_are_refused(dataset, image_age):
    with pytest.raises(ValueError, match="image_age"):
        sample_set(dataset.root, "train", image_age=image_age)
