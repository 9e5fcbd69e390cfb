import numpy as np
import pytest
import torch

from dagr_lite.data.augment import TrainAugment, crop, crop_size, hflip, warp_image, zoom_translate
from dagr_lite.data.dataset import Sample
from tests.settings import AUGMENT

H, W = 40, 60


def make_sample(box=(10.0, 8.0, 30.0, 20.0)):
    """A bright rectangle on black, events at its pixels, and its box."""
    x1, y1, x2, y2 = (int(v) for v in box)
    image = torch.zeros(3, H, W, dtype=torch.uint8)
    image[:, y1:y2, x1:x2] = 200
    ys, xs = torch.meshgrid(torch.arange(y1, y2), torch.arange(x1, x2), indexing="ij")
    n = xs.numel()
    events = torch.stack([xs.flatten().float(), ys.flatten().float(), torch.arange(n).float(), torch.ones(n)], 1)
    return Sample(events=events, image=image, boxes=torch.tensor([box]), labels=torch.zeros(1, dtype=torch.int64),
                  video="v", frame=1, image_frame=0, t_start_us=0, t_end_us=33333, t_image_us=0)


def bright_extent(image):
    ys, xs = torch.nonzero(image[0] > 100, as_tuple=True)
    return xs.min().item(), ys.min().item(), xs.max().item() + 1, ys.max().item() + 1


def test_hflip_moves_image_events_and_boxes_together():
    sample = make_sample()
    flipped = hflip(sample)
    assert flipped.boxes.tolist() == [[30.0, 8.0, 50.0, 20.0]]
    assert bright_extent(flipped.image) == (30, 8, 50, 20)
    assert flipped.events[:, 0].min() == 30 and flipped.events[:, 0].max() == 49
    again = hflip(flipped)
    assert torch.equal(again.image, sample.image) and torch.equal(again.events, sample.events)
    assert torch.equal(again.boxes, sample.boxes)


def test_zoom_translate_moves_image_events_and_boxes_together():
    sample = make_sample()
    out = zoom_translate(sample, 1.5, -6.0, 4.0)
    expected = [10 * 1.5 - 6, 8 * 1.5 + 4, 30 * 1.5 - 6, 20 * 1.5 + 4]  # [9, 16, 39, 34]
    np.testing.assert_allclose(out.boxes.numpy(), [expected])
    assert bright_extent(out.image) == (9, 16, 39, 34)
    ex, ey = out.events[:, 0], out.events[:, 1]
    assert ex.min() >= 9 - 0.5 and ex.max() <= 39 - 0.5 and ey.min() >= 16 - 0.5 and ey.max() <= 34 - 0.5
    assert len(out.events) == len(sample.events)  # nothing left the frame
    np.testing.assert_allclose(out.events[:, 0].numpy(), 1.5 * (sample.events[:, 0].numpy() + 0.5) - 6 - 0.5)
    assert torch.equal(out.events[:, 2:], sample.events[:, 2:])


def test_identity_transform_changes_nothing():
    sample = make_sample()
    out = zoom_translate(sample, 1.0, 0.0, 0.0)
    assert torch.equal(out.image, sample.image) and torch.equal(out.events, sample.events)
    assert torch.equal(out.boxes, sample.boxes)


def test_boxes_leaving_the_frame_are_clipped_and_tiny_ones_dropped():
    sample = make_sample()
    sample = sample.replace(boxes=torch.tensor([[10.0, 8.0, 30.0, 20.0], [50.0, 30.0, 59.0, 39.0]]),
                            labels=torch.zeros(2, dtype=torch.int64))
    out = zoom_translate(sample, 1.0, 35.0, 0.0, min_box_size=2.0)
    # First box moves to [45, 65] and is clipped at 60; the second moves fully out and is dropped.
    np.testing.assert_allclose(out.boxes.numpy(), [[45.0, 8.0, 60.0, 20.0]])
    assert out.labels.tolist() == [0]
    assert (out.events[:, 0] <= W - 1).all() and len(out.events) < len(sample.events)
    thin = zoom_translate(sample, 1.0, 59.0, 0.0, min_box_size=2.0)  # 1 px of the first box stays
    assert thin.boxes.shape == (0, 4)


