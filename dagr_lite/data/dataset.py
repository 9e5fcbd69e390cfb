"""The EventEgoHands dataset: one sample per label frame (docs/design.md, "One sample").

For label frame ``k`` and image age ``a`` (in frames) a sample holds the image of frame
``k - a``, the events of :func:`~dagr_lite.data.spec.sample_start_us` up to ``t(k)`` and the boxes of frame ``k``.
The events bring the stale image up to date. Training draws ``a`` per sample from a range;
evaluation fixes it. Which events a sample holds depends on the query time, the image's time
and fixed spans only, so the streaming detector reads exactly the same events
(:mod:`dagr_lite.stream`); nothing thins a sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.align import add_polarities, background_shift, frame_gradients, max_shift_px, shifted_frame
from dagr_lite.data.errors import DatasetFormatError, Problem
from dagr_lite.data.events import EventFile
from dagr_lite.data.denoise import support_keep
from dagr_lite.data.frames import frame_header_problems, list_frames, read_frame
from dagr_lite.data.spec import SampleSpec, increasing_positive_integers, is_integer, sample_start_us
from dagr_lite.data.labels import box_problems, list_videos, read_labels
from dagr_lite.data.picture import add_confirmed, add_events, add_history, render, render_history

# At most this many frame problems are listed when the dataset refuses to open.
MAX_LISTED_PROBLEMS = 10
# Which events a sample holds (see :func:`~dagr_lite.data.spec.sample_start_us`): bounded by the image and the window
# (models with an image), or by the window alone.
EVENT_SPANS = ("image", "window")
# The event picture (:func:`event_picture`): a pixel's count of each polarity saturates at this many events.
PICTURE_COUNT_FULL = 8
RGB_CHANNELS = 3        # a camera frame's
PICTURE_CHANNELS = 3    # an event picture's: ON count, OFF count, recency (a fourth with a recent window)


def picture_channels(recent_us: float) -> int:
    """The channels of an event picture: ON count, OFF count, recency, and with ``recent_us > 0``
    the recency over the last ``recent_us`` (:func:`picture_of`)."""
    return PICTURE_CHANNELS + (1 if recent_us > 0 else 0)


def carry_channels(recent_us: float, confirm_us: float, align_us: float = 0, spans_us: Sequence[int] = (),
                   onset: bool = False) -> int:
    """The channels of a carry picture (:class:`CarryPicture`): an event picture's
    (:func:`picture_channels`), with ``confirm_us > 0`` three more of the confirmed events, with
    ``align_us > 0`` three more of the frame moved by the camera's motion since it, with ``spans_us``
    one more for each of its ``len(spans_us) + 1`` spans of time since the image, and with
    ``onset`` one more, each pixel's first event."""
    return (picture_channels(recent_us) + (PICTURE_CHANNELS if confirm_us > 0 else 0)
            + (RGB_CHANNELS if align_us > 0 else 0) + (len(spans_us) + 1 if len(spans_us) else 0)
            + (1 if onset else 0))


def check_spans(spans_us) -> tuple[int, ...]:
    """``spans_us`` (a carry picture's span bounds, microseconds since the image) as a tuple, or a
    :class:`~dagr_lite.errors.UserError` naming it unless it is a list of increasing positive integers."""
    if not increasing_positive_integers(spans_us):
        raise UserError(f"carry_spans_us must be a list of increasing positive integers (microseconds since the "
                        f"image; []: none), got {spans_us!r}")
    return tuple(int(v) for v in spans_us)


def event_picture(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, t_end_us: float, window_us: float,
                  height: int, width: int, recent_us: float = 0) -> np.ndarray:
    """A picture of events for a dense CNN: ``(H, W, 3)`` uint8 with channel 0 the ON count, 1 the
    OFF count (each ``255 * min(count, PICTURE_COUNT_FULL) / PICTURE_COUNT_FULL``) and 2 the
    recency of each pixel's latest event, ``255 * (1 - (t_end_us - t_last) / window_us)`` (0: no event).
    With ``recent_us > 0`` a fourth channel (``(H, W, 4)``) holds the recency over the last
    ``recent_us`` alone, ``255 * (1 - (t_end_us - t_last) / recent_us)`` clipped at 0: where the
    events are now, when ``window_us`` is long (a carry picture's span, since the image).

    The dense peer the event branch is measured against reads this picture of the events-only
    sample in place of the camera frame (``data.event_picture``)."""
    counts, last = picture_state(height, width)
    add_to_picture(counts, last, x, y, t, p, width)
    return picture_of(counts, last, t_end_us, window_us, height, width, recent_us)


def channels_first(parts: Sequence[np.ndarray]) -> np.ndarray:
    """``(H, W, C_i)`` uint8 pictures (a frame, an event picture) as one ``(sum C_i, H, W)`` array, each
    part's channels after the one before: ``np.concatenate(parts, 2).transpose(2, 0, 1)``, written
    in one pass per part (a sample's frame and carry picture: 0.2 ms against 1.3)."""
    height, width = parts[0].shape[:2]
    out = np.empty((sum(part.shape[2] for part in parts), height, width), np.uint8)
    at = 0
    for part in parts:
        out[at:at + part.shape[2]] = part.transpose(2, 0, 1)
        at += part.shape[2]
    return out


