"""Compiled kernels of the event picture (:func:`~dagr_lite.data.dataset.event_picture`): one pass
over the events to count them and keep each pixel's latest time, one pass over the pixels to write
the picture. They compute what the NumPy expressions they replace computed, operation for
operation in float64 (rounding half to even), so a picture is the same to the bit; the training
loader makes one per sample and the streaming detector one per answer.
"""
from __future__ import annotations

import numba
import numpy as np

from dagr_lite.data.denoise import neighbour_fired
from dagr_lite.graph.compiled import KERNEL  # the project's kernel options: cached, GIL released


@numba.njit(**KERNEL)
def add_events(counts, last, x, y, t, p, width):  # pragma: no cover - compiled
    """In place, for the events ``x, y, t, p`` as stored (any integer or float types; a pixel is
    ``int(y) * width + int(x)``, a time ``float(t)``): ``counts[0, pixel]`` += 1 for ON events
    (``p == 1``), ``counts[1, pixel]`` for OFF (``p == 0``); ``last[pixel] = max(last[pixel], t)``
    for every event. Reading the stored types saves the copies a cast of each column would make."""
    for i in range(len(t)):
        j = np.int64(y[i]) * width + np.int64(x[i])
        if p[i] == 1:
            counts[0, j] += 1
        elif p[i] == 0:
            counts[1, j] += 1
        ti = np.float64(t[i])
        if ti > last[j]:
            last[j] = ti


@numba.njit(**KERNEL)
def render(counts, last, t_end_us, window_us, recent_us, count_full, picture):  # pragma: no cover - compiled
    """Fills ``picture (P, C)`` uint8 from the per-pixel state: counts saturating at ``count_full``
    scaled to 255, recency ``255 * clip(1 - age / window_us, 0, 1)`` and, with ``C == 4``, the same
    over ``recent_us`` (0 where a pixel has no event)."""
    scale = 255.0 / count_full
    for j in range(picture.shape[0]):
        for row in range(2):
            picture[j, row] = np.uint8(np.rint(min(counts[row, j], count_full) * scale))
        if np.isfinite(last[j]):
            age = t_end_us - last[j]
            picture[j, 2] = np.uint8(np.rint(min(max(1 - age / window_us, 0.0), 1.0) * 255.0))
            if picture.shape[1] == 4:
                picture[j, 3] = np.uint8(np.rint(min(max(1 - age / recent_us, 0.0), 1.0) * 255.0))
        else:
            for c in range(2, picture.shape[1]):
                picture[j, c] = 0


@numba.njit(**KERNEL)
def add_confirmed(counts, last, seen, x, y, t, p, t_from, confirm_us, width, height):  # pragma: no cover - compiled
    """In place, for the events ``x, y, t, p`` in arrival order: an event at or after ``t_from`` whose
    8 neighbouring pixels hold one with ``t - seen[q] < confirm_us`` (``seen``: each pixel's latest
    earlier event time, -inf: none; its own pixel does not count) is *confirmed* and added to
    ``counts`` and ``last`` as :func:`add_events` adds it; every event then updates ``seen``. The
    rule of the background-activity filter (:mod:`~dagr_lite.data.denoise`), deciding what is
    counted rather than what is kept."""
    for i in range(len(t)):
        xi, yi = np.int64(x[i]), np.int64(y[i])
        ti = np.float64(t[i])
        j = yi * width + xi
        if ti >= t_from and neighbour_fired(seen, xi, yi, ti, confirm_us, width, height):
            if p[i] == 1:
                counts[0, j] += 1
            elif p[i] == 0:
                counts[1, j] += 1
            if ti > last[j]:
                last[j] = ti
        if ti > seen[j]:
            seen[j] = ti


@numba.njit(**KERNEL)
def add_history(spans, first, x, y, t, t_from, bounds, width):  # pragma: no cover - compiled
    """In place, for the events ``x, y, t`` (sorted by ``t``, none before ``t_from``): each event is
    counted in ``spans[k, pixel]`` for the span ``k`` of its time since ``t_from``
    (``bounds[k - 1] <= t - t_from < bounds[k]``; ``bounds`` increasing, the last span open), and
    ``first[pixel]`` (``inf``: none yet) keeps each pixel's first event time. ``spans`` may have no
    rows and ``first`` one entry (neither kept); counts only grow and a first time is written once,
    so events added in any pieces give the same state."""
    keep_first = len(first) > 1
    for i in range(len(t)):
        j = np.int64(y[i]) * width + np.int64(x[i])
        ti = np.float64(t[i])
        if spans.shape[0]:
            k = 0
            while k < len(bounds) and ti - t_from >= bounds[k]:
                k += 1
            spans[k, j] += 1
        if keep_first and ti < first[j]:
            first[j] = ti


@numba.njit(**KERNEL)
def render_history(spans, first, t_from, t_end, count_full, picture):  # pragma: no cover - compiled
    """Fills ``picture (P, C)`` uint8 from :func:`add_history`'s state at query time ``t_end``:
    channel ``k < spans.shape[0]`` each span's count saturating at ``count_full``, times
    ``255 // count_full`` (31 a count for 8), and with ``C > spans.shape[0]`` a last channel, the
    first event's time since ``t_from`` as a fraction ``f`` of ``t_end - t_from``:
    ``rint(1 + 254 * clip(f, 0, 1))``, 0 where a pixel has no event."""
    scale = 255 // count_full
    spans_n = spans.shape[0]
    span = max(t_end - t_from, 1.0)
    for j in range(picture.shape[0]):
        for k in range(spans_n):
            picture[j, k] = np.uint8(min(spans[k, j], count_full) * scale)
        if picture.shape[1] > spans_n:
            if np.isfinite(first[j]):
                picture[j, spans_n] = np.uint8(np.rint(1.0 + 254.0 * min(max((first[j] - t_from) / span, 0.0), 1.0)))
            else:
                picture[j, spans_n] = 0