def test_train_augment_is_reproducible_and_consistent():
    augment = TrainAugment(**AUGMENT)
    sample = make_sample((5.0, 12.0, 20.0, 28.0))  # left of centre: a flip sends it right
    first = augment(sample, np.random.default_rng(5))
    second = augment(sample, np.random.default_rng(5))
    assert torch.equal(first.image, second.image) and torch.equal(first.boxes, second.boxes)
    flips = kept = 0
    for seed in range(60):
        out = augment(sample, np.random.default_rng(seed))
        if not len(out.boxes):
            continue
        kept += 1
        x1, y1, x2, y2 = out.boxes[0].tolist()
        ex, ey = out.events[:, 0] + 0.5, out.events[:, 1] + 0.5  # pixel centres
        assert ((ex >= x1 - 1e-3) & (ex <= x2 + 1e-3) & (ey >= y1 - 1e-3) & (ey <= y2 + 1e-3)).all()
        # Unflipped, the centre stays below 25 px; flipped, it lies above 35 px.
        centre = (x1 + x2) / 2
        assert centre < 25 or centre > 35
        flips += int(centre > 35)
    assert kept > 40 and 0.25 * kept < flips < 0.75 * kept


def test_bad_settings():
    with pytest.raises(ValueError, match="zoom"):
        TrainAugment(**{**AUGMENT, "zoom": (1.5, 1.0)})
    with pytest.raises(ValueError, match="flip_prob"):
        TrainAugment(**{**AUGMENT, "flip_prob": 2})


def test_events_whose_pixel_centre_stays_inside_are_kept_within_pixel_range():
    sample = make_sample((0.0, 0.0, 10.0, 10.0))
    out = zoom_translate(sample, 1.0, -0.3, 0.0)  # column 0 moves to -0.3: its centre (0.2) is inside
    assert len(out.events) == len(sample.events)
    assert out.events[:, 0].min() == 0.0
    gone = zoom_translate(sample, 1.0, -0.6, 0.0)  # column 0's centre moves to -0.1: outside
    assert len(gone.events) == len(sample.events) - 10


def test_image_dropout_greys_the_image_and_leaves_the_geometry_alone():
    sample = make_sample()
    always = TrainAugment(**{**AUGMENT, "image_dropout": 1.0})(sample, np.random.default_rng([3]))
    never = TrainAugment(**{**AUGMENT, "image_dropout": 0.0})(sample, np.random.default_rng([3]))
    assert torch.all(always.image == 128)
    assert torch.equal(always.boxes, never.boxes) and torch.equal(always.events, never.events)
    kept = sum(bool(torch.all(TrainAugment(**{**AUGMENT, "image_dropout": 0.25})(sample, np.random.default_rng([i])).image == 128))
               for i in range(400))
    assert 60 < kept < 140  # about a quarter
    with pytest.raises(ValueError, match="image_dropout"):
        TrainAugment(**{**AUGMENT, "image_dropout": 1.5})
    # A picture of events beside the frame (carry_picture) is events: dropout greys the frame alone.
    pictured = sample.replace(image=torch.cat([sample.image, torch.full_like(sample.image, 7)]))
    greyed = TrainAugment(**{**AUGMENT, "image_dropout": 1.0, "flip_prob": 0.0, "zoom": (1.0, 1.0),
                             "translate": 0.0})(pictured, np.random.default_rng([3]))
    assert torch.all(greyed.image[:3] == 128) and torch.all(greyed.image[3:] == 7)


def test_event_drop_removes_a_drawn_fraction_of_the_events_and_nothing_else():
    sample = make_sample()
    sample = sample.replace(events=sample.events.repeat(50, 1))  # enough events to count fractions
    base = TrainAugment(**{**AUGMENT, "event_drop": 0.0})
    dropping = TrainAugment(**{**AUGMENT, "event_drop": 0.6})
    fractions = []
    for seed in range(40):
        kept_all = base(sample, np.random.default_rng([seed]))
        out = dropping(sample, np.random.default_rng([seed]))
        assert torch.equal(out.image, kept_all.image) and torch.equal(out.boxes, kept_all.boxes)  # drawn last
        rows = {tuple(e) for e in kept_all.events.tolist()}
        assert all(tuple(e) in rows for e in out.events.tolist())  # every kept event is one of them, unmoved
        fractions.append(1 - len(out.events) / len(kept_all.events))
    assert 0 <= min(fractions) < 0.15 and 0.45 < max(fractions) <= 0.65  # drawn from [0, 0.6]
    assert 0.2 < np.mean(fractions) < 0.4
    with pytest.raises(ValueError, match="event_drop"):
        TrainAugment(**{**AUGMENT, "event_drop": 1.0})


