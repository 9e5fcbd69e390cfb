"""The ego dataset: a second built-in dataset, hard where the stub is easy.

Egocentric scenes seen by a head-mounted camera: the whole background pans and shakes by several
pixels a frame (a smooth random walk of the head plus a fast tremor), the light flickers, and one
to four hands move in the camera's frame on their own: they rest, set off, leave the frame and
come back, in several sizes, shapes (fingers spread, closed to a fist, three to five fingers) and
skin tones from dark to light, some with a sleeve. Hands pass behind a held object and behind each
other, and the background holds skin-coloured patches. Events come from the ``mixed`` DVS model
(each video clean or noisy, as EventEgoHands v6), so half the videos carry shot noise and leak
events and a 30 Hz photoreceptor bandwidth.

Boxes are the visible pixels of each hand (a hand hidden by an object or another hand is boxed
where it shows), so a box always holds the pixels that make the hand's events. Frames, events
and boxes are written in the release layout by the same code as the stub
(:func:`dagr_lite.synth.video.emulate_video`); ``docs/datasets.md`` gives its statistics beside
the stub's.
"""
from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.synth.stub import Splits, boxes_of, cached_dataset, paint_ellipse, scene_at, write_scenes
from dagr_lite.synth.dvs import LUMA_WEIGHTS, DVSParams
from dagr_lite.synth.video import choose_dvs_model

# Bump when the generated data changes, so caches made by an older recipe are not reused.
EGO_VERSION = 4           # 4: version 3's scenes, each event at the moment its pixel's level crosses it
                          # (synth.dvs), not at the middle of the emulator's step
                          # 3: 96 training videos, the 48 of version 2 and 48 after its test videos (valid and test
                          # as in version 2); 2: splits of 48 / 4 / 16 (1: 16 / 3 / 4, too few test videos)
EGO_HEIGHT, EGO_WIDTH = 180, 320
EGO_SPLITS = (("train", 48), ("valid", 4), ("test", 16), ("train", 48))  # videos ego_000, ... in this order
EGO_SECONDS = 2.0
EGO_UPSAMPLE = 6
EGO_DVS_MODEL = "mixed"     # per video clean or noisy (synth.video.choose_dvs_model, seeded by the video's name)
MIN_BOX_SIZE = 4.0          # a visible part smaller than this either way has no box
MIN_VISIBLE_PIXELS = 30     # nor one of fewer pixels
_WORLD = (384, 704)         # the periodic background the camera looks at, (H, W) px
_SKIN = np.array([[75, 50, 38], [141, 85, 60], [198, 134, 96], [224, 172, 138], [246, 208, 180]], np.float32)


def ego_root(cache_dir: Path | str | None = None) -> Path:
    """The ego dataset, generated on first use into the cache folder (atomically)."""
    return cached_dataset(f"ego-v{EGO_VERSION}", generate_ego, "ego", cache_dir)


def _periodic_noise(rng: np.random.Generator, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Smooth noise in [0, 1] that wraps around both axes (white noise low-passed in Fourier space)."""
    fy, fx = np.fft.fftfreq(shape[0])[:, None], np.fft.fftfreq(shape[1])[None, :]
    spectrum = np.fft.fft2(rng.standard_normal(shape)) * np.exp(-(fx ** 2 + fy ** 2) * (np.pi * scale) ** 2)
    field = np.fft.ifft2(spectrum).real
    field -= field.min()
    return field / max(field.max(), 1e-9)


def _wrapped(d: np.ndarray, period: float) -> np.ndarray:
    """Signed distance along a periodic axis, in [-period / 2, period / 2)."""
    return (d + period / 2) % period - period / 2


def _ease(u: np.ndarray | float) -> np.ndarray | float:
    """Smooth 0 -> 1 with zero speed at both ends (a hand sets off and comes to rest)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))


