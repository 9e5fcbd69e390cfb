"""The event picture (the dense peer's input) against a per-event loop, and the dataset that reads it."""
import numpy as np
import pytest

from dagr_lite.data.dataset import (PICTURE_COUNT_FULL, CarryPicture, add_to_picture, carry_channels, channels_first,
                                    event_picture, picture_of, picture_state)
from dagr_lite.data.denoise import support_keep, support_keep_reference
from dagr_lite.synth.stub import stub_root
from tests.settings import sample_set


def _picture_by_loop(x, y, t, p, t_end, window, height, width, recent=0):
    on, off = np.zeros((height, width)), np.zeros((height, width))
    last = np.full((height, width), np.nan)
    for xi, yi, ti, pi in zip(x, y, t, p):
        (on if pi == 1 else off)[yi, xi] += 1
        last[yi, xi] = ti if np.isnan(last[yi, xi]) else max(last[yi, xi], ti)
    recency = np.where(np.isnan(last), 0.0, np.clip(1 - (t_end - np.nan_to_num(last)) / window, 0, 1) * 255)
    counts = [np.minimum(c, PICTURE_COUNT_FULL) * 255 / PICTURE_COUNT_FULL for c in (on, off)]
    channels = [*counts, recency]
    if recent:  # the recency over the recent window alone
        channels.append(np.where(np.isnan(last), 0.0, np.clip(1 - (t_end - np.nan_to_num(last)) / recent, 0, 1) * 255))
    return np.round(np.stack(channels, axis=2)).astype(np.uint8)


def test_event_picture_equals_a_per_event_loop():
    rng = np.random.default_rng(0)
    height, width, n = 9, 13, 2000
    x, y = rng.integers(0, width, n), rng.integers(0, height, n)
    t, p = np.sort(rng.integers(0, 30_000, n)), rng.integers(0, 2, n)
    got = event_picture(x, y, t, p, 30_000, 33_333, height, width)
    np.testing.assert_array_equal(got, _picture_by_loop(x, y, t, p, 30_000, 33_333, height, width))
    assert got[..., 0].max() == 255 and got[..., 1].max() == 255  # some pixel saturates at this density
    assert not event_picture(x[:0], y[:0], t[:0], p[:0], 0, 33_333, height, width).any()
    recent = event_picture(x, y, t, p, 30_000, 33_333, height, width, recent_us=4_000)
    np.testing.assert_array_equal(recent, _picture_by_loop(x, y, t, p, 30_000, 33_333, height, width, 4_000))
    np.testing.assert_array_equal(recent[..., :3], got)  # the fourth channel is added, the three unchanged
    assert (recent[..., 3] == 0).sum() > (got[..., 2] == 0).sum()  # older than the recent window: 0


def test_a_large_picture_in_pieces_equals_the_loop_ties_rounded_to_even():
    rng = np.random.default_rng(1)
    height, width, n = 30, 40, 6000
    x, y = rng.integers(0, width, n).astype(np.uint16), rng.integers(0, height, n).astype(np.uint16)
    t, p = np.sort(rng.integers(0, 90_000, n)), rng.integers(0, 2, n).astype(np.uint8)
    counts, last = picture_state(height, width)
    for piece in np.array_split(np.arange(n), 7):  # a stream's pieces
        add_to_picture(counts, last, x[piece], y[piece], t[piece], p[piece], width)
    got = picture_of(counts, last, 90_000, 90_000, height, width, 20_000)
    np.testing.assert_array_equal(got, _picture_by_loop(x, y, t, p, 90_000, 90_000, height, width, 20_000))
    ties = counts[0].reshape(height, width) == PICTURE_COUNT_FULL // 2  # 255 * 4 / 8 = 127.5
    assert ties.any() and (got[..., 0][ties] == 128).all()  # half to even


def test_a_dataset_with_the_event_picture_reads_the_window_not_the_frame():
    with pytest.raises(ValueError, match="event_span='window'"):
        sample_set(stub_root(), "valid", event_picture=True)
    frames = sample_set(stub_root(), "valid", event_span="window")
    pictures = sample_set(stub_root(), "valid", event_span="window", event_picture=True)
    for index in (0, 40):
        a, b = frames[index], pictures[index]
        np.testing.assert_array_equal(a.events.numpy(), b.events.numpy())  # the same sample's events
        e = b.events.numpy()
        expected = _picture_by_loop(e[:, 0].astype(int), e[:, 1].astype(int), e[:, 2] + b.t_image_us, e[:, 3],
                                    b.t_end_us, 33_333, 180, 320)
        np.testing.assert_array_equal(b.image.numpy().transpose(1, 2, 0), expected)
        assert not np.array_equal(a.image.numpy(), b.image.numpy())