def test_a_frameless_sample_moves_its_events_and_boxes_as_one_with_a_frame():
    augment = TrainAugment(**AUGMENT)
    sample = make_sample((5.0, 12.0, 20.0, 28.0))
    frameless = sample.replace(image=sample.image[:0])  # (0, H, W): a model without an image
    for seed in range(20):
        a, b = augment(sample, np.random.default_rng(seed)), augment(frameless, np.random.default_rng(seed))
        assert b.image.shape == (0, H, W)
        assert torch.equal(a.events, b.events) and torch.equal(a.boxes, b.boxes) and torch.equal(a.labels, b.labels)


def test_a_crop_cuts_image_events_and_boxes_at_whole_pixels():
    sample = make_sample((10.0, 8.0, 30.0, 20.0))
    sample = sample.replace(boxes=torch.tensor([[10.0, 8.0, 30.0, 20.0], [40.0, 30.0, 50.0, 38.0]]),
                            labels=torch.tensor([0, 0]))
    out = crop(sample, 20, 5, 24, 16)  # columns 20-43, rows 5-20
    assert out.image.shape == (3, 16, 24) and torch.equal(out.image, sample.image[:, 5:21, 20:44])
    # The first box keeps [20, 30) x [8, 20), moved by (-20, -5); the second lies outside and goes.
    np.testing.assert_allclose(out.boxes.numpy(), [[0.0, 3.0, 10.0, 15.0]])
    assert out.labels.tolist() == [0]
    # The events of columns 20-29, rows 8-19, moved with it, in their order.
    inside = (sample.events[:, 0] >= 20) & (sample.events[:, 1] <= 20)
    expected = sample.events[inside] - torch.tensor([20.0, 5.0, 0.0, 0.0])
    assert len(expected) == 10 * 12 and torch.equal(out.events, expected)
    # A box left thinner than min_box_size is dropped; a fractional event is kept by its pixel centre.
    assert crop(sample, 29, 0, 20, 20, min_box_size=2.0).boxes.shape == (0, 4)
    moved = sample.replace(events=torch.tensor([[19.4, 9.0, 0.0, 1.0], [19.6, 9.0, 1.0, 1.0], [43.4, 9.0, 2.0, 0.0],
                                                [43.6, 9.0, 3.0, 0.0]]))
    kept = crop(moved, 20, 5, 24, 16).events
    np.testing.assert_allclose(kept.numpy(), [[0.0, 4.0, 1.0, 1.0], [23.0, 4.0, 2.0, 0.0]], atol=1e-5)
    with pytest.raises(ValueError, match="must lie inside the 60x40 frame"):
        crop(sample, 40, 0, 24, 16)


def test_crop_size_rounds_up_to_the_stride_within_the_frame():
    assert crop_size(180, 320, 0.5, 32) == (96, 160)
    assert crop_size(180, 320, 1.0, 32) == (180, 320)
    assert crop_size(180, 320, 0.9, 32) == (180, 288)  # 162 rounds up to 192, beyond the frame
    assert crop_size(40, 60, 0.1, 8) == (8, 8)
    with pytest.raises(ValueError, match="crop fraction"):
        crop_size(180, 320, 0.0, 32)


def test_train_augment_crops_each_sample_at_a_drawn_place_after_its_geometry():
    plain = {**AUGMENT, "flip_prob": 0.0, "zoom": (1.0, 1.0), "translate": 0.0}
    sample = make_sample((5.0, 12.0, 20.0, 28.0))
    cropping = TrainAugment(**{**plain, "crop": 0.5, "crop_multiple": 8})  # 20x30 of 40x60, rounded up to 24x32
    places = set()
    for seed in range(30):
        out = cropping(sample, np.random.default_rng(seed))
        rng = np.random.default_rng(seed)
        rng.random(), rng.uniform(1.0, 1.0), rng.uniform(0, 0), rng.uniform(0, 0), rng.uniform(0, 0), rng.uniform(0, 0)
        rng.random()  # whether it is placed around a box (never, by default)
        x0, y0 = int(rng.integers(0, 60 - 32 + 1)), int(rng.integers(0, 40 - 24 + 1))
        expected = crop(sample, x0, y0, 32, 24)
        assert torch.equal(out.image, expected.image) and torch.equal(out.events, expected.events)
        assert torch.equal(out.boxes, expected.boxes)
        places.add((x0, y0))
    assert len(places) > 20  # drawn, not fixed
    whole = TrainAugment(**plain)(sample, np.random.default_rng(3))
    assert whole.image.shape == (3, H, W)
    with pytest.raises(ValueError, match="crop"):
        TrainAugment(**{**plain, "crop": 1.5})
    with pytest.raises(ValueError, match="crop_boxes"):
        TrainAugment(**{**plain, "crop": 0.5, "crop_boxes": 2.0})


