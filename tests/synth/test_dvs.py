import math

import numpy as np
import pytest

from dagr_lite.synth.dvs import DVSEmulator, DVSParams, lin_log, preset, rgb_to_luma


def run(emulator, frames, dt_us=1000.0):
    """Step through frames (the first resets); all events concatenated."""
    emulator.reset(frames[0], 0.0)
    parts = [emulator.step(f, dt_us * (i + 1)) for i, f in enumerate(frames[1:])]
    return {k: np.concatenate([p[k] for p in parts]) for k in "xytp"}


def test_lin_log_is_linear_below_20_log_above_and_continuous():
    x = np.array([0.0, 10.0, 20.0, 100.0])
    np.testing.assert_allclose(lin_log(x), [0.0, 10 * math.log(20) / 20, math.log(20), math.log(100)])
    eps = 1e-9
    assert abs(lin_log(np.array([20 - eps]))[0] - lin_log(np.array([20 + eps]))[0]) < 1e-8


def test_luma_uses_bt601_weights():
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255]]], np.uint8)
    np.testing.assert_allclose(rgb_to_luma(rgb), [[0.299 * 255, 0.587 * 255, 0.114 * 255]])


def test_constant_image_gives_no_events_with_the_clean_preset():
    frames = [np.full((16, 20, 3), 120.0)] * 30
    events = run(DVSEmulator(16, 20, preset("clean"), seed=0), frames)
    assert len(events["t"]) == 0


def test_log_rise_of_one_gives_exactly_five_on_events_inside_the_interval():
    emulator = DVSEmulator(1, 1, preset("clean", sigma_threshold=0.0), seed=0)
    emulator.reset(np.full((1, 1), 100.0), 0.0)
    events = emulator.step(np.full((1, 1), 100.0 * math.e), 1000.0)  # log intensity +1.0
    assert events["p"].tolist() == [1] * 5
    # Where the level crosses 0.2, 0.4, ..., 1.0; the last, due at the step's very end, inside it.
    assert events["t"].tolist() == [200, 400, 600, 800, 999]
    # The remainder carries over: +0.1 more gives nothing, +0.1 again gives one more event.
    assert len(emulator.step(np.full((1, 1), 100.0 * math.exp(1.1)), 2000.0)["t"]) == 0
    assert emulator.step(np.full((1, 1), 100.0 * math.exp(1.2)), 3000.0)["p"].tolist() == [1]


def crossing_times_by_search(start, end, threshold, t0, dt_us, samples=200_001):
    """Reference: walk the difference ``start -> end`` linearly over the step on a fine grid and
    note the first sample at or past each whole threshold in its direction (us, floored)."""
    sign = 1.0 if end > 0 else -1.0
    f = np.linspace(0.0, 1.0, samples)
    d = sign * (start + f * (end - start))
    times = []
    for k in range(1, int(math.floor(abs(end) / threshold + 1e-9)) + 1):
        reached = np.nonzero(d >= k * threshold - 1e-12)[0]
        times.append(math.floor(t0 + f[reached[0]] * dt_us))
    return times


def test_events_sit_where_the_linear_level_crosses_each_threshold():
    """Pixels that rise, fall, reverse, leak and start mid-way: each event's time is the moment the
    difference, linear across the step, reaches it (a brute-force search over the step)."""
    theta = 0.2
    params = preset("clean", sigma_threshold=0.0, leak_rate_hz=0.0)
    rng = np.random.default_rng(7)
    for _ in range(20):
        first = rng.uniform(30, 200, (3, 5))
        second = first * np.exp(rng.uniform(-1.3, 1.3, (3, 5)))
        third = second * np.exp(rng.uniform(-1.3, 1.3, (3, 5)))
        emulator = DVSEmulator(3, 5, params, seed=0)
        emulator.reset(first, 0.0)
        for frame, t_end in ((second, 1000.0), (third, 3500.0)):
            t0 = emulator.t_us
            start = emulator.filtered - emulator.memory  # the difference at the step's start
            end = lin_log(frame) - emulator.memory  # and at its end, before any event of the step
            events = emulator.step(frame, t_end)
            for y in range(3):
                for x in range(5):
                    mine = events["t"][(events["x"] == x) & (events["y"] == y)]
                    expected = crossing_times_by_search(start[y, x], end[y, x], theta, t0, t_end - t0)
                    assert len(mine) == len(expected)
                    assert np.abs(mine - np.array(expected, dtype=np.int64)).max(initial=0) <= 1, (mine, expected)


