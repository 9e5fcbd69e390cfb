"""The background-activity filter against the pairwise rule, by hand, and chunk by chunk."""
import numpy as np
import pytest

from dagr_lite.data.denoise import support_keep, support_keep_reference


def random_events(rng, n, width, height, t_max, tick):
    t = np.sort(rng.integers(0, t_max, n)) // tick * tick  # several events per microsecond
    return rng.integers(0, width, n), rng.integers(0, height, n), t


@pytest.mark.parametrize("support_us", [1, 150, 2_000])
def test_the_filter_is_the_pairwise_rule_whole_and_in_chunks(support_us):
    rng = np.random.default_rng(support_us)
    width, height, n = 9, 6, 1500  # small: neighbours, borders and corners are common
    x, y, t = random_events(rng, n, width, height, 60_000, 13)
    expected = support_keep_reference(x, y, t, support_us, width, height)
    assert 0 < expected.sum() < n
    np.testing.assert_array_equal(support_keep(x, y, t, support_us, width, height), expected)
    last = np.full(width * height, -np.inf)
    cuts = np.sort(rng.integers(0, n, 15))
    chunks = [support_keep(x[a:b], y[a:b], t[a:b], support_us, width, height, last)
              for a, b in zip([0, *cuts], [*cuts, n])]
    np.testing.assert_array_equal(np.concatenate(chunks), expected)  # a stream's state, chunk by chunk


def test_the_filter_by_hand():
    # (x, y, t): a lone event; a neighbour 100 us later (kept: 100 < 150); a hot pixel firing again at
    # its own place (its own pixel does not support it); a diagonal neighbour exactly 150 us after the
    # last event near it (dropped: the bound is strict); two events of one microsecond side by side
    # (the first has no earlier neighbour, the second has).
    x = np.array([5, 6, 6, 7, 0, 1])
    y = np.array([5, 5, 5, 6, 0, 0])
    t = np.array([0, 100, 120, 270, 1_000, 1_000])
    assert support_keep(x, y, t, 150, 10, 10).tolist() == [False, True, True, False, False, True]
    assert support_keep_reference(x, y, t, 150, 10, 10).tolist() == [False, True, True, False, False, True]
    hot = support_keep(np.full(50, 3), np.full(50, 3), np.arange(50) * 10, 1_000, 8, 8)
    assert not hot.any()  # a pixel alone never supports itself
    assert support_keep(np.zeros(0, int), np.zeros(0, int), np.zeros(0), 10, 4, 4).shape == (0,)


def test_bad_input_is_named():
    x, y, t = np.array([0, 4]), np.array([0, 1]), np.array([0, 5])
    with pytest.raises(ValueError, match="outside the 4x4 sensor"):
        support_keep(x, y, t, 10, 4, 4)
    with pytest.raises(ValueError, match="support_us must be > 0, got 0"):
        support_keep(x, y, t, 0, 8, 8)
    with pytest.raises(ValueError, match=r"last_t must be float64 of shape \(64,\)"):
        support_keep(x, y, t, 10, 8, 8, np.zeros(63))