def test_crops_placed_around_boxes_hold_a_box_centre_and_the_rest_are_anywhere():
    plain = {**AUGMENT, "flip_prob": 0.0, "zoom": (1.0, 1.0), "translate": 0.0}
    sample = make_sample((44.0, 30.0, 58.0, 39.0))  # a box in the bottom right corner, centre (51, 34.5)
    around = TrainAugment(**{**plain, "crop": 0.25, "crop_multiple": 4, "crop_boxes": 1.0})  # 12x16 crops of 40x60
    anywhere = TrainAugment(**{**plain, "crop": 0.25, "crop_multiple": 4})
    held = [around(sample, np.random.default_rng(seed)) for seed in range(40)]
    assert all(len(out.boxes) == 1 for out in held)
    for out in held:  # the box's centre, moved with the crop, lies inside it
        x1, y1, x2, y2 = out.boxes[0].tolist()
        assert x1 < 16 and y1 < 12 and x2 > 0 and y2 > 0
    assert len({tuple(out.boxes[0].tolist()) for out in held}) > 10  # the place is drawn among those
    with_box = sum(len(anywhere(sample, np.random.default_rng(seed)).boxes) for seed in range(200))
    assert with_box < 100  # anywhere, most 16x12 crops miss a 14x9 box in a corner
    # A sample without boxes is cropped anywhere.
    empty = sample.replace(boxes=sample.boxes[:0], labels=sample.labels[:0])
    assert around(empty, np.random.default_rng(1)).image.shape == (3, 12, 16)


def textured_sample(rng, channels=7, height=72, width=128, n=3000, boxes=4):
    """Random pixels in every channel (a frame and a carry picture), random events and boxes."""
    image = torch.from_numpy(rng.integers(0, 256, (channels, height, width), dtype=np.uint8))
    events = torch.from_numpy(np.stack([rng.integers(0, width, n), rng.integers(0, height, n), np.sort(rng.random(n)),
                                        rng.integers(0, 2, n)], 1).astype(np.float32))
    corner = rng.uniform([0, 0], [width - 20, height - 20], (boxes, 2))
    box = np.concatenate([corner, corner + rng.uniform(4, 20, (boxes, 2))], 1).astype(np.float32)
    return Sample(events=events, image=image, boxes=torch.from_numpy(box), labels=torch.zeros(boxes, dtype=torch.int64),
                  video="v", frame=1, image_frame=0, t_start_us=0, t_end_us=33333, t_image_us=0)


def test_a_warped_window_is_the_same_part_of_the_whole_warped_image_to_the_bit():
    rng = np.random.default_rng(3)
    image = textured_sample(rng).image
    for scale, tx, ty in ((1.0, 0.0, 0.0), (1.37, -20.3, -7.9), (1.0, 5.5, -3.25), (1.5, -64.0, -36.0)):
        whole = warp_image(image, scale, tx, ty)
        for x0, y0, w, h in ((0, 0, 128, 72), (32, 8, 64, 32), (97, 40, 31, 32), (5, 0, 1, 1)):
            assert torch.equal(warp_image(image, scale, tx, ty, window=(x0, y0, w, h)), whole[:, y0:y0 + h, x0:x0 + w])
    frameless = image[:0]
    assert warp_image(frameless, 1.2, 3.0, 1.0, window=(4, 2, 10, 6)).shape == (0, 6, 10)