def test_the_carry_picture_is_the_frame_beside_a_picture_of_every_event_since_the_image():
    plain = sample_set(stub_root(), "valid", image_age=(1, 10))
    carried = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=0)
    old = next(i for i in range(len(plain)) if plain[i].age_us > 4 * 33_333)  # an image older than the horizon
    for index in (3, old):
        a, b = plain[index], carried[index]
        assert b.image.shape == (6, 180, 320)
        np.testing.assert_array_equal(b.image[:3].numpy(), a.image.numpy())  # the camera frame
        np.testing.assert_array_equal(b.events.numpy(), a.events.numpy())  # the sample's own events stay
        v = carried.videos.index(b.video)
        raw = carried.events_of(v, b.t_image_us, b.t_end_us)  # every event since the image, not the horizon's
        expected = _picture_by_loop(raw["x"], raw["y"], raw["t"].astype(np.float64), raw["p"], b.t_end_us,
                                    b.t_end_us - b.t_image_us, 180, 320)
        np.testing.assert_array_equal(b.image[3:].numpy().transpose(1, 2, 0), expected)
    assert len(raw["t"]) > 2 * len(b.events)  # the picture reads events the horizon does not hold
    recent = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000)[old]
    assert recent.image.shape == (7, 180, 320)
    expected = _picture_by_loop(raw["x"], raw["y"], raw["t"].astype(np.float64), raw["p"], b.t_end_us,
                                b.t_end_us - b.t_image_us, 180, 320, 10_000)
    np.testing.assert_array_equal(recent.image[3:].numpy().transpose(1, 2, 0), expected)
    with pytest.raises(ValueError, match="choose one"):
        sample_set(stub_root(), "valid", event_span="window", event_picture=True, carry_picture=True)


def test_channels_first_is_the_concatenation_transposed():
    rng = np.random.default_rng(0)
    frame, picture = (rng.integers(0, 256, (18, 32, c), dtype=np.uint8) for c in (3, 4))
    for parts in ([frame], [frame, picture], [frame[:, :, :0], picture]):
        expected = np.ascontiguousarray(np.concatenate(parts, axis=2).transpose(2, 0, 1))
        got = channels_first(parts)
        assert got.flags.c_contiguous and got.dtype == np.uint8
        np.testing.assert_array_equal(got, expected)


def test_the_confirmed_channels_are_the_picture_of_the_events_a_neighbour_confirms():
    """:class:`CarryPicture`'s confirmed channels against the background-activity filter's brute-force
    rule, the events added in random pieces; an event before the image confirms and is not counted."""
    rng = np.random.default_rng(3)
    height, width, n, t_image, confirm = 11, 14, 3000, 20_000, 150
    x, y = rng.integers(0, width, n), rng.integers(0, height, n)
    t, p = np.sort(rng.integers(0, 60_000, n)) // 10 * 10, rng.integers(0, 2, n)  # ties at 10 us
    carry = CarryPicture(height, width, t_image, recent_us=4_000, confirm_us=confirm)
    assert carry.channels == carry_channels(4_000, confirm) == 7
    cuts = np.sort(rng.integers(0, n, 12))
    for piece in np.split(np.arange(n), cuts):
        carry.add(x[piece], y[piece], t[piece], p[piece])
    got = carry.picture(60_000)
    since = t >= t_image
    confirmed = support_keep_reference(x, y, t, confirm, width, height) & since
    assert 0.2 < confirmed.sum() / since.sum() < 0.9  # some events are confirmed, not all
    np.testing.assert_array_equal(got[..., :4], event_picture(x[since], y[since], t[since], p[since], 60_000, 40_000,
                                                              height, width, 4_000))
    np.testing.assert_array_equal(got[..., 4:], _picture_by_loop(x[confirmed], y[confirmed], t[confirmed],
                                                                 p[confirmed], 60_000, 40_000, height, width))
    plain = CarryPicture(height, width, t_image)  # without confirmation: the event picture since the image
    plain.add(x, y, t, p)
    assert plain.channels == 3 and carry_channels(0, 0) == 3
    np.testing.assert_array_equal(plain.picture(60_000), event_picture(x[since], y[since], t[since], p[since], 60_000,
                                                                       40_000, height, width))


def test_a_sample_with_confirmed_channels_reads_the_events_just_before_its_image():
    plain = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000)
    confirmed = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000,
                           carry_confirm_us=5_000)
    assert confirmed.sample.carry_confirm_us == 5_000
    for index in (3, 40):
        a, b = plain[index], confirmed[index]
        assert b.image.shape == (10, 180, 320)
        np.testing.assert_array_equal(b.image[:7].numpy(), a.image.numpy())  # the frame and the raw picture
        np.testing.assert_array_equal(b.events.numpy(), a.events.numpy())  # the graph reads every event
        v = confirmed.videos.index(b.video)
        raw = confirmed.events_of(v, b.t_image_us - 5_000, b.t_end_us)
        keep = support_keep(raw["x"], raw["y"], raw["t"], 5_000, 320, 180) & (raw["t"] >= b.t_image_us)
        assert 0 < keep.sum() < (raw["t"] >= b.t_image_us).sum()
        expected = _picture_by_loop(raw["x"][keep], raw["y"][keep], raw["t"][keep].astype(np.float64), raw["p"][keep],
                                    b.t_end_us, b.t_end_us - b.t_image_us, 180, 320)
        np.testing.assert_array_equal(b.image[7:].numpy().transpose(1, 2, 0), expected)
    with pytest.raises(ValueError, match="carry_confirm_us must be an integer >= 0, got -1"):
        sample_set(stub_root(), "valid", carry_picture=True, carry_confirm_us=-1)