def picture_state(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """An empty picture's per-pixel state for :func:`add_to_picture`: ``counts (2, H * W)`` int64
    zeros and ``last (H * W,)`` all -inf (no event yet)."""
    return np.zeros((2, height * width), np.int64), np.full(height * width, -np.inf)


def add_to_picture(counts: np.ndarray, last: np.ndarray, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                   width: int) -> None:
    """Adds events to a picture's per-pixel state, in place: ``counts (2, H * W)`` of ON (row 0)
    and OFF (row 1) events and ``last (H * W,)``, each pixel's latest event time (-inf: none).
    Adding events in any pieces gives the state of adding them at once (a stream's picture)."""
    if not len(t):
        return
    add_events(counts, last, np.asarray(x), np.asarray(y), np.asarray(t), np.asarray(p), int(width))


def picture_of(counts: np.ndarray, last: np.ndarray, t_end_us: float, window_us: float, height: int,
               width: int, recent_us: float = 0) -> np.ndarray:
    """:func:`event_picture` from the per-pixel state of :func:`add_to_picture` at ``t_end_us``."""
    picture = np.empty((height * width, picture_channels(recent_us)), np.uint8)
    render(counts, last, float(t_end_us), float(window_us), float(recent_us), PICTURE_COUNT_FULL, picture)
    return picture.reshape(height, width, -1)


class CarryPicture:
    """A picture of every event since the image (``t_image_us``), kept as per-pixel state that
    events are added to in any pieces: the carry branch's input, made by the loader for a sample
    and by the streaming detector at each answer, the same to the bit.

    Its channels at query time ``t``: those of :func:`event_picture` of the events of
    ``[t_image_us, t)`` over the image's age (ON count, OFF count, recency; with ``recent_us > 0``
    the recency over the last ``recent_us``), then, with ``confirm_us > 0``, the ON count, OFF
    count and recency of the *confirmed* events alone: those one of whose 8 neighbouring pixels
    had an event less than ``confirm_us`` before it (the background-activity filter's rule,
    :mod:`~dagr_lite.data.denoise`, counting every event and dropping none). A noise event fires
    alone, so the confirmed channels show where edges moved even where noise covers the frame.
    Deciding needs the events of ``confirm_us`` before the image too: :meth:`add` them all
    (:attr:`reads_from_us`); those before the image only confirm.

    With ``align_us > 0`` three more channels follow, last: the camera ``frame`` moved by the
    background's displacement since it (:meth:`shift`), found by laying the frame's log-luma
    gradient over the polarities of the pixels that fired in the last ``align_us``
    (:mod:`~dagr_lite.data.align`): the background as it should look now, beside where the events are.

    With ``spans_us`` (increasing bounds, microseconds since the image) ``len(spans_us) + 1``
    channels come before the moved frame, each pixel's count of events (both polarities, ``31 x min(count, 8)``) in
    each span of time since the image (``[0, spans_us[0])``, ..., ``[spans_us[-1], inf)``): a
    background that fires all along (a pan) fills every span so far, a hand that moved since the
    image only the spans it passed in. With ``onset`` one more, after them: each pixel's first event
    since the image, ``1 + 254 x`` its time as a fraction of the image's age (0: none). Counts only
    grow and a first time is written once, so the streaming detector keeps them as the other channels.
    """

    def __init__(self, height: int, width: int, t_image_us: float, recent_us: float = 0, confirm_us: float = 0,
                 align_us: float = 0, frame: np.ndarray | None = None, spans_us: Sequence[int] = (),
                 onset: bool = False):
        self.height, self.width = int(height), int(width)
        self.t_image_us, self.recent_us, self.confirm_us = float(t_image_us), float(recent_us), float(confirm_us)
        self.align_us = float(align_us)
        if self.align_us > 0:
            if frame is None or frame.shape != (self.height, self.width, RGB_CHANNELS):
                raise ValueError(f"a carry picture with align_us > 0 moves the camera frame: expected an "
                                 f"({self.height}, {self.width}, 3) frame, got "
                                 f"{None if frame is None else frame.shape}")
            self.frame = np.array(frame, copy=True)  # a camera's buffer may be reused for its next frame
            self.gradients = frame_gradients(self.frame)
            self.signs = np.zeros(self.height * self.width)  # each pixel's latest polarity since the image, +-1
        self.counts, self.last = picture_state(self.height, self.width)
        self.spans_us, self.onset = check_spans(spans_us), bool(onset)
        self.span_bounds = np.asarray(self.spans_us, np.float64)
        # counts per span of time since the image, each pixel's first event (no rows / one entry: not kept)
        self.spans = np.zeros((len(self.spans_us) + 1 if self.spans_us else 0, self.height * self.width), np.int32)
        self.first = np.full(self.height * self.width if self.onset else 1, np.inf)
        if self.confirm_us > 0:
            self.confirmed = picture_state(self.height, self.width)
            self.seen = np.full(self.height * self.width, -np.inf)  # every pixel's latest event, before the image too

    @property
    def reads_from_us(self) -> float:
        """The earliest event time the picture depends on: the image's, less ``confirm_us``."""
        return self.t_image_us - max(self.confirm_us, 0.0)

    @property
    def channels(self) -> int:
        return carry_channels(self.recent_us, self.confirm_us, self.align_us, self.spans_us, self.onset)

    @property
    def history_channels(self) -> int:
        """The channels of the spans and the onset."""
        return len(self.spans) + (1 if self.onset else 0)

    def add(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        """Adds events sorted by ``t``, later than any added before (integer pixels in the frame)."""
        if not len(t):
            return
        x, y, t, p = np.asarray(x), np.asarray(y), np.asarray(t), np.asarray(p)
        since = first_at_or_after(t, self.t_image_us)
        add_to_picture(self.counts, self.last, x[since:], y[since:], t[since:], p[since:], self.width)
        if self.history_channels:
            add_history(self.spans, self.first, x[since:], y[since:], t[since:], self.t_image_us, self.span_bounds,
                        self.width)
        if self.align_us > 0:
            add_polarities(self.signs, x[since:], y[since:], p[since:], self.width)
        if self.confirm_us > 0:
            add_confirmed(*self.confirmed, self.seen, x, y, t, p, self.t_image_us, self.confirm_us, self.width,
                          self.height)

    def picture(self, t_end_us: float) -> np.ndarray:
        """``(H, W, channels)`` uint8 at query time ``t_end_us``."""
        span = max(t_end_us - self.t_image_us, 1)
        picture = picture_of(self.counts, self.last, t_end_us, span, self.height, self.width, self.recent_us)
        parts = [picture]
        if self.confirm_us > 0:
            parts.append(picture_of(*self.confirmed, t_end_us, span, self.height, self.width))
        if self.history_channels:
            history = np.empty((self.height * self.width, self.history_channels), np.uint8)
            render_history(self.spans, self.first, self.t_image_us, float(t_end_us), PICTURE_COUNT_FULL, history)
            parts.append(history.reshape(self.height, self.width, -1))
        if self.align_us > 0:  # last: a blanked frame blanks the moved frame too (Sample.blank_frame)
            parts.append(shifted_frame(self.frame, *self.shift(t_end_us)))
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)

    def shift(self, t_end_us: float) -> tuple[int, int]:
        """The background's whole-pixel displacement ``(dx, dy)`` from the frame to ``t_end_us``
        (:func:`~dagr_lite.data.align.background_shift` over the pixels whose latest event since
        the image is at most ``align_us`` before ``t_end_us``, each with that event's polarity).
        Every event added must be earlier than ``t_end_us``, as for :meth:`picture`."""
        signs = np.where(self.last >= t_end_us - self.align_us, self.signs, 0.0).reshape(self.height, self.width)
        return background_shift(self.gradients, signs, max_shift_px(t_end_us - self.t_image_us))


def refractory_keep(x: np.ndarray, y: np.ndarray, t: np.ndarray, refractory_us: float, width: int,
                    last_t: np.ndarray | None = None) -> np.ndarray:
    """Which events a per-pixel refractory period keeps, decided on arrival.

    Event ``i`` (events sorted by ``t``) is kept when the latest earlier event at its pixel, kept or
    not and of either polarity, is at least ``refractory_us`` older: ``t_i - t_prev >= refractory_us``.
    A pixel firing faster than that (a hot pixel, a burst of several events in one microsecond)
    gives its first event only. The decision reads the events of ``[t_i - refractory_us, t_i]``
    alone, so a stream filtered chunk by chunk and a sample read from ``refractory_us`` before
    its start agree.

    Args:
        x, y: integer pixel coordinates; ``width``: the sensor's width (pixel ``y * width + x``).
        last_t: ``(H * W,)`` float64, the latest event time of each pixel before these events
            (``-inf``: none); updated in place (a stream's state). None: no earlier events.

    Returns:
        ``(N,)`` bool.
    """
    n = len(t)
    if n == 0:
        return np.zeros(0, dtype=bool)
    pixel = np.asarray(y, np.int64) * width + np.asarray(x, np.int64)
    order = np.argsort(pixel, kind="stable")  # by pixel, then by arrival
    pixel_sorted, t_sorted = pixel[order], np.asarray(t, np.float64)[order]
    first = np.ones(n, dtype=bool)
    first[1:] = pixel_sorted[1:] != pixel_sorted[:-1]
    previous = np.empty(n, dtype=np.float64)
    previous[1:] = t_sorted[:-1]
    previous[first] = -np.inf if last_t is None else last_t[pixel_sorted[first]]
    keep = np.empty(n, dtype=bool)
    keep[order] = t_sorted - previous >= refractory_us
    if last_t is not None:
        last = np.ones(n, dtype=bool)
        last[:-1] = first[1:]
        last_t[pixel_sorted[last]] = t_sorted[last]
    return keep


def arrival_keep(x: np.ndarray, y: np.ndarray, t: np.ndarray, *, refractory_us: int, support_us: int, width: int,
                 height: int, pixel_last: np.ndarray | None = None,
                 support_last: np.ndarray | None = None) -> np.ndarray:
    """Which events the arrival filters keep, decided on arrival: the refractory period
    (:func:`refractory_keep`) and the background-activity filter
    (:func:`~dagr_lite.data.denoise.support_keep`), each of a period > 0, each deciding on every
    event (kept by the other or not). ``pixel_last``, ``support_last``: their per-pixel states (a
    stream's), updated in place; None: no earlier events (a sample read
    :attr:`~dagr_lite.data.spec.SampleSpec.filter_lead_us` before its start)."""
    keep = np.ones(len(t), dtype=bool)
    if refractory_us:
        keep &= refractory_keep(x, y, t, refractory_us, width, pixel_last)
    if support_us:
        keep &= support_keep(x, y, t, support_us, width, height, support_last)
    return keep


class SampleTooLarge(ValueError):
    """A sample holds more events than ``max_events`` allows (a guard, never a thinning)."""


def first_at_or_after(t: np.ndarray, time_us: float) -> int:
    """Index of the first entry of the sorted times ``t`` at or after ``time_us``. Integer times are
    searched for the whole microsecond at or after a fractional ``time_us`` (the same index): NumPy
    would otherwise cast the whole array to float first."""
    if np.issubdtype(t.dtype, np.integer) and math.isfinite(time_us):
        time_us = math.ceil(time_us)
    return int(np.searchsorted(t, time_us, side="left"))


def draw_age(rng: np.random.Generator, low: int, high: int, power: float = 0.0) -> int:
    """An image age from ``[low, high]``: ``a`` with probability proportional to ``(a - low + 1) ** power``.

    ``power=0`` is one uniform integer draw (the same numbers as before weighting existed).
    """
    if high <= low:
        return low
    if not power:
        return int(rng.integers(low, high + 1))
    ages = np.arange(low, high + 1)
    weights = (ages - low + 1.0) ** power
    return int(ages[np.searchsorted(np.cumsum(weights), rng.random() * weights.sum(), side="right")])


def ramped_high(low: int, high: int, ramp: int, epoch: int) -> int:
    """The longest image age drawn in ``epoch`` (from 0) under a ramp of ``ramp`` frames an epoch:
    ``min(high, low + ramp * (epoch + 1))``, or ``high`` without a ramp (``ramp`` 0)."""
    return high if ramp <= 0 else min(high, low + ramp * (int(epoch) + 1))


def age_range(image_age: int | Sequence[int]) -> tuple[int, int]:
    """``(low, high)`` frames of an image age given as an int or an inclusive ``[low, high]`` range."""
    ages = list(image_age) if isinstance(image_age, Sequence) else [image_age] * 2
    integers = all(is_integer(a) for a in ages)
    if len(ages) != 2 or not integers or not 0 <= ages[0] <= ages[1]:
        raise UserError(f"image_age must be an integer >= 0 or a range [low, high] with 0 <= low <= high "
                         f"(frames; the image is never from the future), got {image_age!r}")
    return int(ages[0]), int(ages[1])


@dataclass
class Sample:
    """One training or evaluation sample.

    Attributes:
        events: ``(N, 4)`` float32 columns x, y, t, p: pixel coordinates, microseconds since the
            image (``t_image_us``; negative for events before it), polarity in {0, 1}; sorted by t.
        image: ``(3, H, W)`` uint8 RGB frame ``image_frame`` (with a picture of events, more channels;
            a frameless sample, ``EventEgoHands(frames=False)``, ``(0, H, W)``).
        boxes: ``(M, 4)`` float32 x1, y1, x2, y2 in pixels (M may be 0).
        labels: ``(M,)`` int64 class indices (0 = hand).
        video: video name; ``frame``: label frame index k; ``image_frame``: ``k - a`` for image age a.
        t_start_us, t_end_us: the event window ``[t_start_us, t_end_us)``; ``t_end_us`` is the time
            the boxes are for (``t(k)``, or between frames in a sweep). With a graph context
            (``graph_context_us``), ``events`` also hold earlier ones, which the graph reads and never pools.
        t_image_us: the image's time ``t(k - a)``.
        moved_frame: the image's last three channels are the frame moved by the camera's motion
            since it (a carry picture with ``carry_align_us``): a blanked frame blanks them too.
    """

    events: torch.Tensor
    image: torch.Tensor
    boxes: torch.Tensor
    labels: torch.Tensor
    video: str
    frame: int
    image_frame: int
    t_start_us: int
    t_end_us: int
    t_image_us: int
    moved_frame: bool = False

    @property
    def age_us(self) -> int:
        """How old the image is when the boxes are asked for."""
        return self.t_end_us - self.t_image_us

    @property
    def height(self) -> int:
        return self.image.shape[1]

    @property
    def width(self) -> int:
        return self.image.shape[2]

    def replace(self, **changes) -> "Sample":
        return replace(self, **changes)

    def blank_frame(self) -> "Sample":
        """This sample with its camera frame mid-grey (a picture of events beside it, ``carry_picture``, kept)."""
        image = self.image.clone()
        image[:RGB_CHANNELS] = 128
        if self.moved_frame:
            image[-RGB_CHANNELS:] = 128
        return replace(self, image=image)


class EventEgoHands(Dataset):
    """Samples of one split of a dataset in the EventEgoHands layout.

    Opening checks each video cheaply (keys, lengths, ``timeidx`` against the frame count and a
    few timestamps, every frame's JPEG header and size, label geometry) and raises
    :class:`DatasetFormatError` naming the file and key. Event files are read lazily, per worker
    process; each file's frame times follow its own convention (:attr:`EventFile.convention`).

    Args:
        root: dataset folder (holding ``train/``, ``valid/``, ``test/``, ``bounding_boxes.json``).
        split: ``train``, ``valid`` or ``test``.
        image_age: how many frames older the image is than the label frame: an int (fixed, as in
            evaluation) or an inclusive ``(low, high)`` range from which each sample draws its own
            (training; a label frame ``k`` draws from ``[low, min(high, k)]``, see :func:`draw_age`).
        age_power: how a range is drawn: age ``a`` with probability proportional to
            ``(a - low + 1) ** age_power`` (0: uniform; 1: ten frames ten times as often as one).
        age_ramp: > 0: a curriculum of image ages: in epoch ``e`` (from 0) a range draws from
            ``[low, min(high, low + age_ramp * (e + 1))]``, so the longest ages join a few epochs in
            (:func:`ramped_high`); 0: the whole range from the start.
        event_span: ``"image"``: the events of ``[max(t(k - a) - context_us, t(k) - window_us), t(k))``
            (a model with an image); ``"window"``: ``[t(k) - window_us, t(k))`` (a model without one).
            See :func:`~dagr_lite.data.spec.sample_start_us`.
        window_us: the horizon: no sample reads events older than this before its query time.
        context_us: with ``event_span="image"``, events from before the image may join (within the horizon).
        refractory_us: > 0: a pixel's event is dropped when the pixel had an event less than this
            long before it (:func:`refractory_keep`, decided on arrival, as the streaming detector
            does); 0: every event.
        support_us: > 0: an event is kept only when one of its 8 neighbouring pixels had an event
            less than this long before it (:func:`~dagr_lite.data.denoise.support_keep`, a
            background-activity filter decided on arrival, as the streaming detector does); 0: none.
        max_events: a guard: a sample holding more events raises :class:`SampleTooLarge` (None: no
            guard). It never thins a sample, since the streaming detector could not follow.
        first_frame: the first label frame (default: the smallest image age), e.g. the largest
            age of a sweep so that every age scores the same frames.
        fps: frame rate defining the frame times.
        image_size: expected ``(H, W)`` of the frames; a disagreeing frame is an error.
        videos: restrict to these videos of the split (all by default).
        transform: called as ``transform(sample, rng)`` on each sample (augmentation).
        clip_boxes: clip boxes to the image and drop empty ones instead of raising.
        labelled_only: samples only at frames with a label entry (sparse labels: an unlabelled
            frame is unknown, not empty); by default every frame is a sample, unlabelled ones empty.
        seed: seed of the image ages and of ``transform``'s generator.
        event_picture: the image is :func:`event_picture` of the sample's events instead of the
            camera frame (needs ``event_span="window"``): the dense peer of the event branch.
        carry_picture: the camera frame gains the channels of :func:`event_picture` of the events
            of ``[t(k - a), t(k))``, since the image's time (recency over that span; with
            ``refractory_us`` those it keeps): ``(6, H, W)`` images, the dense peer of a hybrid
            that carries the image forward with every event since it.
        carry_recent_us: > 0: the carry picture gains a fourth channel, the recency over the last
            ``carry_recent_us`` (where the events are now; ``(7, H, W)`` images); 0: three.
        carry_confirm_us: > 0: the carry picture gains three channels of the events a neighbouring
            pixel confirms within this long (:class:`CarryPicture`); 0: none.
        carry_align_us: > 0: the carry picture gains three channels, the frame moved by the
            camera's motion since it, found from the pixels that fired in the last ``carry_align_us``
            (:mod:`~dagr_lite.data.align`); 0: none.
        carry_spans_us: increasing bounds (microseconds since the image): the carry picture gains
            one channel per span of time since the image, each pixel's count of events in it
            (:class:`CarryPicture`); empty: none.
        carry_onset: the carry picture gains a channel of each pixel's first event since the image.
        graph_context_us: > 0: a sample's events also hold those of this long before its start
            (for ``event_span="image"`` not from before ``t(k - a) - context_us``), which the event
            graph reads as neighbours and never pools (:class:`~dagr_lite.data.spec.SampleSpec`);
            ``Sample.t_start_us`` stays the pooled start.
        frames: read the camera frames; false (a model without an image, in training, where
            nothing draws the frame): ``Sample.image`` is ``(0, H, W)``, a frame of no channels,
            saving each sample's frame decode and warp.
    """

    def __init__(self, root: Path | str, split: str, *, image_age: int | Sequence[int], window_us: int,
                 context_us: int, refractory_us: int, max_events: int | None, event_span: str = "image",
                 first_frame: int | None = None,
                 fps: float = fmt.DEFAULT_FPS,
                 image_size: Sequence[int] | None = None, videos: Sequence[str] | None = None,
                 transform: Callable[[Sample, np.random.Generator], Sample] | None = None,
                 clip_boxes: bool = False, labelled_only: bool = False, seed: int = 0, age_power: float = 0.0,
                 age_ramp: int = 0,
                 graph_context_us: int, event_picture: bool = False, carry_picture: bool = False,
                 carry_recent_us: int = 0, frames: bool = True, support_us: int, carry_confirm_us: int = 0,
                 carry_align_us: int = 0, carry_spans_us: Sequence[int] = (), carry_onset: bool = False):
        if split not in fmt.SPLITS:
            raise UserError(f"split must be one of {', '.join(fmt.SPLITS)}, got {split!r}")
        self.age_range = age_range(image_age)
        if not (np.isfinite(age_power) and age_power >= 0):
            raise UserError(f"age_power must be a number >= 0, got {age_power!r}")
        self.age_power = float(age_power)
        if not is_integer(age_ramp) or age_ramp < 0:
            raise UserError(f"age_ramp must be an integer >= 0 (frames an epoch; 0: no ramp), got {age_ramp!r}")
        self.age_ramp = int(age_ramp)
        if event_span not in EVENT_SPANS:
            raise UserError(f"event_span must be one of {EVENT_SPANS}, got {event_span!r}")
        if window_us <= 0:
            raise UserError(f"window_us must be > 0, got {window_us}")
        if event_picture and event_span != "window":
            raise UserError("event_picture reads the events of the window alone: it needs event_span='window', "
                             f"got {event_span!r}")
        self.event_picture = bool(event_picture)
        if carry_picture and event_picture:
            raise UserError("event_picture and carry_picture are two kinds of image: choose one")
        self.carry_picture = bool(carry_picture)
        self.frames = bool(frames)
        if carry_recent_us < 0:
            raise UserError(f"carry_recent_us must be >= 0, got {carry_recent_us}")
        self.carry_recent_us = int(carry_recent_us)
        if not is_integer(carry_confirm_us) or carry_confirm_us < 0:
            raise UserError(f"carry_confirm_us must be an integer >= 0, got {carry_confirm_us!r}")
        self.carry_confirm_us = int(carry_confirm_us)
        if not is_integer(carry_align_us) or carry_align_us < 0:
            raise UserError(f"carry_align_us must be an integer >= 0, got {carry_align_us!r}")
        if carry_align_us and carry_picture and not frames:
            raise UserError("carry_align_us moves the camera frame: a frameless sample (frames=False) has none")
        self.carry_align_us = int(carry_align_us)
        self.carry_spans_us = check_spans(carry_spans_us)
        if not isinstance(carry_onset, bool):
            raise UserError(f"carry_onset must be true or false, got {carry_onset!r}")
        self.carry_onset = carry_onset
        if context_us < 0:
            raise UserError(f"context_us must be >= 0, got {context_us}")
        if refractory_us < 0:
            raise UserError(f"refractory_us must be >= 0, got {refractory_us}")
        if support_us < 0:
            raise UserError(f"support_us must be >= 0, got {support_us}")
        self.support_us = int(support_us)
        if max_events is not None and max_events <= 0:
            raise UserError(f"max_events must be positive or None, got {max_events}")
        if graph_context_us < 0:
            raise UserError(f"graph_context_us must be >= 0, got {graph_context_us}")
        self.graph_context_us = int(graph_context_us)
        self.root, self.split = Path(root), split
        self.event_span, self.window_us, self.context_us = event_span, int(window_us), int(context_us)
        self.max_events, self.refractory_us = max_events, int(refractory_us)
        self.first_frame = self.age_range[0] if first_frame is None else max(int(first_frame), self.age_range[0])
        self.fps, self.transform, self.seed, self.epoch = float(fps), transform, int(seed), 0
        available = list_videos(self.root, split)
        if videos is not None:
            unknown = sorted(set(videos) - set(available))
            if unknown:
                raise DatasetFormatError.at(self.root / split, f"videos {unknown} are not in this split "
                                                               f"(it holds {available})")
            available = [v for v in available if v in set(videos)]
        self.videos = available
        labels = read_labels(self.root)
        self.image_size: tuple[int, int] | None = tuple(image_size) if image_size is not None else None
        self._size_from: Path | None = None  # the frame that set image_size, when not configured
        self._events: list[EventFile] = []
        self._boxes: list[dict[int, np.ndarray]] = []
        sample_video, sample_frame = [], []
        for v, video in enumerate(self.videos):
            events, boxes = self._open_video(video, labels.get(video, {}), clip_boxes)
            self._events.append(events)
            self._boxes.append(boxes)
            ks = np.arange(self.first_frame, events.num_frames)
            if labelled_only:
                ks = ks[np.isin(ks, np.fromiter(boxes, dtype=np.int64, count=len(boxes)))]
            sample_video.append(np.full(len(ks), v, dtype=np.int64))
            sample_frame.append(ks)
        self._sample_video = np.concatenate(sample_video) if sample_video else np.zeros(0, np.int64)
        self._sample_frame = np.concatenate(sample_frame) if sample_frame else np.zeros(0, np.int64)


    @property
    def sample(self) -> SampleSpec:
        """What each sample's events are (the streaming detector reads the same)."""
        return SampleSpec(window_us=self.window_us, context_us=self.context_us, refractory_us=self.refractory_us,
                          max_events=self.max_events, event_picture=self.event_picture,
                          graph_context_us=self.graph_context_us, carry_picture=self.carry_picture,
                          carry_recent_us=self.carry_recent_us, support_us=self.support_us,
                          carry_confirm_us=self.carry_confirm_us, carry_align_us=self.carry_align_us,
                          carry_spans_us=self.carry_spans_us, carry_onset=self.carry_onset)

    def _open_video(self, video: str, labels: dict[int, np.ndarray], clip_boxes: bool):
        frames_dir = fmt.frames_dir(self.root, self.split, video)
        frames = list_frames(frames_dir)
        num_frames = len(frames)
        if frames and max(frames) != num_frames - 1:
            first_gap = min(set(range(num_frames)) - set(frames))
            raise DatasetFormatError.at(frames_dir, f"frames are not numbered 0..{num_frames - 1}: "
                                                    f"{fmt.frame_name(first_gap)} is missing")
        events = EventFile(fmt.events_path(self.root, self.split, video), fps=self.fps, num_frames=num_frames)
        self._check_frames({k: frames_dir / name for k, name in frames.items()})
        label_file = fmt.labels_path(self.root)
        problems, boxes = [], {}
        for k, xywh in labels.items():
            key = fmt.label_key(video, k)
            if k >= num_frames:
                problems.append(Problem(label_file, key, f"label for frame {k}, but the video has {num_frames} frames"))
                continue
            xyxy = fmt.xywh_to_xyxy(xywh)
            if clip_boxes:
                height, width = self.image_size
                xyxy = np.clip(xyxy, 0, [width, height, width, height])
                xyxy = xyxy[(xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])]
            else:
                problems += [Problem(label_file, key, msg) for msg in box_problems(xywh, *self.image_size)]
            boxes[k] = xyxy.astype(np.float32)
        if problems:
            problems.append(Problem(label_file, "", "run `python -m dagr_lite.data.check ROOT` for a full report, "
                                                    "or set clip_boxes to clip boxes to the image"))
            raise DatasetFormatError(*problems)
        return events, boxes

    def _check_frames(self, frames: dict[int, Path]) -> None:
        """Every frame's JPEG header: readable, and of the dataset's size (the first frame's if not configured)."""
        expected_from = "as the dataset is configured" if self._size_from is None else f"as {self._size_from}"
        problems, size = frame_header_problems(frames, self.image_size, expected_from)
        if self.image_size is None and size is not None:
            self.image_size, self._size_from = size, frames[min(frames)]
        if len(problems) > MAX_LISTED_PROBLEMS:
            problems = problems[:MAX_LISTED_PROBLEMS] + [
                Problem(frames[min(frames)].parent, "", f"... and {len(problems) - MAX_LISTED_PROBLEMS} more "
                                                        "frame problems in this folder")]
        if problems:
            raise DatasetFormatError(*problems)

    def set_epoch(self, epoch: int) -> None:
        """Vary image ages and augmentation between epochs (same epoch, same samples)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self._sample_frame)

    def sample_name(self, index: int) -> tuple[str, int]:
        """``(video, label frame k)`` of sample ``index``, without reading it."""
        return self.videos[self._sample_video[index]], int(self._sample_frame[index])

    def __getitem__(self, index: int | tuple[int, int]) -> Sample:
        """Sample ``index`` as drawn in the current epoch (:meth:`set_epoch`), or with an
        ``(epoch, index)`` pair as drawn in that epoch (its image age and augmentation)."""
        epoch = self.epoch
        if isinstance(index, tuple):
            epoch, index = index
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample index {index} out of range for {len(self)} samples")
        index = int(index) % len(self)
        v, k = int(self._sample_video[index]), int(self._sample_frame[index])
        rng = np.random.default_rng([self.seed, int(epoch), index])
        low, high = self.age_range
        high = ramped_high(low, high, self.age_ramp, epoch)
        age = draw_age(rng, low, min(high, k), self.age_power)
        t_end = self.frame_time_us(v, k)
        return self.sample_at(v, k, k - age, t_end, self.boxes_of(v, k), rng)

    def num_frames(self, v: int) -> int:
        """Frames of video number ``v``."""
        return self._events[v].num_frames

    def frame_time_us(self, v: int, k: int) -> int:
        """Time of frame ``k`` of video number ``v``, in its file's frame-time convention."""
        return self._events[v].frame_time_us(k)

    def boxes_of(self, v: int, k: int) -> np.ndarray:
        """``(M, 4)`` xyxy boxes of frame ``k`` of video number ``v`` (none for an unlabelled frame)."""
        return self._boxes[v].get(k, np.zeros((0, 4), np.float32))

    def events_of(self, v: int, t_start: int, t_end: int) -> dict[str, np.ndarray]:
        """The raw events ``x, y, t, p`` of video number ``v`` with ``t_start <= t < t_end`` (us), as stored."""
        return self._events[v].window(t_start, t_end)

    def image_of(self, v: int, frame: int) -> np.ndarray:
        """Frame ``frame`` of video number ``v``: ``(H, W, 3)`` uint8 RGB."""
        return read_frame(fmt.frame_path(self.root, self.split, self.videos[v], frame), self.image_size)

    def sample_at(self, v: int, k: int, image_frame: int, t_end: int, boxes: np.ndarray,
                  rng: np.random.Generator) -> Sample:
        """The sample of video number ``v`` with the image of ``image_frame``, the events up to
        ``t_end`` (us) and ``boxes`` (xyxy) as the truth at ``t_end``; ``k`` names the label frame."""
        video, events_file = self.videos[v], self._events[v]
        t_image = events_file.frame_time_us(image_frame)
        with_image = t_image if self.event_span == "image" else None
        t_start = int(sample_start_us(t_end, self.window_us, with_image, self.context_us))
        t_graph = int(sample_start_us(t_end, self.window_us + self.graph_context_us, with_image, self.context_us))
        height, width = self.image_size
        frame = self.image_of(v, image_frame) if self.frames and not self.event_picture else None  # (H, W, 3)
        # One read serves the graph's events and, with a carry picture, every event since the image (and
        # those confirm_us before it, which confirm).
        carry = CarryPicture(height, width, t_image, self.carry_recent_us, self.carry_confirm_us, self.carry_align_us,
                             frame, self.carry_spans_us, self.carry_onset) if self.carry_picture else None
        kept = self._kept_events(v, min(t_graph, math.floor(carry.reads_from_us)) if carry else t_graph, t_end)
        graph_from = int(np.searchsorted(kept["t"], t_graph, side="left"))
        raw = {key: values[graph_from:] for key, values in kept.items()}
        if self.max_events is not None and len(raw["t"]) > self.max_events:
            raise SampleTooLarge(f"{events_file.path}: the sample of frame {k} (image frame {image_frame}) holds "
                                 f"{len(raw['t'])} events in [{t_graph}, {t_end}) us, more than max_events="
                                 f"{self.max_events}; shorten the horizon (data.window_us), thin it on arrival "
                                 f"(data.refractory_us, data.support_us) or raise the guard (data.max_events, null: none)")
        events = np.stack([raw["x"].astype(np.float32), raw["y"].astype(np.float32),
                           (raw["t"] - t_image).astype(np.float32),
                           raw["p"].astype(np.float32)], axis=1).reshape(-1, 4)  # (N, 4)
        if self.event_picture:
            pooled = int(np.searchsorted(raw["t"], t_start, side="left"))
            image = event_picture(*(raw[key][pooled:] for key in ("x", "y", "t", "p")), t_end, self.window_us,
                                  height, width)
        elif self.frames:
            image = frame
        else:
            image = np.zeros((height, width, 0), np.uint8)  # no frame: (H, W, 0)
        parts = [image]
        if self.carry_picture:  # every event since the image, recency over its age (and the recent window)
            since = first_at_or_after(kept["t"], carry.reads_from_us)
            carry.add(*(kept[key][since:] for key in ("x", "y", "t", "p")))
            parts.append(carry.picture(t_end))
        sample = Sample(events=torch.from_numpy(events),
                        image=torch.from_numpy(channels_first(parts)),  # (3, H, W), with a picture (6 or 7, H, W)
                        boxes=torch.from_numpy(np.array(boxes, dtype=np.float32).reshape(-1, 4)),
                        labels=torch.zeros(len(boxes), dtype=torch.int64), video=video, frame=k,
                        image_frame=image_frame, t_start_us=t_start, t_end_us=t_end, t_image_us=t_image,
                        moved_frame=bool(self.carry_picture and self.carry_align_us))
        if self.transform is not None:
            sample = self.transform(sample, rng)
        return sample

    def _kept_events(self, v: int, t_from: int, t_end: int) -> dict[str, np.ndarray]:
        """Video ``v``'s events of ``[t_from, t_end)`` that the refractory period and the
        background-activity filter keep (each decided from the events of its period before each
        event), checked to lie in the frame."""
        height, width = self.image_size
        lead = self.sample.filter_lead_us
        raw = self.events_of(v, t_from - lead, t_end)
        x, y = raw["x"], raw["y"]
        if len(x) and (x.max() >= width or y.max() >= height):
            raise DatasetFormatError.at(self._events[v].path, f"events of [{t_from - lead}, {t_end}) us "
                                                              f"lie outside the {width}x{height} frame (x max "
                                                              f"{x.max()}, y max {y.max()})", key="events/x, events/y")
        first = int(np.searchsorted(raw["t"], t_from, side="left"))
        if lead:
            keep = arrival_keep(x, y, raw["t"], refractory_us=self.refractory_us, support_us=self.support_us,
                                width=width, height=height)
            keep[:first] = False
        else:
            keep = slice(first, None)
        return {key: values[keep] for key, values in raw.items()}

    def close(self) -> None:
        for events in self._events:
            events.close()