def test_the_warp_is_torchs_bilinear_grid_sample_within_one_grey_level_and_mirrors_to_the_bit():
    """The compiled warp against ``grid_sample`` (align_corners=False, zeros outside), the independent
    reference: the two round float32 and float64 sampling positions, so a pixel may differ by one
    grey level where its value lies at a half; the flag ``flip`` is the image mirrored first."""
    rng = np.random.default_rng(4)
    image = textured_sample(rng).image  # (7, 72, 128)
    _, height, width = image.shape
    for scale, tx, ty in ((1.0, 0.0, 0.0), (1.37, -20.3, -7.9), (1.0, 5.5, -3.25), (1.5, -64.0, -36.0), (0.8, 9.1, 4.4)):
        us = (torch.arange(width, dtype=torch.float64) + 0.5 - tx) / scale
        vs = (torch.arange(height, dtype=torch.float64) + 0.5 - ty) / scale
        grid = torch.stack(torch.meshgrid(2 * us / width - 1, 2 * vs / height - 1, indexing="xy"), -1)
        ref = torch.nn.functional.grid_sample(image[None].double(), grid[None], mode="bilinear", padding_mode="zeros",
                                              align_corners=False)[0].round().clamp(0, 255)
        out = warp_image(image, scale, tx, ty)
        diff = (out.double() - ref).abs()
        assert diff.max() <= 1 and (diff > 0).double().mean() < 0.01
        assert torch.equal(warp_image(image, scale, tx, ty, flip=True), warp_image(image.flip(-1), scale, tx, ty))
        assert torch.equal(warp_image(image, scale, tx, ty, window=(3, 5, 40, 20), flip=True),
                           warp_image(image.flip(-1), scale, tx, ty)[:, 5:25, 3:43])


def test_float64_events_move_in_float64_as_the_reference_functions_move_them():
    aug = TrainAugment(flip_prob=0.5, zoom=(1.0, 1.5), translate=0.1, min_box_size=2.0, image_dropout=0.0,
                       event_drop=0.0, crop=0.5, crop_multiple=32, crop_boxes=0.75)
    for seed in range(8):
        sample = textured_sample(np.random.default_rng(seed), channels=3)
        sample = sample.replace(events=sample.events.double() + 0.123456789)  # digits float32 would round away
        fast = aug(sample, np.random.default_rng([seed, 3]))
        rng = np.random.default_rng([seed, 3])
        ref = hflip(sample) if rng.random() < 0.5 else sample
        scale = float(rng.uniform(1.0, 1.5))
        offsets = [rng.uniform(min(0.0, s * (1 - scale)), max(0.0, s * (1 - scale))) + rng.uniform(-0.1, 0.1) * s
                   for s in (ref.width, ref.height)]
        ref = zoom_translate(ref, scale, offsets[0], offsets[1], min_box_size=2.0, image=False, crop_follows=True)
        x0, y0, w, h = aug._crop_place(ref, rng)
        ref = crop(ref, x0, y0, w, h, min_box_size=2.0)
        assert fast.events.dtype == torch.float64 and torch.equal(fast.events, ref.events)


def test_boxes_are_clipped_and_thin_ones_dropped_as_a_plain_reference_does():
    """The NumPy clip and filter against the same steps written out in torch."""
    rng = np.random.default_rng(11)
    for _ in range(50):
        boxes = torch.from_numpy(rng.uniform(-30, 160, (6, 4)).astype(np.float32))
        boxes[:, 2:] = boxes[:, :2] + torch.from_numpy(rng.uniform(0, 40, (6, 2)).astype(np.float32))
        sample = textured_sample(rng, channels=3, boxes=6)
        sample = sample.replace(labels=torch.arange(6))
        out = zoom_translate(sample.replace(boxes=boxes), 1.0, 0.0, 0.0, min_box_size=2.0)
        ref = boxes.clone()
        ref[:, [0, 2]] = ref[:, [0, 2]].clamp(0, 128)
        ref[:, [1, 3]] = ref[:, [1, 3]].clamp(0, 72)
        keep = ((ref[:, 2] - ref[:, 0]) >= 2.0) & ((ref[:, 3] - ref[:, 1]) >= 2.0)
        assert torch.equal(out.boxes, ref[keep]) and torch.equal(out.labels, torch.arange(6)[keep])


def test_the_augmentation_of_whole_frames_is_the_reference_functions_to_the_bit():
    """``crop: 1``: a flip, then a zoom and translation of the whole frame (or none)."""
    for zoom, translate in (((1.0, 1.5), 0.1), ((1.0, 1.0), 0.0)):
        aug = TrainAugment(flip_prob=0.5, zoom=zoom, translate=translate, min_box_size=2.0, image_dropout=0.0,
                           event_drop=0.0, crop=1.0, crop_multiple=32, crop_boxes=0.0)
        for seed in range(12):
            sample = textured_sample(np.random.default_rng(seed), channels=(7, 3, 0)[seed % 3])
            fast = aug(sample, np.random.default_rng([seed, 2]))
            rng = np.random.default_rng([seed, 2])
            ref = hflip(sample) if rng.random() < 0.5 else sample
            scale = float(rng.uniform(*zoom))
            offsets = [rng.uniform(min(0.0, s * (1 - scale)), max(0.0, s * (1 - scale)))
                       + rng.uniform(-translate, translate) * s for s in (ref.width, ref.height)]
            if scale != 1.0 or offsets != [0.0, 0.0]:
                ref = zoom_translate(ref, scale, offsets[0], offsets[1], min_box_size=2.0)
            for key in ("image", "events", "boxes", "labels"):
                assert torch.equal(getattr(fast, key), getattr(ref, key)), (zoom, seed, key)