def history_by_loop(x, y, t, t_image, t_end, bounds, height, width):
    """The span and onset channels by a plain loop over the events, per the definition: an event of
    time ``d`` after the image is in span ``k`` when ``bounds[k - 1] <= d < bounds[k]``; a count
    shows as 31 a count up to 8; the onset is ``round(1 + 254 f)`` for the first event's ``f``,
    its time since the image over the image's age."""
    spans = np.zeros((height, width, len(bounds) + 1), np.int64)
    first = {}
    for xi, yi, ti in zip(x, y, t):
        if ti < t_image:
            continue
        d = ti - t_image
        spans[yi, xi, sum(d >= b for b in bounds)] += 1
        first.setdefault((yi, xi), ti)
    picture = np.zeros((height, width, len(bounds) + 2), np.uint8)
    picture[..., :-1] = np.minimum(spans, 8) * 31
    for (yi, xi), ti in first.items():
        f = min(max((ti - t_image) / (t_end - t_image), 0.0), 1.0)
        picture[yi, xi, -1] = round(1 + 254 * f)
    return picture


def test_the_span_and_onset_channels_against_a_loop():
    """:class:`CarryPicture`'s channels of the counts per span of time since the image and of each
    pixel's first event, against a plain loop, the events added in random pieces (events before
    the image are not counted); a bound falls on an event's time; the channels follow the others."""
    rng = np.random.default_rng(5)
    height, width, n, t_image = 9, 12, 4000, 10_000
    x, y = rng.integers(0, width, n), rng.integers(0, height, n)
    t, p = np.sort(rng.integers(0, 300_000, n)), rng.integers(0, 2, n)
    t[n // 2] = t_image + 33_333  # an event on a bound is in the span it starts
    t = np.sort(t)
    bounds = (33_333, 66_667, 133_333)
    carry = CarryPicture(height, width, t_image, recent_us=10_000, spans_us=list(bounds), onset=True)
    assert carry.channels == carry_channels(10_000, 0, 0, bounds, True) == 4 + 4 + 1
    for piece in np.split(np.arange(n), np.sort(rng.integers(0, n, 15))):
        carry.add(x[piece], y[piece], t[piece], p[piece])
    got = carry.picture(300_000)
    since = t >= t_image
    np.testing.assert_array_equal(got[..., :4], event_picture(x[since], y[since], t[since], p[since], 300_000,
                                                              290_000, height, width, 10_000))
    expected = history_by_loop(x, y, t, t_image, 300_000, bounds, height, width)
    np.testing.assert_array_equal(got[..., 4:], expected)
    assert len(np.unique(got[..., 4:8])) > 3 and len(np.unique(got[..., 8])) > 20  # counts and onsets vary
    spans_only = CarryPicture(height, width, t_image, spans_us=[50_000])
    spans_only.add(x, y, t, p)
    assert spans_only.channels == 3 + 2 and spans_only.picture(300_000).shape == (height, width, 5)
    onset_only = CarryPicture(height, width, t_image, onset=True)
    onset_only.add(x, y, t, p)
    np.testing.assert_array_equal(onset_only.picture(300_000)[..., 3], expected[..., -1])
    for bad in ([0], [5, 5], [10, 3], "33333", [1.5]):
        with pytest.raises(ValueError, match="carry_spans_us must be a list of increasing positive integers"):
            CarryPicture(height, width, t_image, spans_us=bad)


def test_a_samples_carry_picture_holds_the_spans_and_onset_of_every_event_since_the_image():
    """The dataset's samples (what training, evaluation and the sweep read) hold the span and onset
    channels last, after the recent window, as the loop over the events since the image gives them."""
    bounds = (20_000, 60_000)
    carried = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000,
                         carry_spans_us=list(bounds), carry_onset=True)
    assert carried.sample.carry_spans_us == bounds and carried.sample.carry_onset
    old = next(i for i in range(len(carried)) if carried[i].age_us > 3 * 33_333)
    b = carried[old]
    assert b.image.shape == (3 + 4 + 3 + 1, 180, 320)
    raw = carried.events_of(carried.videos.index(b.video), b.t_image_us, b.t_end_us)
    expected = history_by_loop(raw["x"], raw["y"], raw["t"].astype(np.float64), b.t_image_us, b.t_end_us, bounds,
                               180, 320)
    np.testing.assert_array_equal(b.image[7:].numpy().transpose(1, 2, 0), expected)
    assert b.image[9].numpy().max() > 0  # the last span holds events: the image is older than 60 ms
