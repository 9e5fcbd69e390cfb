"""A background-activity filter: an event is kept when a neighbouring pixel fired shortly before it.

A DVS pixel's noise (shot noise, leak events, a hot pixel) fires alone: no neighbour fires with
it. An edge that moves fires a run of neighbouring pixels within a few milliseconds. So event
``i`` (at pixel ``(x, y)``, time ``t``, in arrival order) is kept when one of its 8 neighbouring
pixels had an event, kept or not and of either polarity, less than ``support_us`` before it:
``t - t_q < support_us`` for the latest earlier event ``t_q`` of some neighbour ``q``. Its own
pixel does not count, so a hot pixel does not support itself.

The decision reads the events of ``(t_i - support_us, t_i]`` alone, so a stream filtered chunk
by chunk (:class:`~dagr_lite.stream.StreamingDetector`, with the per-pixel state carried) and a
sample read from ``support_us`` before its start agree to the event. One compiled pass over the
events; ``support_keep_reference`` is the same rule written out with NumPy, for the tests.
"""
from __future__ import annotations

import numba
import numpy as np

from dagr_lite.graph.compiled import KERNEL  # the project's kernel options: cached, GIL released


@numba.njit(**KERNEL)
def neighbour_fired(last, xi, yi, ti, period_us, width, height):  # pragma: no cover - compiled
    """Whether one of pixel ``(xi, yi)``'s 8 neighbours has ``ti - last[q] < period_us`` (``last``:
    each pixel's latest event time, -inf: none; the pixel itself does not count)."""
    for yy in range(max(yi - 1, 0), min(yi + 2, height)):
        row = yy * width
        for xx in range(max(xi - 1, 0), min(xi + 2, width)):
            if (xx != xi or yy != yi) and ti - last[row + xx] < period_us:
                return True
    return False


@numba.njit(**KERNEL)
def _support_pass(x, y, t, support_us, width, height, last, keep):  # pragma: no cover - compiled
    """Fills ``keep`` in arrival order, updating ``last`` (each pixel's latest event time)."""
    for i in range(len(t)):
        xi, yi, ti = x[i], y[i], t[i]
        keep[i] = neighbour_fired(last, xi, yi, ti, support_us, width, height)
        last[yi * width + xi] = ti


def _checked(x, y, t, width: int, height: int):
    x, y = np.ascontiguousarray(x, np.int64), np.ascontiguousarray(y, np.int64)
    t = np.ascontiguousarray(t, np.float64)
    if len(x) and (x.min() < 0 or x.max() >= width or y.min() < 0 or y.max() >= height):
        raise ValueError(f"events lie outside the {width}x{height} sensor (x in [{x.min()}, {x.max()}], "
                         f"y in [{y.min()}, {y.max()}])")
    return x, y, t


def support_keep(x: np.ndarray, y: np.ndarray, t: np.ndarray, support_us: float, width: int, height: int,
                 last_t: np.ndarray | None = None) -> np.ndarray:
    """Which events the background-activity filter keeps (the module's rule), decided on arrival.

    Args:
        x, y, t: the events in arrival order (sorted by ``t``; ties in the order given), integer
            pixel coordinates of a ``width`` x ``height`` sensor.
        support_us: how recent a neighbour's event must be (microseconds, > 0).
        last_t: ``(H * W,)`` float64, each pixel's latest event time before these events
            (``-inf``: none); updated in place (a stream's state). None: no earlier events.

    Returns:
        ``(N,)`` bool.
    """
    if not support_us > 0:
        raise ValueError(f"support_us must be > 0, got {support_us}")
    x, y, t = _checked(x, y, t, width, height)
    if last_t is None:
        last_t = np.full(width * height, -np.inf)
    elif last_t.shape != (width * height,) or last_t.dtype != np.float64:
        raise ValueError(f"last_t must be float64 of shape ({width * height},), got {last_t.dtype} {last_t.shape}")
    keep = np.empty(len(t), dtype=bool)
    _support_pass(x, y, t, float(support_us), int(width), int(height), last_t, keep)
    return keep


def support_keep_reference(x: np.ndarray, y: np.ndarray, t: np.ndarray, support_us: float, width: int,
                           height: int) -> np.ndarray:
    """The same rule as :func:`support_keep` (no earlier events), by comparing every pair of events:
    ``i`` is kept when some earlier ``j`` lies at a neighbouring pixel (Chebyshev distance 1) and
    ``t_i - t_j < support_us``. Quadratic; for tests."""
    x, y, t = _checked(x, y, t, width, height)
    n = len(t)
    keep = np.zeros(n, dtype=bool)
    for i in range(n):
        j = np.arange(i)
        near = (np.maximum(np.abs(x[j] - x[i]), np.abs(y[j] - y[i])) == 1) & (t[i] - t[j] < support_us)
        keep[i] = bool(near.any())
    return keep
