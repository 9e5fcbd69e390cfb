"""The camera's own motion since the image, found by laying the frame's edges over the latest events.

A head-mounted camera pans and shakes: between the image and a query time every part of the
background moves by one displacement ``d``, and its edges fire events where they now are. An edge
moving with velocity ``v`` fires ON events where the brightness rises, ``-grad(L) . v > 0``, and OFF
events where it falls, so the polarity of each recently fired pixel, laid over the frame's log-luma
gradient moved by ``d``, correlates with one direction of motion: the score of a shift ``d`` is
``C_x(d)^2 + C_y(d)^2``, ``C(d) = sum_x s(x) grad L(x - d)`` over the recently fired pixels ``x``
with polarity ``s(x) = +-1`` (the best direction of motion, ``v ~ -C``, need not be known). A
hand that moved on its own does not follow ``d``. :func:`background_shift` searches every shift
within the fastest motion searched at a quarter of the resolution (cross-correlations by FFT),
then the 9x9 shifts around the best one at full resolution (a compiled sum over the fired pixels).
It always answers a shift: where the fired pixels are not the background's moving edges (a still
camera with a moving hand, a flicker that fires one polarity everywhere, noise) the shift is the
best of no good ones, and the carry branch must learn when to trust it.

The carry picture gains the frame moved by ``d`` (``data.carry_align_us``): the background as it
should look now, beside the picture of the events since the image, so that the carry branch can
tell the events the camera's motion explains (on the moved frame's edges) from a hand's. Both the
training loader and the streaming detector call these functions on the same inputs (the frame,
and each pixel's latest event time and polarity since the image), so the shift is the same to the bit.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from scipy.fft import irfft2, next_fast_len, rfft2

from dagr_lite.graph.compiled import KERNEL

ALIGN_SPEED_PX_PER_MS = 0.5   # the fastest background motion searched: a head-mounted camera's pans at 320x180
ALIGN_COARSE = 4              # the coarse search's cell, px
_REFINE = ALIGN_COARSE        # the fine search: every shift within this many px of the coarse one, on each axis
_BLUR = 1.0                   # px, the Gaussian blur of the log luma before its gradient


class Gradients(NamedTuple):
    """A frame's log-luma gradient ``gx, gy`` (``(H, W)`` float64) and their sums over the coarse
    search's cells."""
    gx: np.ndarray
    gy: np.ndarray
    coarse_x: np.ndarray
    coarse_y: np.ndarray


_LOG_LUMA = np.log(np.arange(3 * 255 + 1) / 3.0 + 10.0)  # the log luma of every sum of a pixel's R, G and B
_TAPS = np.exp(-0.5 * (np.arange(-3, 4) / _BLUR) ** 2)
_TAPS /= _TAPS.sum()  # the Gaussian's 7 taps (3 sigma each way)


