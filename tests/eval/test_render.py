"""The training picture of a sample: the frame (grey for a frameless sample) beside its events."""
import numpy as np
import torch

from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import Sample
from dagr_lite.eval.score import ANSWER, CAPTION_HEIGHT, TRUTH, caption_lines, render_sample

H, W = 20, 30


def _sample(channels: int) -> Sample:
    image = torch.full((channels, H, W), 50, dtype=torch.uint8)
    events = torch.tensor([[3.0, 4.0, 100.0, 1.0], [7.0, 2.0, 200.0, 0.0]])
    return Sample(events=events, image=image, boxes=torch.tensor([[10.0, 5.0, 20.0, 15.0]]),
                  labels=torch.zeros(1, dtype=torch.int64), video="v", frame=1, image_frame=0, t_start_us=0,
                  t_end_us=33_333, t_image_us=0)


def test_a_frameless_sample_is_drawn_on_grey_and_a_framed_one_on_its_frame():
    grey, framed = render_sample(collate([_sample(0)]), 0), render_sample(collate([_sample(3)]), 0)
    top = framed.shape[0] - H  # the panels sit under the caption bar, of whole lines
    assert top % CAPTION_HEIGHT == 0 and top >= CAPTION_HEIGHT and framed.shape[1:] == (2 * W, 3)
    assert grey.shape[1:] == framed.shape[1:]
    assert (grey[-H, 0] == 128).all() and (framed[top, 0] == 50).all()  # away from the box
    assert tuple(grey[-H + 5, 10]) == TRUTH  # the true box's outline on the grey frame
    np.testing.assert_array_equal(grey[-H:, W:], framed[-H:, W:])  # the events' panel is the same
    assert tuple(grey[-H + 4, W + 3]) == (220, 30, 30) and tuple(grey[-H + 2, W + 7]) == (30, 60, 220)  # ON, OFF


def test_answers_are_drawn_in_their_own_colour_above_the_threshold_only_under_a_caption():
    batch = collate([_sample(3)])
    answers = {"boxes": torch.tensor([[1.0, 1.0, 8.0, 8.0], [20.0, 10.0, 28.0, 18.0]]),
               "scores": torch.tensor([0.9, 0.1])}
    picture = render_sample(batch, 0, answers, score_threshold=0.3)
    top = picture.shape[0] - H
    assert tuple(picture[top + 1, 4]) == ANSWER and tuple(picture[top + 1, W + 4]) == ANSWER  # on both panels
    assert tuple(picture[top + 14, 20]) != ANSWER  # the answer under the threshold is not drawn
    assert (picture[:top] != 0).any(axis=2).sum() > 20  # the caption's text
    np.testing.assert_array_equal(picture[-2:], render_sample(batch, 0)[-2:])  # the rows below both answers


def test_a_caption_takes_as_many_lines_as_its_width_needs():
    parts = ["stub_014 frame 40, 33 ms after its image", "truth green, answers >= 0.4 orange", "events ON red, OFF blue"]
    assert caption_lines(parts, 632) == ["; ".join(parts)]  # a 320x180 frame's picture: one line
    narrow = caption_lines(parts, 312)  # a 160x96 training crop's
    assert len(narrow) > 1 and "; ".join(narrow) == "; ".join(parts)
    assert caption_lines(parts, 10) == parts  # a part longer than a line keeps a line of its own


def test_a_score_label_stays_inside_its_panel_on_a_dark_ground():
    """The demo's and detect's labels: white on black at the box's corner, moved inside the panel
    (a box at the right edge spilled its label into the events' panel, green on green)."""
    from PIL import Image, ImageDraw

    from dagr_lite.camera.render import score_label
    for box in ([280.0, 40.0, 320.0, 100.0], [0.0, 0.0, 40.0, 30.0], [300.0, 170.0, 320.0, 180.0]):
        panel = Image.new("RGB", (320, 180), (255, 255, 255))
        draw = ImageDraw.Draw(panel)
        left, top, right, bottom = draw.textbbox((0, 0), "0.44")
        score_label(draw, box, "0.44", 320, 180)
        marked = np.argwhere((np.asarray(panel) != 255).any(axis=2))
        # the whole label is drawn, none of it cut off by the panel's edges
        assert marked[:, 1].max() - marked[:, 1].min() + 1 == right - left + 4
        assert marked[:, 0].max() - marked[:, 0].min() + 1 == bottom - top + 2
        assert np.asarray(panel)[tuple(marked[0])].tolist() == [0, 0, 0]  # the label's dark ground
