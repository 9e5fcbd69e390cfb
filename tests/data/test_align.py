"""The camera's motion since the image (:mod:`dagr_lite.data.align`) against brute force and known shifts."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from dagr_lite.data.align import (_fine_scores, add_polarities, background_shift, frame_gradients, max_shift_px,
                                  shifted_frame)
from dagr_lite.data.dataset import CarryPicture, carry_channels
from dagr_lite.errors import UserError
from dagr_lite.synth.stub import stub_root
from tests.settings import sample_set

H, W = 90, 160


def textured_frame(seed: int, height: int = H, width: int = W) -> np.ndarray:
    """A frame of smooth noise and a few rectangles: edges in every direction."""
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.normal(size=(height, width)), 3.0)
    base = (base - base.min()) / np.ptp(base) * 160 + 40
    for _ in range(6):
        y, x = rng.integers(0, height - 20), rng.integers(0, width - 30)
        base[y:y + rng.integers(8, 20), x:x + rng.integers(10, 30)] *= rng.uniform(0.5, 1.5)
    return np.repeat(np.clip(base, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def brute_scores(gx: np.ndarray, gy: np.ndarray, signs: np.ndarray, radius: int) -> dict[tuple[int, int], float]:
    """Every shift's score within ``radius``: ``C_x^2 + C_y^2``, ``C = sum s(x) grad(x - d)`` over fired pixels."""
    rows, cols = np.nonzero(signs)
    scores = {}
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx * dx + dy * dy > radius * radius:
                continue
            r, c = rows - dy, cols - dx
            inside = (r >= 0) & (r < gx.shape[0]) & (c >= 0) & (c < gx.shape[1])
            s = signs[rows[inside], cols[inside]]
            cx, cy = (s * gx[r[inside], c[inside]]).sum(), (s * gy[r[inside], c[inside]]).sum()
            scores[(dx, dy)] = float(cx ** 2 + cy ** 2)
    return scores


def moving_edges_fire(frame: np.ndarray, shift: tuple[int, int], velocity: tuple[float, float]) -> np.ndarray:
    """The polarities a DVS fires when ``frame``'s background, moved by ``shift``, moves on with
    ``velocity``: +1 where the brightness rises (``-grad L . v`` large), -1 where it falls."""
    moved = frame_gradients(shifted_frame(frame, *shift))
    rate = -(moved.gx * velocity[0] + moved.gy * velocity[1])
    inside = np.zeros(rate.shape, bool)  # not the border the shift leaves empty
    inside[max(shift[1], 0) + 2:H + min(shift[1], 0) - 2, max(shift[0], 0) + 2:W + min(shift[0], 0) - 2] = True
    level = np.quantile(np.abs(rate[inside]), 0.8)
    return np.where(inside & (rate > level), 1.0, 0.0) + np.where(inside & (rate < -level), -1.0, 0.0)


def test_shifted_frame_against_a_loop():
    frame = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    for dx, dy in [(0, 0), (2, 1), (-3, 2), (1, -4), (-8, -6), (9, 0), (0, -7)]:
        expected = np.zeros_like(frame)
        for y in range(7):
            for x in range(9):
                if 0 <= y - dy < 7 and 0 <= x - dx < 9:
                    expected[y, x] = frame[y - dy, x - dx]
        np.testing.assert_array_equal(shifted_frame(frame, dx, dy), expected)


def test_frame_gradients_against_scipy():
    """The compiled blur, Sobel gradient and cell sums against SciPy's filters (borders clamped to
    the nearest pixel, the Gaussian's 3 sigma) and NumPy's block sums, on a frame of odd size."""
    frame = np.random.default_rng(6).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    got = frame_gradients(frame)
    log_luma = np.log(frame.astype(np.float64).mean(axis=2) + 10.0)
    blurred = ndimage.gaussian_filter(log_luma, 1.0, mode="nearest", truncate=3.0)
    gx, gy = ndimage.sobel(blurred, 1, mode="nearest"), ndimage.sobel(blurred, 0, mode="nearest")
    np.testing.assert_allclose(got.gx, gx, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.gy, gy, rtol=0, atol=1e-12)
    padded = np.zeros((40, 56))
    for coarse, fine in ((got.coarse_x, gx), (got.coarse_y, gy)):
        padded[:37, :53] = fine
        np.testing.assert_allclose(coarse, padded.reshape(10, 4, 14, 4).sum(axis=(1, 3)), rtol=0, atol=1e-12)


def test_the_fine_scores_are_the_brute_force_sums():
    rng = np.random.default_rng(1)
    gx, gy = rng.normal(size=(20, 30)), rng.normal(size=(20, 30))
    signs = np.where(rng.random((20, 30)) < 0.2, rng.choice([-1.0, 1.0], (20, 30)), 0.0)
    rows, cols = np.nonzero(signs)
    scores = np.empty((9, 9))
    _fine_scores(rows, cols, signs[rows, cols], gx, gy, 3, -2, 4, 6, scores)
    brute = brute_scores(gx, gy, signs, 12)
    for j in range(9):
        for i in range(9):
            dx, dy = 3 + i - 4, -2 + j - 4
            if dx * dx + dy * dy > 36:
                assert scores[j, i] == -np.inf
            else:
                assert scores[j, i] == pytest.approx(brute[(dx, dy)], rel=1e-12)


@pytest.mark.parametrize(("shift", "velocity"), [((0, 0), (1.0, 0.0)), ((5, -3), (0.6, -0.8)), ((-17, 9), (-1.0, 0.3)),
                                                 ((26, 14), (0.2, 1.0)), ((-2, -30), (-0.5, -0.5))])