class EgoScene:
    """A hard egocentric scene, rendered at any time ``t`` (seconds).

    Implements the frame-source interface of :mod:`dagr_lite.synth.video`; :meth:`boxes` gives the
    visible extent of each hand at a frame.
    """

    def __init__(self, seed: int, *, height: int = EGO_HEIGHT, width: int = EGO_WIDTH, seconds: float = EGO_SECONDS,
                 fps: float = fmt.DEFAULT_FPS):
        rng = np.random.default_rng([seed, 1])
        self.height, self.width, self.fps = height, width, fps
        self.num_frames = int(round(seconds * fps))
        self.seconds = seconds
        self._background(rng)
        # The head: a drift, slow sways (a smooth random walk; 2 to 10 px a frame at their fastest) and a tremor.
        self.drift = rng.uniform(-90, 90, 2) * np.array([1.0, 0.4])  # px/s
        self.sway_amp = rng.uniform(15, 55, (3, 2)) * np.array([1.0, 0.5])
        self.sway_freq = rng.uniform(0.2, 0.9, (3, 2))
        self.sway_phase = rng.uniform(0, 2 * np.pi, (3, 2))
        self.tremor_amp, self.tremor_freq = rng.uniform(0.5, 2.5, 2), rng.uniform(5, 9, 2)
        self.tremor_phase = rng.uniform(0, 2 * np.pi, 2)
        # Light: a slow drift and, in most videos, a flicker of 4 to 12 Hz, stronger on one side.
        self.light_freq, self.light_phase = rng.uniform(0.2, 0.6), rng.uniform(0, 2 * np.pi)
        self.flicker_amp = rng.uniform(0.06, 0.2) if rng.random() < 0.75 else 0.0
        self.flicker_freq, self.flicker_phase = rng.uniform(4, 12), rng.uniform(0, 2 * np.pi)
        ramp = np.linspace(0, 1, width, dtype=np.float32)
        self.flicker_shape = (0.5 + ramp if rng.random() < 0.5 else 1.5 - ramp)[None, :, None]
        self._hands(rng, int(rng.integers(1, 5)))
        # A held object (a mug, a phone) in front of the hands in about half the videos.
        self.occluder = None
        if rng.random() < 0.5:
            self.occluder = {"size": rng.uniform([12, 10], [30, 22]), "colour": rng.uniform(20, 200, 3),
                             "start": rng.uniform([0.2, 0.3], [0.8, 0.8]) * [width, height],
                             "amp": rng.uniform(20, 70, 2), "freq": rng.uniform(0.2, 0.6, 2),
                             "phase": rng.uniform(0, 2 * np.pi, 2)}
        self.yy, self.xx = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5

    # Construction.

    def _background(self, rng: np.random.Generator) -> None:
        """A periodic world: two scales of smooth noise, furniture-like rectangles with edges, and
        a few skin-coloured patches (a table, an arm, a face in view)."""
        wh, ww = _WORLD
        coarse, fine = _periodic_noise(rng, _WORLD, 18.0), _periodic_noise(rng, _WORLD, 3.0)
        tint = rng.uniform([0.25, 0.3, 0.3], [0.6, 0.6, 0.7])
        world = (tint * (0.45 + 0.8 * (0.6 * coarse + 0.4 * fine))[..., None] * 255).astype(np.float32)
        yy, xx = np.mgrid[0:wh, 0:ww].astype(np.float32)
        for _ in range(int(rng.integers(5, 11))):  # edges the pans turn into events
            cy, cx = rng.uniform(0, wh), rng.uniform(0, ww)
            hh, hw = rng.uniform(10, 60), rng.uniform(15, 120)
            inside = (np.abs(_wrapped(yy - cy, wh)) < hh) & (np.abs(_wrapped(xx - cx, ww)) < hw)
            world[inside] = world[inside] * rng.uniform(0.6, 1.4) + rng.uniform(-15, 15, 3)
        for _ in range(int(rng.integers(2, 6))):  # hand-coloured background
            cy, cx = rng.uniform(0, wh), rng.uniform(0, ww)
            a, b, angle = rng.uniform(15, 60), rng.uniform(8, 30), rng.uniform(0, np.pi)
            dy, dx = _wrapped(yy - cy, wh), _wrapped(xx - cx, ww)
            u = (dx * np.cos(angle) + dy * np.sin(angle)) / a
            v = (-dx * np.sin(angle) + dy * np.cos(angle)) / b
            inside = u * u + v * v <= 1
            world[inside] = _SKIN[rng.integers(len(_SKIN))] * rng.uniform(0.85, 1.1)
        self.world = np.clip(world, 0, 255)

    def _hands(self, rng: np.random.Generator, n: int) -> None:
        """Each hand's look (size, shape, skin, sleeve) and its path: key positions at key times,
        held (the hand rests) or eased between (it moves); some keys lie outside the frame (it
        leaves and comes back)."""
        h, w = self.height, self.width
        self.hand = []
        for _ in range(n):
            size = rng.uniform(9, 28)  # palm half-length, px: hands of 25 to 100 px
            palm = np.array([size, size * rng.uniform(0.6, 0.85)])
            fingers = int(rng.choice([3, 4, 5], p=[0.15, 0.25, 0.6]))
            skin = _SKIN[rng.integers(len(_SKIN))] * rng.uniform(0.9, 1.08, 3)
            keys_t, keys_p = [0.0], [rng.uniform([0.1, 0.15], [0.9, 0.9]) * [w, h]]
            t = 0.0
            while t < self.seconds + 0.5:
                t += rng.uniform(0.15, 0.6)
                roll = rng.random()
                if roll < 0.3:  # rest
                    nxt = keys_p[-1]
                elif roll < 0.45:  # leave the frame across its nearest border
                    p = keys_p[-1]
                    side = int(np.argmin([p[0], w - p[0], p[1], h - p[1]]))
                    out = 2.5 * size + 5
                    nxt = np.array([-out, p[1]] if side == 0 else [w + out, p[1]] if side == 1 else
                                   [p[0], -out] if side == 2 else [p[0], h + out])
                else:  # move within the frame, 3 to 15 px a frame
                    step = rng.uniform(40, 150) * rng.choice([-1, 1], 2) * rng.uniform(0.4, 1.0, 2)
                    nxt = np.clip(keys_p[-1] + step, [0.05 * w, 0.1 * h], [0.95 * w, 0.95 * h])
                keys_t.append(t)
                keys_p.append(np.asarray(nxt, dtype=np.float64))
            self.hand.append({
                "palm": palm, "fingers": fingers, "skin": skin.astype(np.float32),
                "spread": rng.uniform(0.5, 1.0), "finger_width": rng.uniform(0.18, 0.3),
                "keys_t": np.array(keys_t), "keys_p": np.array(keys_p),
                "angle0": rng.uniform(0, 2 * np.pi), "spin": rng.uniform(-2.0, 2.0),
                "grip_freq": rng.uniform(0.3, 1.2), "grip_phase": rng.uniform(0, 2 * np.pi),
                "fist": rng.random() < 0.25,
                "sleeve": rng.uniform(30, 160, 3).astype(np.float32) if rng.random() < 0.5 else None,
            })

    # Geometry.

    def _position(self, hand: dict, t: float) -> np.ndarray:
        keys_t, keys_p = hand["keys_t"], hand["keys_p"]
        i = int(np.clip(np.searchsorted(keys_t, t, side="right") - 1, 0, len(keys_t) - 2))
        u = _ease((t - keys_t[i]) / (keys_t[i + 1] - keys_t[i]))
        return keys_p[i] + u * (keys_p[i + 1] - keys_p[i])

    def camera(self, t: float) -> np.ndarray:
        """Where the camera looks in the world at time ``t``: ``(x, y)`` offset in px."""
        sway = (self.sway_amp * np.sin(2 * np.pi * self.sway_freq * t + self.sway_phase)).sum(axis=0)
        tremor = self.tremor_amp * np.sin(2 * np.pi * self.tremor_freq * t + self.tremor_phase)
        return self.drift * t + sway + tremor

    def _parts(self, t: float):
        """Per hand, its ellipses ``(cx, cy, a, b, angle)`` (palm and fingers) and its sleeve, if any."""
        out = []
        for hand in self.hand:
            cx, cy = self._position(hand, t)
            angle = hand["angle0"] + hand["spin"] * np.sin(0.5 * t + hand["angle0"])
            a, b = hand["palm"]
            openness = 0.1 if hand["fist"] else 0.55 + 0.45 * np.sin(2 * np.pi * hand["grip_freq"] * t
                                                                      + hand["grip_phase"])
            parts = [(cx, cy, a, b, angle)]
            offsets = np.linspace(-0.55, 0.45, hand["fingers"] - 1)
            for j, offset in enumerate([*offsets, 1.25]):  # the last one is the thumb
                direction = angle + offset * hand["spread"] * (0.6 + 0.6 * openness)
                length = (0.75 if j == hand["fingers"] - 1 else 0.95) * a
                half = 0.5 * length * (0.4 + 0.6 * openness)
                reach = 0.8 * a + half
                parts.append((cx + reach * np.cos(direction), cy + reach * np.sin(direction), half,
                              hand["finger_width"] * b, direction))
            sleeve = None
            if hand["sleeve"] is not None:  # from the wrist away from the fingers, out of the frame
                back = angle + np.pi
                start = np.array([cx + 0.9 * a * np.cos(back), cy + 0.9 * a * np.sin(back)])
                sleeve = (start, start + 400 * np.array([np.cos(back), np.sin(back)]), 0.9 * b)
            out.append((parts, sleeve))
        return out

    def _occluder(self, t: float):
        o = self.occluder
        if o is None:
            return None
        centre = o["start"] + o["amp"] * np.sin(2 * np.pi * o["freq"] * t + o["phase"])
        return centre, o["size"]

    # Rendering.

    def paint(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W, 3)`` float32 RGB in digital numbers at time ``t`` (seconds), and an ``(H, W)``
        map of which hand (1, 2, ...) each pixel shows (0: none)."""
        h, w = self.height, self.width
        wh, ww = _WORLD
        ox, oy = self.camera(t)
        x0, y0 = int(np.floor(ox)), int(np.floor(oy))
        fx, fy = ox - x0, oy - y0
        cols, rows = (np.arange(x0, x0 + w + 1) % ww), (np.arange(y0, y0 + h + 1) % wh)
        patch = self.world[rows[:, None], cols[None, :]]  # (h + 1, w + 1, 3)
        image = ((1 - fy) * ((1 - fx) * patch[:-1, :-1] + fx * patch[:-1, 1:])
                 + fy * ((1 - fx) * patch[1:, :-1] + fx * patch[1:, 1:]))
        owner = np.zeros((h, w), np.int32)
        for index, ((parts, sleeve), hand) in enumerate(zip(self._parts(t), self.hand), start=1):
            if sleeve is not None:
                self._capsule(image, owner, *sleeve, hand["sleeve"])
            for cx, cy, a, b, angle in parts:
                self._ellipse(image, owner, cx, cy, a, b, angle, hand["skin"], index)
        occluder = self._occluder(t)
        if occluder is not None:
            (cx, cy), (hw, hh) = occluder
            c0, c1 = max(int(cx - hw), 0), min(int(np.ceil(cx + hw)), w)
            r0, r1 = max(int(cy - hh), 0), min(int(np.ceil(cy + hh)), h)
            if c0 < c1 and r0 < r1:
                image[r0:r1, c0:c1] = self.occluder["colour"]
                owner[r0:r1, c0:c1] = 0
        slow = 0.8 + 0.2 * np.sin(2 * np.pi * self.light_freq * t + self.light_phase)
        flicker = 1 + self.flicker_amp * self.flicker_shape * np.sin(2 * np.pi * self.flicker_freq * t
                                                                     + self.flicker_phase)
        return np.clip(image * slow * flicker, 0, 255).astype(np.float32), owner

    def _ellipse(self, image, owner, cx, cy, a, b, angle, colour, index) -> None:
        painted = paint_ellipse(image, self.xx, self.yy, (cx, cy, a, b, angle), colour)
        if painted is not None:
            rows, cols, inside = painted
            owner[rows, cols][inside] = index

    def _capsule(self, image, owner, start, end, radius, colour) -> None:
        h, w = owner.shape
        lo, hi = np.minimum(start, end) - radius, np.maximum(start, end) + radius
        c0, c1 = max(int(lo[0]), 0), min(int(np.ceil(hi[0])) + 1, w)
        r0, r1 = max(int(lo[1]), 0), min(int(np.ceil(hi[1])) + 1, h)
        if c0 >= c1 or r0 >= r1:
            return
        px, py = self.xx[r0:r1, c0:c1] - start[0], self.yy[r0:r1, c0:c1] - start[1]
        d = end - start
        s = np.clip((px * d[0] + py * d[1]) / float(d @ d), 0, 1)
        inside = (px - s * d[0]) ** 2 + (py - s * d[1]) ** 2 <= radius ** 2
        image[r0:r1, c0:c1][inside] = colour
        owner[r0:r1, c0:c1][inside] = 0

    def render(self, t: float) -> np.ndarray:
        return self.paint(t)[0]

    def frame(self, k: int) -> np.ndarray:
        return self.render(k / self.fps)

    def between(self, k: int, alpha: float) -> np.ndarray:
        return self.render((k + alpha) / self.fps)

    def boxes(self, k: int) -> np.ndarray:
        """``(M, 4)`` xywh around the visible pixels of each hand at frame ``k`` (hands showing at
        least ``MIN_VISIBLE_PIXELS`` pixels and ``MIN_BOX_SIZE`` px each way)."""
        return boxes_of([corners for _, corners in self._visible(self.paint(k / self.fps)[1])], MIN_BOX_SIZE)

    def luma_contrasts(self, k: int, *, margin: int = 6, threshold: float = DVSParams.pos_threshold,
                       lin_log_dn: float = DVSParams.lin_log_dn) -> np.ndarray:
        """``(M,)`` each boxed hand's luma contrast with what lies around it at frame ``k``, in the
        order of :meth:`boxes`: ``|ln(L_hand / L_around)| / threshold``, where ``L_hand`` is the mean
        BT.601 luma of the pixels painted as the hand and ``L_around`` that of the pixels showing no
        hand within ``margin`` px of its box, each at least ``lin_log_dn`` (the emulator's lin-log
        joint). A DVS pixel sees log luma, not colour: a hand's edge fires about this many events a
        pixel as it passes (the presets' threshold, 0.2), so a hand under one threshold
        is nearly invisible to the events however its colour differs. NaN where fewer than
        ``MIN_VISIBLE_PIXELS`` pixels lie around it."""
        image, owner = self.paint(k / self.fps)
        luma = np.maximum(image @ LUMA_WEIGHTS.astype(np.float32), lin_log_dn)
        out = []
        for index, (x1, y1, x2, y2) in self._visible(owner):
            if not len(boxes_of([(x1, y1, x2, y2)], MIN_BOX_SIZE)):
                continue  # a hand without a box
            y0, y3, x0, x3 = max(y1 - margin, 0), y2 + margin, max(x1 - margin, 0), x2 + margin
            around = owner[y0:y3, x0:x3] == 0
            if around.sum() < MIN_VISIBLE_PIXELS:
                out.append(np.nan)
                continue
            hand = luma[y1:y2, x1:x2][owner[y1:y2, x1:x2] == index].mean()  # its box holds all its pixels
            out.append(abs(np.log(hand / luma[y0:y3, x0:x3][around].mean())) / threshold)
        return np.asarray(out, dtype=np.float64)

    def _visible(self, owner: np.ndarray) -> list[tuple[int, tuple[int, int, int, int]]]:
        """``(hand index, (x1, y1, x2, y2))`` of each hand showing at least ``MIN_VISIBLE_PIXELS`` pixels."""
        out = []
        for index in range(1, len(self.hand) + 1):
            rows, cols = np.nonzero(owner == index)
            if len(rows) >= MIN_VISIBLE_PIXELS:
                out.append((index, (int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1)))
        return out


def generate_ego(out: Path | str, *, seconds: float = EGO_SECONDS, splits: Splits | None = None,
                 seed: int = 0, upsample: int = EGO_UPSAMPLE, dvs_model: str = EGO_DVS_MODEL,
                 compression: str | None = "blosc", progress: bool = True, workers: int | None = None) -> Path:
    """Write the ego dataset to ``out``; videos are ``ego_000``, ``ego_001``, ... in split order.

    ``dvs_model``: ``mixed`` (each video clean or noisy by a draw on its name), ``clean`` or
    ``noisy`` (every video; the same scenes, for measuring mixed training). ``splits``:
    :func:`~dagr_lite.synth.stub.split_of_videos`; ``workers``: processes
    (:func:`~dagr_lite.synth.stub.write_scenes`)."""
    if dvs_model not in ("clean", "noisy", "mixed"):
        raise UserError(f"dvs_model must be clean, noisy or mixed, got {dvs_model!r}")
    return write_scenes(out, partial(scene_at, EgoScene, seed, seconds), "ego", splits or EGO_SPLITS,
                        lambda video: choose_dvs_model(video, seed=seed) if dvs_model == "mixed" else dvs_model,
                        upsample=upsample, seed=seed, compression=compression, progress=progress,
                        workers=workers)