@pytest.mark.parametrize("zoom, translate", [((1.0, 1.5), 0.1), ((1.0, 1.0), 0.0)])  # the second: no warp
def test_a_crop_after_the_zoom_is_the_whole_zoomed_sample_cut_to_the_bit(zoom, translate):
    """The augmentation resamples only the crop's pixels; the reference warps the whole frame, then
    slices it (the order of the draws is the same)."""
    settings = dict(flip_prob=0.5, zoom=zoom, translate=translate, min_box_size=2.0, image_dropout=0.0,
                    event_drop=0.0, crop=0.5, crop_multiple=32, crop_boxes=0.75)
    aug = TrainAugment(**settings)
    flips = 0
    for seed in range(24):
        sample = textured_sample(np.random.default_rng(seed), channels=(7, 3, 0)[seed % 3])
        fast = aug(sample, np.random.default_rng([seed, 9]))
        rng = np.random.default_rng([seed, 9])  # the reference, drawing as the augmentation does
        flip = rng.random() < settings["flip_prob"]
        flips += flip
        ref = hflip(sample) if flip else sample
        scale = float(rng.uniform(*zoom))
        offsets = [rng.uniform(min(0.0, s * (1 - scale)), max(0.0, s * (1 - scale)))
                   + rng.uniform(-translate, translate) * s for s in (ref.width, ref.height)]
        if scale != 1.0 or offsets != [0.0, 0.0]:
            ref = zoom_translate(ref, scale, offsets[0], offsets[1], min_box_size=2.0)
        x0, y0, w, h = aug._crop_place(ref, rng)
        ref = crop(ref, x0, y0, w, h, min_box_size=2.0)
        assert fast.image.shape == ref.image.shape == (len(sample.image), *crop_size(72, 128, 0.5, 32))
        assert torch.equal(fast.image, ref.image)
        assert torch.equal(fast.events, ref.events) and torch.equal(fast.boxes, ref.boxes)
        assert torch.equal(fast.labels, ref.labels)
        assert 0 < len(fast.events) < len(sample.events)
    assert 0 < flips < 24


def test_events_kept_once_by_the_crop_are_the_events_kept_by_the_zoom_then_the_crop():
    """With a crop to follow, the zoom moves the events and leaves keeping them to the crop: events
    near every edge of the frame (within half a pixel, inside and out) end the same, crops touching
    each edge and none."""
    rng = np.random.default_rng(5)
    sample = textured_sample(rng, channels=3, n=4000)
    edges = np.concatenate([rng.uniform(-1.0, 1.0, (200, 1)), rng.uniform(126.0, 128.5, (200, 1))])
    rows = np.concatenate([rng.uniform(-1.0, 1.0, (200, 1)), rng.uniform(70.0, 72.5, (200, 1))])
    near = np.concatenate([np.concatenate([edges, rng.uniform(0, 72, (400, 1))], 1),
                           np.concatenate([rng.uniform(0, 128, (400, 1)), rows], 1)])
    extra = np.concatenate([near, np.zeros((800, 1)), np.ones((800, 1))], 1).astype(np.float32)
    for scale, tx, ty in ((1.0, 0.4, -0.3), (1.23, -7.7, -3.1), (1.5, -64.0, -36.0), (1.0, 0.0, 0.0)):
        # events of fractional position as a zoom leaves them, then the same zoom moves them on
        base = sample.replace(events=torch.cat([sample.events, torch.from_numpy(extra)]))
        once = zoom_translate(base, scale, tx, ty, image=False, crop_follows=True)
        twice = zoom_translate(base, scale, tx, ty, image=False)
        assert torch.equal(once.boxes, twice.boxes) and len(once.events) == len(base.events) > len(twice.events)
        for x0, y0 in ((0, 0), (64, 40), (0, 40), (64, 0), (17, 9)):
            a, b = crop(once, x0, y0, 64, 32), crop(twice, x0, y0, 64, 32)
            assert torch.equal(a.events, b.events) and len(a.events) > 0
            assert torch.equal(a.boxes, b.boxes) and torch.equal(a.labels, b.labels)
