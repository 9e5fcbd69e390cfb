"""A v2e-style DVS pixel emulator, vectorised over pixels (numpy).

The model follows the published description of v2e (Hu, Liu, Delbruck, CVPR Workshops 2021):

1. Luma from RGB (BT.601 weights), in digital numbers 0..255.
2. Lin-log conversion: ``log(x)`` above ``lin_log_dn`` (20 DN), the straight line
   ``x * log(lin_log_dn) / lin_log_dn`` below it, continuous at the joint.
3. Optional photoreceptor low-pass, first order, with a cutoff that scales with intensity
   (``cutoff_hz`` at full scale, lower in the dark): ``eps = dt * 2 pi cutoff_hz * (I + 20) / 275``,
   clamped to 1. ``cutoff_hz = 0`` is unlimited bandwidth.
4. Per-pixel ON and OFF thresholds drawn once from ``N(theta, sigma)`` and clamped to
   ``min_threshold``.
5. At each step, a pixel emits ``floor(|L - M| / theta)`` events of the sign of ``L - M``, where
   ``L`` is the filtered log intensity and ``M`` the memorised level; ``M`` moves by the emitted
   events only, so the remainder carries over to the next step.
6. A pixel's events of one step are placed where its level crosses them: across the step the
   difference ``L - M`` is taken as linear from its value at the step's start to its value at
   the end (the leak's drift of ``M`` included), and the ``k``-th event of the step is at the
   moment it reaches ``k`` thresholds, as ESIM places its events between two rendered frames (a
   level already held at the step's start is due at its start). Times are whole microseconds
   inside the step, at most one before its end, so a frame's events come before it.
7. Optional refractory period (an event due sooner than that after the pixel's previous one is
   emitted once the period has passed, if that is still inside the step; otherwise it is not
   emitted in this step and ``M`` does not move for it, so it is due at the next step's start
   while the difference still holds it), leak events (``M`` drifts down by
   ``leak_rate_hz * theta_on`` per second, with a per-pixel rate spread, giving ON events at about
   ``leak_rate_hz`` per pixel in a static scene) and shot noise (Poisson ON and OFF events at
   ``shot_noise_rate_hz`` per pixel in the dark, falling to a quarter of it at full intensity;
   they do not move ``M``).

Everything random is drawn from one seeded generator: the same seed and input give the same
events. All parameters are overridable; :data:`PRESETS` holds ``clean`` and ``noisy`` as in the
EventEgoHands paper (Table II, columns resolved by its text).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from dagr_lite.errors import UserError

LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])
# Shot noise rate at full intensity, as a fraction of the rate in the dark.
SHOT_NOISE_BRIGHT_FACTOR = 0.25


@dataclass(frozen=True)
class DVSParams:
    """Parameters of the pixel model (thresholds in log-intensity units, rates in Hz)."""

    pos_threshold: float = 0.2
    neg_threshold: float = 0.2
    sigma_threshold: float = 0.02
    min_threshold: float = 0.01
    cutoff_hz: float = 0.0
    leak_rate_hz: float = 0.0
    leak_jitter: float = 0.1  # per-pixel spread of the leak rate, as a fraction of it
    shot_noise_rate_hz: float = 0.0
    refractory_us: float = 0.0
    lin_log_dn: float = 20.0

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value) or value < 0:
                raise UserError(f"DVS parameter {f.name} must be finite and >= 0, got {value}")
        for name in ("pos_threshold", "neg_threshold", "min_threshold", "lin_log_dn"):
            if getattr(self, name) <= 0:
                raise UserError(f"DVS parameter {name} must be > 0, got {getattr(self, name)}")

    def with_overrides(self, **overrides) -> "DVSParams":
        known = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise UserError(f"unknown DVS parameters {unknown}; known: {sorted(known)}")
        return replace(self, **overrides)


PRESETS = {
    "clean": DVSParams(sigma_threshold=0.02),
    "noisy": DVSParams(sigma_threshold=0.03, shot_noise_rate_hz=5.0, leak_rate_hz=0.1, cutoff_hz=30.0),
}


def preset(name: str, **overrides) -> DVSParams:
    """The ``clean`` or ``noisy`` parameters, with any field overridden."""
    if name not in PRESETS:
        raise UserError(f"unknown DVS preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name].with_overrides(**overrides)


def rgb_to_luma(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` RGB (uint8 or float in DN 0..255) -> ``(H, W)`` float64 luma in DN."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.ndim == 2:
        return rgb
    return rgb @ LUMA_WEIGHTS


def lin_log(luma: np.ndarray, lin_log_dn: float = 20.0) -> np.ndarray:
    """Log intensity with a linear segment below ``lin_log_dn`` (continuous at the joint)."""
    luma = np.asarray(luma, dtype=np.float64)
    slope = math.log(lin_log_dn) / lin_log_dn
    return np.where(luma <= lin_log_dn, luma * slope, np.log(np.maximum(luma, lin_log_dn)))


def _repeat_ranges(counts: np.ndarray) -> np.ndarray:
    """For counts ``[2, 3]``: ``[0, 1, 0, 1, 2]`` (index of each repeat within its group)."""
    total = int(counts.sum())
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    return np.arange(total) - starts


class DVSEmulator:
    """Turns a sequence of frames into DVS events, one step per frame.

    Call :meth:`reset` with the first frame, then :meth:`step` with each following frame and
    its time; each step returns the events of the interval since the previous frame, sorted by
    time.

    Args:
        height, width: frame size.
        params: pixel model parameters (see :class:`DVSParams`, :func:`preset`).
        seed: seed of every random draw (thresholds, leak, shot noise).
    """

    def __init__(self, height: int, width: int, params: DVSParams = PRESETS["clean"], *, seed: int = 0):
        self.height, self.width, self.params = int(height), int(width), params
        self.rng = np.random.default_rng([seed])
        shape = (self.height, self.width)
        p = params
        self.pos_threshold = np.maximum(self.rng.normal(p.pos_threshold, p.sigma_threshold, shape), p.min_threshold)
        self.neg_threshold = np.maximum(self.rng.normal(p.neg_threshold, p.sigma_threshold, shape), p.min_threshold)
        self.leak_rate = p.leak_rate_hz * np.maximum(1 + p.leak_jitter * self.rng.standard_normal(shape), 0)
        self.memory: np.ndarray | None = None  # (H, W) memorised log intensity
        self.filtered: np.ndarray | None = None  # (H, W) low-passed log intensity
        self.last_event_us = np.full(shape, -np.inf)  # (H, W)
        self.t_us: float | None = None

    def reset(self, frame: np.ndarray, t_us: float = 0.0) -> None:
        """Start from ``frame`` at time ``t_us``: memorised levels equal its log intensity."""
        luma = self._luma(frame)
        self.filtered = lin_log(luma, self.params.lin_log_dn)
        self.memory = self.filtered.copy()
        if self.params.leak_rate_hz > 0:
            # A random leak phase per pixel, so leak events do not all fire together.
            self.memory -= self.rng.random(self.memory.shape) * self.pos_threshold
        self.last_event_us[:] = -np.inf
        self.t_us = float(t_us)

    def _luma(self, frame: np.ndarray) -> np.ndarray:
        luma = rgb_to_luma(frame)
        if luma.shape != (self.height, self.width):
            raise ValueError(f"frame is {luma.shape[1]}x{luma.shape[0]} (WxH), expected {self.width}x{self.height}")
        return luma

    def step(self, frame: np.ndarray, t_us: float) -> dict[str, np.ndarray]:
        """Events between the previous frame and ``frame`` at ``t_us``: arrays x, y, t (int64 us), p."""
        if self.memory is None:
            raise RuntimeError("call reset(first_frame, t_us) before step()")
        dt_us = float(t_us) - self.t_us
        if dt_us <= 0:
            raise ValueError(f"frame time {t_us} us is not after the previous one ({self.t_us} us)")
        p = self.params
        luma = self._luma(frame)
        log_luma = lin_log(luma, p.lin_log_dn)  # (H, W)
        before = self.filtered - self.memory  # (H, W) the difference at the step's start
        if p.cutoff_hz > 0:
            intensity = (luma + 20.0) / 275.0
            eps = np.minimum(dt_us * 1e-6 * 2 * math.pi * p.cutoff_hz * intensity, 1.0)
            self.filtered = self.filtered + eps * (log_luma - self.filtered)
        else:
            self.filtered = log_luma
        if p.leak_rate_hz > 0:
            self.memory -= self.leak_rate * (dt_us * 1e-6) * self.pos_threshold
        t0 = self.t_us
        parts = [self._change_events(t0, dt_us, before)]
        if p.shot_noise_rate_hz > 0:
            parts.append(self._shot_noise(luma, t0, dt_us))
        self.t_us = float(t_us)
        x, y, t, pol = (np.concatenate(a) for a in zip(*parts))
        order = np.argsort(t, kind="stable")
        return {"x": x[order], "y": y[order], "t": t[order], "p": pol[order]}

    def _change_events(self, t0: float, dt_us: float, before: np.ndarray):
        change = self.filtered - self.memory  # (H, W)
        on = change > 0
        threshold = np.where(on, self.pos_threshold, self.neg_threshold)
        # The tolerance keeps a change of exactly k thresholds at k events despite rounding.
        counts = np.floor(np.abs(change) / threshold + 1e-9).astype(np.int64)  # (H, W)
        ys, xs = np.nonzero(counts)
        n = counts[ys, xs]  # (P,)
        j = _repeat_ranges(n)  # (E,) index of each event within its pixel
        pixel = np.repeat(np.arange(len(n)), n)  # (E,)
        sign = np.where(on[ys, xs], 1.0, -1.0)  # (P,)
        theta = threshold[ys, xs]  # (P,)
        start, end = before[ys, xs], change[ys, xs]  # (P,)
        # (E,) how far each event's level, k thresholds, lies beyond the difference at the start
        gap = sign[pixel] * (j + 1) * theta[pixel] - start[pixel]
        # A level still ahead of the start is crossed on the way (the slope then has its sign and is
        # not zero); one already held at the start, within the counts' own tolerance of 1e-9
        # thresholds (a refractory period's backlog), is due at once.
        ahead = sign[pixel] * gap > 1e-9 * theta[pixel]
        fraction = np.zeros(len(j))
        fraction[ahead] = gap[ahead] / (end - start)[pixel][ahead]
        t = t0 + np.clip(fraction, 0.0, 1.0) * dt_us  # (E,) increasing with j within a pixel
        if self.params.refractory_us > 0:
            keep = self._refractory_keep(ys, xs, n, t, t0 + dt_us)
        else:
            keep = np.ones(len(t), dtype=bool)
        emitted = np.bincount(pixel[keep], minlength=len(n))  # (P,)
        self.memory[ys, xs] += sign * emitted * theta
        t, pixel = t[keep], pixel[keep]
        if len(t):
            np.maximum.at(self.last_event_us, (ys[pixel], xs[pixel]), t)
        # Whole microseconds inside the step, [t0, t0 + dt): an event due at its very end (a level
        # reached exactly there) is a microsecond earlier, so a frame's events all come before it.
        stamp = np.minimum(np.floor(t), math.ceil(t0 + dt_us) - 1).astype(np.int64)
        return (xs[pixel], ys[pixel], stamp, on[ys, xs][pixel].astype(np.uint8))

    def _refractory_keep(self, ys, xs, n, t, end_us: float) -> np.ndarray:
        """The events a pixel emits with a refractory period, their times moved in place: in order
        (their crossing times ``t`` rise within a pixel), each at its crossing or once the period
        since the pixel's previous event has passed, whichever is later, while that is inside the
        step. The rest of the pixel's events wait for a later step (``M`` has not moved for them)."""
        refractory = self.params.refractory_us
        last = self.last_event_us[ys, xs].copy()  # (P,)
        keep = np.zeros(len(t), dtype=bool)
        first = np.cumsum(n) - n  # (P,) index of each pixel's first event
        open_ = np.ones(len(n), dtype=bool)  # pixels that have not yet run out of the step
        for step in range(int(n.max()) if len(n) else 0):
            pixels = np.nonzero((n > step) & open_)[0]
            events = first[pixels] + step
            at = np.maximum(t[events], last[pixels] + refractory)
            ok = (at <= t[events]) | (at < end_us)  # not held back, or released inside the step
            t[events[ok]] = at[ok]
            keep[events[ok]] = True
            last[pixels[ok]] = at[ok]
            open_[pixels[~ok]] = False
        return keep

    def _shot_noise(self, luma: np.ndarray, t0: float, dt_us: float):
        """Poisson noise events, by thinning: candidates at the dark-pixel rate anywhere in the
        frame, each kept with the pixel's rate over that rate (the same law as one Poisson draw
        per pixel, at a cost that scales with the events instead of the pixels)."""
        p = self.params
        height, width = luma.shape
        candidates = self.rng.poisson(p.shot_noise_rate_hz * dt_us * 1e-6 * height * width)
        flat = self.rng.integers(0, height * width, candidates)  # (C,)
        intensity = np.clip(luma.reshape(-1)[flat] / 255.0, 0, 1)
        keep = self.rng.random(candidates) < 1 + (SHOT_NOISE_BRIGHT_FACTOR - 1) * intensity
        ys, xs = np.divmod(flat[keep], width)
        on = self.rng.random(len(ys)) < 0.5
        t = t0 + self.rng.random(len(ys)) * dt_us
        # Noise events leave the memorised level alone: moving it would make the pixel answer
        # each noise event with a real one of the other sign and double the noise rate.
        return (xs, ys, np.floor(t).astype(np.int64), on.astype(np.uint8))