def test_a_bigger_rise_reaches_its_first_threshold_sooner_in_the_step():
    """Ten pixels whose log intensity rises by 0.25 to 2.0 over one step: the first event of each is
    at 0.2 / rise of the step (the old even spread put a one-event pixel at the step's middle)."""
    width = 10
    rise = np.linspace(0.25, 2.0, width)
    emulator = DVSEmulator(1, width, preset("clean", sigma_threshold=0.0), seed=0)
    emulator.reset(np.full((1, width), 40.0), 0.0)
    events = emulator.step(40.0 * np.exp(rise)[None, :], 1000.0)
    first = np.array([events["t"][events["x"] == x].min() for x in range(width)])
    np.testing.assert_allclose(first, np.floor(1000.0 * 0.2 / rise), atol=1)


def test_falling_ramp_gives_off_events():
    emulator = DVSEmulator(2, 2, preset("clean", sigma_threshold=0.0), seed=0)
    frames = [np.full((2, 2), 200.0 * math.exp(-0.1 * i)) for i in range(21)]  # log falls by 2.0
    events = run(emulator, frames)
    assert set(events["p"].tolist()) == {0}
    assert len(events["t"]) == 4 * 10  # 2.0 / 0.2 per pixel
    assert np.all(np.diff(events["t"]) >= 0)


def test_threshold_spread_matches_sigma_and_is_clamped():
    emulator = DVSEmulator(200, 200, preset("clean", sigma_threshold=0.03), seed=1)
    assert emulator.pos_threshold.mean() == pytest.approx(0.2, abs=0.002)
    assert emulator.pos_threshold.std() == pytest.approx(0.03, rel=0.03)
    assert emulator.neg_threshold.std() == pytest.approx(0.03, rel=0.03)
    wide = DVSEmulator(100, 100, preset("clean", sigma_threshold=0.2), seed=1)
    assert wide.pos_threshold.min() == pytest.approx(0.01)


def test_leak_rate_matches_its_parameter_in_a_static_scene():
    params = preset("clean", leak_rate_hz=2.0, leak_jitter=0.1, sigma_threshold=0.0)
    emulator = DVSEmulator(40, 40, params, seed=2)
    seconds = 10.0
    frames = [np.full((40, 40), 150.0)] * 101
    events = run(emulator, frames, dt_us=seconds * 1e6 / 100)
    rate = len(events["t"]) / (40 * 40 * seconds)
    assert rate == pytest.approx(2.0, rel=0.05)
    assert set(events["p"].tolist()) == {1}  # leak events are ON events


def test_shot_noise_rate_matches_its_parameter_and_is_higher_in_the_dark():
    params = preset("clean", shot_noise_rate_hz=5.0)
    frame = np.zeros((40, 80))
    frame[:, 40:] = 255.0  # left half dark, right half bright
    emulator = DVSEmulator(40, 80, params, seed=3)
    seconds = 20.0
    events = run(emulator, [frame] * 201, dt_us=seconds * 1e6 / 200)
    dark = events["x"] < 40
    dark_rate = dark.sum() / (40 * 40 * seconds)
    bright_rate = (~dark).sum() / (40 * 40 * seconds)
    assert dark_rate == pytest.approx(5.0, rel=0.05)
    assert bright_rate == pytest.approx(5.0 * 0.25, rel=0.1)
    assert 0.4 < events["p"][dark].mean() < 0.6  # ON and OFF alike


def test_low_pass_follows_the_intensity_dependent_first_order_filter():
    params = preset("clean", cutoff_hz=30.0, sigma_threshold=0.0)
    before = np.array([[25.0, 100.0]])  # both above the 20 DN joint: log region
    after = before * math.e  # log intensity +1 in both pixels
    emulator = DVSEmulator(1, 2, params, seed=0)
    emulator.reset(before, 0.0)
    start = emulator.filtered.copy()
    events = emulator.step(after, 1000.0)
    # eps = dt * 2 pi f_c * (I + 20) / 275 with the new intensity I.
    eps = 1e-3 * 2 * math.pi * 30.0 * (after[0] + 20) / 275
    np.testing.assert_allclose(emulator.filtered[0], start[0] + eps * (lin_log(after[0]) - start[0]))
    # Bright: eps ~ 0.2, one event; dark: eps ~ 0.06, none (unlimited bandwidth: 5 each).
    assert events["x"].tolist() == [1]
    late = run(DVSEmulator(1, 2, params, seed=0), [before] + [after] * 600)
    assert (late["x"] == 1).sum() == 5 and (late["x"] == 0).sum() == 5  # both settle on the full change
    assert late["t"][late["x"] == 1].min() < late["t"][late["x"] == 0].min()


