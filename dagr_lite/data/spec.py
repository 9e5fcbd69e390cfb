"""What one sample's events are, owned in one place.

A :class:`SampleSpec` says which events a model reads at a query time ``t`` (docs/design.md, "One
sample"): those of the horizon ``[t - window_us, t)``, for a model with an image none from before
``image time - context_us``, less the events a refractory period or a background-activity filter
drops, with a guard on their count; with ``graph_context_us``, the graph's first stage also reads
the events that long before the horizon, as neighbours only. A training run records it in its checkpoints; evaluation, the sweep, the streaming
detector, detect and labelling read it from there (:class:`~dagr_lite.engine.checkpoint.Checkpoint`),
so a model is always run on the sample it was trained on unless an override says otherwise.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields

import numpy as np

from dagr_lite.errors import UserError


def is_integer(value) -> bool:
    """Whether ``value`` is a Python or numpy integer (not a bool): the one test of every integer
    setting (a sample's, a configuration's)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def increasing_positive_integers(values) -> bool:
    """Whether ``values`` is a sequence (not a string) of positive integers, each larger than the one
    before: the bounds of a carry picture's spans (``carry_spans_us``), in a config or a spec."""
    return (isinstance(values, Sequence) and not isinstance(values, str)
            and all(is_integer(v) and v > 0 for v in values) and all(a < b for a, b in zip(values, values[1:])))


def sample_start_us(t_query_us: float, window_us: int, t_image_us: float | None = None, context_us: int = 0) -> float:
    """The start of the events a model reads when asked at ``t_query_us``: it reads ``[start, t_query_us)``.

    Every model reads at most the last ``window_us`` (a horizon: older events have left); a model
    with an image (``t_image_us`` given) reads none from before ``t_image_us - context_us`` either.
    This is the one definition of a sample's events: the dataset (training, validation,
    evaluation, the sweep), the streaming detector and :meth:`SampleSpec.graph_start_us` call it.
    """
    start = t_query_us - window_us
    if t_image_us is not None:
        start = max(start, t_image_us - context_us)
    return start



@dataclass(frozen=True)
class SampleSpec:
    """The events of one sample (every time in microseconds).

    Args:
        window_us: the horizon: every model reads the events of ``[t - window_us, t)``.
        context_us: a model with an image reads none from before ``image time - context_us``.
        refractory_us: > 0: an event is dropped when its pixel had one (kept or not) less than
            this long before it, decided as it arrives; 0: every event is read.
        support_us: > 0: an event is kept only when one of its 8 neighbouring pixels had one (kept
            or not) less than this long before it (a background-activity filter,
            :mod:`~dagr_lite.data.denoise`), decided as it arrives; 0: no such filter.
        max_events: a sample holding more events is refused (never thinned); None: no guard.
        event_picture: the image is a picture of the events (the dense peer), not a camera frame.
        carry_picture: the image gains three channels, a picture of the events since the image's
            time (the dense peer of a hybrid that carries the image forward).
        carry_recent_us: > 0: the carry picture gains a fourth channel, the recency of each pixel's
            latest event over the last ``carry_recent_us`` (where the events are now); 0: none.
        carry_confirm_us: > 0: the carry picture gains three channels, a picture of the events since
            the image that a neighbouring pixel confirms (an event of one of its 8 neighbours less than
            this long before; :class:`~dagr_lite.data.dataset.CarryPicture`); 0: none.
        carry_align_us: > 0: the carry picture gains three channels, the camera frame moved by the
            background's displacement since it, found from the pixels that fired in the last
            ``carry_align_us`` (:mod:`~dagr_lite.data.align`); 0: none.
        carry_spans_us: increasing bounds (microseconds since the image): the carry picture gains a
            channel per span of time since the image, each pixel's count of events in it; (): none.
        carry_onset: the carry picture gains a channel, each pixel's first event since the image.
        graph_context_us: > 0: the event graph's first stage also reads the events of this long
            before the sample's start (for a model with an image, not from before ``image time -
            context_us``): they are neighbours of the sample's nodes, never pooled, so a node's
            features do not depend on where the horizon starts; 0: none.
    """

    window_us: int
    context_us: int
    refractory_us: int
    max_events: int | None
    event_picture: bool
    graph_context_us: int
    carry_picture: bool
    carry_recent_us: int
    support_us: int
    carry_confirm_us: int
    carry_align_us: int
    carry_spans_us: tuple[int, ...]
    carry_onset: bool

    def __post_init__(self):
        if isinstance(self.carry_spans_us, Sequence) and not isinstance(self.carry_spans_us, (str, tuple)):
            object.__setattr__(self, "carry_spans_us", tuple(self.carry_spans_us))  # a config's list
        checks = {"window_us": (is_integer(self.window_us) and self.window_us > 0, "a positive integer"),
                  "context_us": (is_integer(self.context_us) and self.context_us >= 0, "an integer >= 0"),
                  "refractory_us": (is_integer(self.refractory_us) and self.refractory_us >= 0, "an integer >= 0"),
                  "support_us": (is_integer(self.support_us) and self.support_us >= 0, "an integer >= 0"),
                  "carry_confirm_us": (is_integer(self.carry_confirm_us) and self.carry_confirm_us >= 0,
                                       "an integer >= 0"),
                  "carry_align_us": (is_integer(self.carry_align_us) and self.carry_align_us >= 0, "an integer >= 0"),
                  "max_events": (self.max_events is None or (is_integer(self.max_events) and self.max_events > 0),
                                 "a positive integer or None"),
                  "event_picture": (isinstance(self.event_picture, bool), "true or false"),
                  "carry_picture": (isinstance(self.carry_picture, bool), "true or false"),
                  "carry_recent_us": (is_integer(self.carry_recent_us) and self.carry_recent_us >= 0,
                                      "an integer >= 0"),
                  "graph_context_us": (is_integer(self.graph_context_us) and self.graph_context_us >= 0,
                                       "an integer >= 0"),
                  "carry_spans_us": (isinstance(self.carry_spans_us, tuple)
                                     and increasing_positive_integers(self.carry_spans_us),
                                     "a tuple of increasing positive integers"),
                  "carry_onset": (isinstance(self.carry_onset, bool), "true or false")}
        for name, (ok, expected) in checks.items():
            if not ok:
                raise UserError(f"sample {name} must be {expected}, got {getattr(self, name)!r}")

    def graph_start_us(self, t_query_us: float, t_image_us: float | None) -> float:
        """The earliest event the graph's first stage reads at ``t_query_us``: the sample's start
        moved back by ``graph_context_us``, for a model with an image not before ``image time - context_us``."""
        return sample_start_us(t_query_us, self.window_us + self.graph_context_us, t_image_us, self.context_us)

    @property
    def filter_lead_us(self) -> int:
        """How long before a sample's first event the arrival filters (refractory period,
        background-activity filter) read the stream to decide on it: the longer of their periods."""
        return max(self.refractory_us, self.support_us)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(field.name for field in fields(cls))

    @classmethod
    def from_dict(cls, values: dict) -> "SampleSpec":
        """The spec of a dict holding these keys (others, such as ``image_age``, are ignored); a
        missing key is an error naming it."""
        missing = [key for key in cls.keys() if key not in values]
        if missing:
            raise UserError(f"a sample spec needs {missing}, got keys {sorted(values)}")
        return cls(**{key: values[key] for key in cls.keys()})
