"""The training picture of a sample: the frame (grey for a frameless sample) beside its events."""
import numpy as np
import torch

from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import Sample
from dagr_lite.eval.score import render_sample

H, W = 20, 30


def _sample(channels: int) -> Sample:
    image = torch.full((channels, H, W), 50, dtype=torch.uint8)
    events = torch.tensor([[3.0, 4.0, 100.0, 1.0], [7.0, 2.0, 200.0, 0.0]])
    return Sample(events=events, image=image, boxes=torch.tensor([[10.0, 5.0, 20.0, 15.0]]),
                  labels=torch.zeros(1, dtype=torch.int64), video="v", frame=1, image_frame=0, t_start_us=0,
                  t_end_us=33_333, t_image_us=0)


def test_a_frameless_sample_is_drawn_on_grey_and_a_framed_one_on_its_frame():
    grey, framed = render_sample(collate([_sample(0)]), 0), render_sample(collate([_sample(3)]), 0)
    assert grey.shape == framed.shape == (H, 2 * W, 3)
    assert (grey[0, 0] == 128).all() and (framed[0, 0] == 50).all()  # away from the box
    assert tuple(grey[5, 10]) == (0, 200, 0)  # the true box's outline on the grey frame
    np.testing.assert_array_equal(grey[:, W:], framed[:, W:])  # the events' panel is the same
    assert tuple(grey[4, W + 3]) == (220, 30, 30) and tuple(grey[2, W + 7]) == (30, 60, 220)  # ON red, OFF blue
