"""The training picture of a sample: the frame (grey for a frameless sample) beside its events."""
import numpy as np
import torch

from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import Sample
from dagr_lite.eval.score import ANSWER, CAPTION_HEIGHT, TRUTH, render_sample

H, W = 20, 30


def _sample(channels: int) -> Sample:
    image = torch.full((channels, H, W), 50, dtype=torch.uint8)
    events = torch.tensor([[3.0, 4.0, 100.0, 1.0], [7.0, 2.0, 200.0, 0.0]])
    return Sample(events=events, image=image, boxes=torch.tensor([[10.0, 5.0, 20.0, 15.0]]),
                  labels=torch.zeros(1, dtype=torch.int64), video="v", frame=1, image_frame=0, t_start_us=0,
                  t_end_us=33_333, t_image_us=0)


def test_a_frameless_sample_is_drawn_on_grey_and_a_framed_one_on_its_frame():
    grey, framed = render_sample(collate([_sample(0)]), 0), render_sample(collate([_sample(3)]), 0)
    top = CAPTION_HEIGHT  # the panels sit under the caption bar
    assert grey.shape == framed.shape == (top + H, 2 * W, 3)
    assert (grey[top, 0] == 128).all() and (framed[top, 0] == 50).all()  # away from the box
    assert tuple(grey[top + 5, 10]) == TRUTH  # the true box's outline on the grey frame
    np.testing.assert_array_equal(grey[top:, W:], framed[top:, W:])  # the events' panel is the same
    assert tuple(grey[top + 4, W + 3]) == (220, 30, 30) and tuple(grey[top + 2, W + 7]) == (30, 60, 220)  # ON, OFF


def test_answers_are_drawn_in_their_own_colour_above_the_threshold_only_under_a_caption():
    batch = collate([_sample(3)])
    answers = {"boxes": torch.tensor([[1.0, 1.0, 8.0, 8.0], [20.0, 10.0, 28.0, 18.0]]),
               "scores": torch.tensor([0.9, 0.1])}
    picture = render_sample(batch, 0, answers, score_threshold=0.3)
    top = CAPTION_HEIGHT
    assert tuple(picture[top + 1, 4]) == ANSWER and tuple(picture[top + 1, W + 4]) == ANSWER  # on both panels
    assert tuple(picture[top + 14, 20]) != ANSWER  # the answer under the threshold is not drawn
    assert (picture[:top] != 0).any(axis=2).sum() > 20  # the caption's text
    np.testing.assert_array_equal(picture[top:, :, :][18:, :], render_sample(batch, 0)[top:][18:, :])  # below both