def test_a_known_shift_of_the_frame_is_found(shift, velocity):
    """The polarities that the frame's edges, moved by ``shift`` and moving on, fire: the shift is
    found exactly, and it is the best of every shift searched (brute force)."""
    frame = textured_frame(2)
    gradients = frame_gradients(frame)
    signs = moving_edges_fire(frame, shift, velocity)
    radius = 35
    found = background_shift(gradients, signs, radius)
    assert found == shift
    brute = brute_scores(gradients.gx, gradients.gy, signs, radius)
    assert brute[found] == pytest.approx(max(brute.values()), rel=1e-12)


def test_no_fired_pixel_gives_no_shift_and_shapes_are_checked():
    gradients = frame_gradients(textured_frame(3))
    assert background_shift(gradients, np.zeros((H, W)), 20) == (0, 0)
    with pytest.raises(ValueError, match="differ in shape"):
        background_shift(gradients, np.zeros((H, W + 1)), 20)
    with pytest.raises(ValueError, match="uint8 frame"):
        frame_gradients(np.zeros((H, W, 3)))
    assert max_shift_px(0) == 3 and max_shift_px(100_000) == 53


def test_polarities_keep_each_pixel_latest():
    signs = np.zeros(6)
    add_polarities(signs, np.array([0, 1, 0, 2]), np.array([0, 0, 0, 1]), np.array([1, 0, 0, 1]), 3)
    np.testing.assert_array_equal(signs, [-1, -1, 0, 0, 0, 1])


def test_a_carry_picture_with_a_moved_frame():
    """Three more channels: the frame moved by :meth:`CarryPicture.shift`, which reads the pixels
    whose latest event since the image is within ``align_us`` of the query time; events added in
    pieces give the picture of adding them at once."""
    frame = textured_frame(4)
    rng = np.random.default_rng(5)
    n, t_image = 4000, 10_000
    t = np.sort(rng.integers(0, 60_000, n))
    x, y, p = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n)
    whole = CarryPicture(H, W, t_image, recent_us=5_000, align_us=4_000, frame=frame)
    pieces = CarryPicture(H, W, t_image, recent_us=5_000, align_us=4_000, frame=frame)
    assert whole.channels == carry_channels(5_000, 0, 4_000) == 7
    added = 0
    for t_end in (30_000, 60_001):  # each answer after the events added before it
        upto = int(np.searchsorted(t, t_end))
        whole.add(x[added:upto], y[added:upto], t[added:upto], p[added:upto])
        for chunk in np.array_split(np.arange(added, upto), 7):
            pieces.add(x[chunk], y[chunk], t[chunk], p[chunk])
        added = upto
        picture = whole.picture(t_end)
        np.testing.assert_array_equal(picture, pieces.picture(t_end))
        signs = np.zeros((H, W))  # the polarity of each pixel's latest event since the image, where recent
        since = np.nonzero((t >= t_image) & (t < t_end))[0]
        for i in since:
            signs[y[i], x[i]] = 1.0 if p[i] == 1 else -1.0
        last = np.full((H, W), -np.inf)
        np.maximum.at(last, (y[since], x[since]), t[since].astype(float))
        signs[last < t_end - 4_000] = 0.0
        shift = background_shift(frame_gradients(frame), signs, max_shift_px(t_end - t_image))
        assert whole.shift(t_end) == shift
        np.testing.assert_array_equal(picture[..., 4:], shifted_frame(frame, *shift))
    with pytest.raises(ValueError, match="moves the camera frame"):
        CarryPicture(H, W, t_image, align_us=4_000)


def test_a_sample_with_a_moved_frame_and_its_blank():
    """The loader's sample: seven carry channels after the frame, the last three the frame moved by
    the carry picture's shift; blanking the frame blanks its moved copy too."""
    plain = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000)
    moved = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000,
                       carry_align_us=10_000)
    assert moved.sample.carry_align_us == 10_000
    for index in (0, 7, 31):
        a, b = plain[index], moved[index]
        assert b.moved_frame and not a.moved_frame and b.image.shape[0] == a.image.shape[0] + 3
        torch.testing.assert_close(b.image[:a.image.shape[0]], a.image, rtol=0, atol=0)
        v = moved.videos.index(b.video)
        frame = b.image[:3].permute(1, 2, 0).numpy()
        carry = CarryPicture(*frame.shape[:2], b.t_image_us, 10_000, 0, 10_000, frame)
        raw = moved.events_of(v, b.t_image_us, b.t_end_us)
        carry.add(raw["x"], raw["y"], raw["t"], raw["p"])
        moved_frame = shifted_frame(frame, *carry.shift(b.t_end_us))
        np.testing.assert_array_equal(b.image[-3:].permute(1, 2, 0).numpy(), moved_frame)
        blank = b.blank_frame()
        assert (blank.image[:3] == 128).all() and (blank.image[-3:] == 128).all()
        torch.testing.assert_close(blank.image[3:-3], b.image[3:-3], rtol=0, atol=0)
    # with the spans and the onset too, the moved frame stays last: they come before it, and a blank greys it
    both = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000,
                      carry_align_us=10_000, carry_spans_us=[50_000], carry_onset=True)[31]
    assert both.image.shape[0] == b.image.shape[0] + 3
    torch.testing.assert_close(both.image[-3:], b.image[-3:], rtol=0, atol=0)
    torch.testing.assert_close(both.image[:-6], b.image[:-3], rtol=0, atol=0)
    blank = both.blank_frame()
    assert (blank.image[-3:] == 128).all() and torch.equal(blank.image[-6:-3], both.image[-6:-3])
    with pytest.raises(UserError, match="carry_align_us must be an integer >= 0, got -1"):
        sample_set(stub_root(), "valid", carry_picture=True, carry_align_us=-1)
