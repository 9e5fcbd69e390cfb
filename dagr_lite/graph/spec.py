"""The event-graph settings, owned in one place.

An :class:`EventGraphSpec` says how events become a graph: node ``i`` sits at
``(x, y, beta * t)`` and takes incoming edges from at most ``max_neighbors`` earlier events
within ``radius`` (see :func:`~dagr_lite.graph.radius.radius_graph`). The detector owns one,
its checkpoint saves it, and the data loader's workers build their graphs from the model's own
spec, so the graph a model was trained on and the one it is run on cannot drift apart.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from dagr_lite.graph.radius import radius_graph

# The graph applies beta rounded to a multiple of 2^-TIME_SCALE_BITS (:attr:`EventGraphSpec.time_scale`).
TIME_SCALE_BITS = 30


@dataclass(frozen=True)
class EventGraphSpec:
    """How events become graph nodes and edges.

    Args:
        radius: neighbourhood radius, in pixels (time counts through ``beta``).
        beta: pixels per microsecond: the time axis of a node's position is ``beta * t``.
        max_neighbors: K, the most incoming edges per node (the nearest earlier events).
    """

    radius: float
    beta: float
    max_neighbors: int

    def __post_init__(self):
        for name in ("radius", "beta"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"graph {name} must be a positive number, got {value!r}")
        if isinstance(self.max_neighbors, bool) or not isinstance(self.max_neighbors, int) or self.max_neighbors <= 0:
            raise ValueError(f"graph max_neighbors must be a positive integer, got {self.max_neighbors!r}")
        if round(self.beta * 2 ** TIME_SCALE_BITS) < 1:
            raise ValueError(f"graph beta must be at least 2^-{TIME_SCALE_BITS + 1} pixels per microsecond (the "
                             f"graph's time axis rounds it to a multiple of 2^-{TIME_SCALE_BITS}), got {self.beta!r}")

    @property
    def time_scale(self) -> float:
        """``beta`` as the positions apply it: rounded to the nearest multiple of ``2^-TIME_SCALE_BITS``
        (5e-4 becomes 5.0000008e-4). For event times in whole microseconds, below ``2^53 / (time_scale
        2^TIME_SCALE_BITS)`` (hours at the default beta), ``time_scale * t`` is then exact in float64,
        and so is the offset between two events' positions: every radius test and ranking decided
        from it is the same whatever time the events count from (a sample counts from its image's
        time, a stream from an origin of its own)."""
        return round(self.beta * 2 ** TIME_SCALE_BITS) / 2 ** TIME_SCALE_BITS

    def positions(self, events: torch.Tensor) -> torch.Tensor:
        """Node positions ``(x, y, time_scale * t)`` of events ``(N, 4)`` (x, y, t in us, p), in their
        dtype (``time_scale``: ``beta`` rounded so that float64 positions are exact)."""
        return torch.stack([events[:, 0], events[:, 1], self.time_scale * events[:, 2]], dim=1)  # (N, 3)

    def edges(self, events: torch.Tensor, batch: torch.Tensor | None = None, *, workers: int = -1,
              backend: str = "auto", query: torch.Tensor | None = None) -> torch.Tensor:
        """The causal event graph ``(2, E)`` of events ``(N, 4)`` of samples ``batch (N,)``, on the
        events' device (``backend``: see :func:`~dagr_lite.graph.radius.radius_graph`; ``auto``
        builds a CUDA tensor's graph on its GPU); with ``query`` (``(N,)`` bool) only the edges into
        the events it marks.

        Positions are computed in float64 whatever the events' dtype, so every caller (the
        loader's workers, the model, the streaming detector) gets the same edges, and with
        :attr:`time_scale` the same whatever time the events count from.
        """
        return radius_graph(self.positions(events.detach().double()), self.radius, self.max_neighbors, batch,
                            workers=workers, backend=backend, query=query)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "EventGraphSpec":
        """The spec of a saved dict; a missing or unknown key is an error naming it."""
        expected = {"radius", "beta", "max_neighbors"}
        if set(values) != expected:
            raise ValueError(f"an event-graph spec needs exactly the keys {sorted(expected)}, got {sorted(values)}")
        return cls(radius=float(values["radius"]), beta=float(values["beta"]),
                   max_neighbors=values["max_neighbors"])