@numba.njit(**KERNEL)
def _gradients(frame, lut, taps, cell, gx, gy, coarse_x, coarse_y):  # pragma: no cover - compiled
    """The log luma of ``frame`` (``lut`` of R + G + B), blurred by the separable ``taps``, its
    Sobel gradient ``gx, gy`` and their sums over ``cell`` x ``cell`` cells; borders clamp to the
    nearest pixel."""
    height, width = gx.shape
    reach = len(taps) // 2
    row = np.empty(width + 2 * reach)
    across = np.empty((height + 2 * reach, width))  # blurred along x, rows clamped beyond the frame
    for y in range(height):
        for x in range(width):
            row[x + reach] = lut[np.int64(frame[y, x, 0]) + np.int64(frame[y, x, 1]) + np.int64(frame[y, x, 2])]
        for k in range(reach):
            row[k] = row[reach]
            row[width + reach + k] = row[width + reach - 1]
        for x in range(width):
            total = 0.0
            for k in range(len(taps)):
                total += taps[k] * row[x + k]
            across[y + reach, x] = total
    for k in range(reach):
        across[k] = across[reach]
        across[height + reach + k] = across[height + reach - 1]
    blurred = np.zeros((height + 2, width + 2))  # blurred along y too, one clamped pixel around
    for y in range(height):
        for x in range(width):
            total = 0.0
            for k in range(len(taps)):
                total += taps[k] * across[y + k, x]
            blurred[y + 1, x + 1] = total
    for y in range(1, height + 1):
        blurred[y, 0] = blurred[y, 1]
        blurred[y, width + 1] = blurred[y, width]
    blurred[0] = blurred[1]
    blurred[height + 1] = blurred[height]
    coarse_x[:] = 0.0
    coarse_y[:] = 0.0
    for y in range(height):
        for x in range(width):
            dx = (blurred[y, x + 2] + 2.0 * blurred[y + 1, x + 2] + blurred[y + 2, x + 2]
                  - blurred[y, x] - 2.0 * blurred[y + 1, x] - blurred[y + 2, x])
            dy = (blurred[y + 2, x] + 2.0 * blurred[y + 2, x + 1] + blurred[y + 2, x + 2]
                  - blurred[y, x] - 2.0 * blurred[y, x + 1] - blurred[y, x + 2])
            gx[y, x] = dx
            gy[y, x] = dy
            coarse_x[y // cell, x // cell] += dx
            coarse_y[y // cell, x // cell] += dy


def frame_gradients(frame: np.ndarray) -> Gradients:
    """The Sobel gradient of an ``(H, W, 3)`` uint8 frame's log luma (``log(mean RGB + 10)``, as a
    DVS pixel sees contrast), blurred by a Gaussian of 1 px first (7 taps; borders clamp to the
    nearest pixel), with its sums over the coarse search's cells."""
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 frame, got shape {frame.shape} {frame.dtype}")
    height, width = frame.shape[:2]
    cell = ALIGN_COARSE
    gx, gy = np.empty((height, width)), np.empty((height, width))
    coarse = (-(-height // cell), -(-width // cell))
    coarse_x, coarse_y = np.empty(coarse), np.empty(coarse)
    _gradients(frame, _LOG_LUMA, _TAPS, cell, gx, gy, coarse_x, coarse_y)
    return Gradients(gx, gy, coarse_x, coarse_y)


def max_shift_px(age_us: float) -> int:
    """The largest displacement searched after ``age_us`` since the image: the fastest motion
    searched over that time, plus 3 px (a tremor's)."""
    return int(math.ceil(ALIGN_SPEED_PX_PER_MS * max(age_us, 0.0) / 1000.0)) + 3


@numba.njit(**KERNEL)
def _fine_scores(rows, cols, signs, gx, gy, dx0, dy0, radius, limit, scores):  # pragma: no cover - compiled
    """``scores[j, i] = C_x^2 + C_y^2``, ``C = sum_k signs[k] * (gx, gy)[rows[k] - dy, cols[k] - dx]``
    (0 outside the frame) for ``dx = dx0 + i - radius``, ``dy = dy0 + j - radius``; -inf for a
    shift longer than ``limit``."""
    height, width = gx.shape
    for j in range(2 * radius + 1):
        dy = dy0 + j - radius
        for i in range(2 * radius + 1):
            dx = dx0 + i - radius
            if dx * dx + dy * dy > limit * limit:
                scores[j, i] = -np.inf
                continue
            cx = 0.0
            cy = 0.0
            for k in range(len(rows)):
                r = rows[k] - dy
                c = cols[k] - dx
                if 0 <= r < height and 0 <= c < width:
                    cx += signs[k] * gx[r, c]
                    cy += signs[k] * gy[r, c]
            scores[j, i] = cx * cx + cy * cy


@numba.njit(**KERNEL)
def add_polarities(signs, x, y, p, width):  # pragma: no cover - compiled
    """In place, for events in time order: ``signs[y * width + x]`` = +1 for an ON event (``p ==
    1``), -1 for any other: each pixel's latest polarity (the last of events sharing a time)."""
    for i in range(len(x)):
        signs[np.int64(y[i]) * width + np.int64(x[i])] = 1.0 if p[i] == 1 else -1.0


@numba.njit(**KERNEL)
def _fired(signs, cell, coarse):  # pragma: no cover - compiled
    """The fired pixels of ``signs (H, W)`` (nonzero) in row-major order: rows, columns, signs;
    ``coarse`` (zeroed here) gets the sums of ``signs`` over ``cell`` x ``cell`` cells."""
    height, width = signs.shape
    coarse[:] = 0.0
    n = 0
    for y in range(height):
        for x in range(width):
            if signs[y, x] != 0.0:
                n += 1
    rows, cols, values = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)
    k = 0
    for y in range(height):
        for x in range(width):
            value = signs[y, x]
            if value != 0.0:
                rows[k], cols[k], values[k] = y, x, value
                coarse[y // cell, x // cell] += value
                k += 1
    return rows, cols, values


def background_shift(gradients: Gradients, signs: np.ndarray, max_shift: int) -> tuple[int, int]:
    """The whole-pixel displacement ``(dx, dy)`` of the background since the frame whose
    :func:`frame_gradients` are ``gradients``, given ``signs`` ``(H, W)``: +1 or -1, the polarity
    of each recently fired pixel's latest event, 0 elsewhere. The best shift with ``dx^2 + dy^2
    <= max_shift^2`` of the 9x9 around the coarse search's best (the module's docstring): the
    maximum of ``C_x^2 + C_y^2`` over every shift when its peak stands out, as a moving
    background's does (``tests/data/test_align.py``), not always otherwise. ``(0, 0)`` when no
    pixel fired."""
    gx, gy = gradients.gx, gradients.gy
    if gx.shape != signs.shape or gy.shape != signs.shape:
        raise ValueError(f"gradients {gx.shape} and signs {signs.shape} differ in shape")
    max_shift, cell = int(max_shift), ALIGN_COARSE
    coarse_s = np.empty(gradients.coarse_x.shape)
    rows, cols, values = _fired(np.ascontiguousarray(signs, np.float64), cell, coarse_s)
    if not len(rows):
        return 0, 0
    reach = -(-max_shift // cell) + 1
    size = tuple(next_fast_len(n + 2 * reach, real=True) for n in coarse_s.shape)  # no shift wraps onto another
    coarse_g = np.stack([gradients.coarse_x, gradients.coarse_y])
    # C(d) = sum_x s(x) g(x - d): s's transform times the conjugate of g's, for both gradients at once.
    corr = irfft2(rfft2(coarse_s, size)[None] * np.conj(rfft2(coarse_g, size)), size)
    shifts = np.arange(-reach, reach + 1)
    corr = corr[:, shifts % size[0]][:, :, shifts % size[1]]  # [g, j, i]: dy = shifts[j], dx = shifts[i]
    score = (corr ** 2).sum(axis=0)
    sy, sx = np.meshgrid(shifts * cell, shifts * cell, indexing="ij")
    score = np.where(sx * sx + sy * sy <= (max_shift + cell) ** 2, score, -np.inf)
    j, i = np.unravel_index(int(np.argmax(score)), score.shape)
    dx0, dy0 = int(shifts[i]) * cell, int(shifts[j]) * cell
    fine = np.empty((2 * _REFINE + 1, 2 * _REFINE + 1))
    _fine_scores(rows, cols, values, gx, gy, dx0, dy0, _REFINE, max_shift, fine)
    if not np.isfinite(fine).any():
        return 0, 0
    j, i = np.unravel_index(int(np.argmax(fine)), fine.shape)
    return dx0 + int(i) - _REFINE, dy0 + int(j) - _REFINE


def shifted_frame(frame: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``frame`` moved by ``(dx, dy)`` whole pixels: ``out[y, x] = frame[y - dy, x - dx]``, zeros
    where nothing moves in."""
    height, width = frame.shape[:2]
    out = np.zeros_like(frame)
    if abs(dx) >= width or abs(dy) >= height:
        return out
    out[max(dy, 0):height + min(dy, 0), max(dx, 0):width + min(dx, 0)] = \
        frame[max(-dy, 0):height + min(-dy, 0), max(-dx, 0):width + min(-dx, 0)]
    return out