def test_refractory_period_spaces_a_pixels_events():
    params = preset("clean", sigma_threshold=0.0, refractory_us=300.0)
    emulator = DVSEmulator(1, 1, params, seed=0)
    emulator.reset(np.full((1, 1), 100.0), 0.0)
    events = emulator.step(np.full((1, 1), 100.0 * math.e), 1000.0)  # 5 events 200 us apart without it
    # Each at its crossing or once 300 us have passed since the one before: 200, 500, 800 (1100 is
    # beyond the step).
    assert events["t"].tolist() == [200, 500, 800]
    # The level moved only by the emitted events: the two held back come at the next step, as soon
    # as the period allows.
    later = emulator.step(np.full((1, 1), 100.0 * math.e), 2000.0)
    assert later["t"].tolist() == [1100, 1400]


def test_a_short_refractory_period_keeps_the_event_due_at_the_steps_end():
    emulator = DVSEmulator(1, 1, preset("clean", sigma_threshold=0.0, refractory_us=1e-3), seed=0)
    emulator.reset(np.full((1, 1), 100.0), 0.0)
    events = emulator.step(np.full((1, 1), 100.0 * math.e), 1000.0)  # the fifth level reached at 1000 us
    assert events["t"].tolist() == [200, 400, 600, 800, 999]


def test_events_held_back_are_not_lost_when_the_difference_shrinks_a_little():
    """A refractory backlog of two OFF events, then a frame that takes back a quarter threshold:
    the difference (-0.4 to -0.35) still holds one of them all through the step, so it comes as
    soon as the period allows (400 us after the event at 999.99 us), not at the step's end or never."""
    params = preset("clean", sigma_threshold=0.0, refractory_us=400.0)
    emulator = DVSEmulator(1, 1, params, seed=0)
    emulator.reset(np.full((1, 1), 100.0), 0.0)
    first = emulator.step(np.full((1, 1), 100.0 * math.exp(-1.0)), 1000.0)  # five due, three emitted
    assert first["t"].tolist() == [199, 599, 999] and set(first["p"].tolist()) == {0}
    later = emulator.step(np.full((1, 1), 100.0 * math.exp(-0.95)), 2000.0)
    assert len(later["t"]) == 1 and abs(int(later["t"][0]) - 1400) <= 1 and later["p"].tolist() == [0]


def test_same_seed_same_events_and_noisy_preset_values():
    frames = [np.random.default_rng(i).uniform(20, 200, (12, 12)) for i in range(6)]
    a = run(DVSEmulator(12, 12, preset("noisy"), seed=5), frames)
    b = run(DVSEmulator(12, 12, preset("noisy"), seed=5), frames)
    c = run(DVSEmulator(12, 12, preset("noisy"), seed=6), frames)
    for name in "xytp":
        np.testing.assert_array_equal(a[name], b[name])
    assert len(a["t"]) != len(c["t"]) or not np.array_equal(a["t"], c["t"])
    noisy = preset("noisy")
    assert (noisy.pos_threshold, noisy.neg_threshold, noisy.sigma_threshold) == (0.2, 0.2, 0.03)
    assert (noisy.shot_noise_rate_hz, noisy.leak_rate_hz, noisy.cutoff_hz) == (5.0, 0.1, 30.0)
    clean = preset("clean")
    assert (clean.sigma_threshold, clean.shot_noise_rate_hz, clean.leak_rate_hz, clean.cutoff_hz) == (0.02, 0, 0, 0)


def test_bad_parameters_and_calls():
    with pytest.raises(ValueError, match="unknown DVS preset 'nope'"):
        preset("nope")
    with pytest.raises(ValueError, match="unknown DVS parameters"):
        preset("clean", sigma=0.1)
    with pytest.raises(ValueError, match="pos_threshold"):
        DVSParams(pos_threshold=0.0)
    emulator = DVSEmulator(2, 2)
    with pytest.raises(RuntimeError, match="reset"):
        emulator.step(np.zeros((2, 2)), 10.0)
    emulator.reset(np.zeros((2, 2)), 10.0)
    with pytest.raises(ValueError, match="not after"):
        emulator.step(np.zeros((2, 2)), 10.0)
    with pytest.raises(ValueError, match="expected 2x2"):
        emulator.step(np.zeros((3, 2)), 20.0)
