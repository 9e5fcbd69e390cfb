"""The stub dataset: small, deterministic, EventEgoHands-like, made by the dataset pipeline itself.

Synthetic egocentric scenes: two to four skin-toned hands (a palm and five fingers each) that
move fast, rotate, open and close, overlap, and leave and re-enter the frame, over a textured
background with camera shake and a slowly changing brightness. Frames are rendered at 30 fps;
the DVS emulator (:mod:`dagr_lite.synth.dvs`) runs over ``STUB_UPSAMPLE`` steps per frame
interval, the scene itself rendering the in-between frames exactly; frames, events and a box
per visible hand per frame are written in the release layout by the same code as any other
dataset (:func:`dagr_lite.synth.video.emulate_video`).
"""
from __future__ import annotations

import multiprocessing
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.ndimage import zoom as nd_zoom

from dagr_lite.data import format as fmt
from dagr_lite.data.writer import VideoWriter, write_labels
from dagr_lite.graph.compiled import threads_for
from dagr_lite.progress import progress_bar
from dagr_lite.synth.dvs import preset
from dagr_lite.synth.video import emulate_video

# Bump when the generated data changes, so caches made by an older recipe are not reused.
STUB_VERSION = 4          # 4: version 3's scenes, each event at the moment its pixel's level crosses it
                          # (synth.dvs), not at the middle of the emulator's step
STUB_HEIGHT, STUB_WIDTH = 180, 320
STUB_SPLITS = {"train": 12, "valid": 2, "test": 2}
STUB_SECONDS = 2.0
STUB_UPSAMPLE = 6
STUB_DVS_MODEL = "clean"
MIN_BOX_SIZE = 4.0
SHAKE_MARGIN = 8


def default_cache_dir() -> Path:
    """Folder for generated data: ``$DAGR_LITE_CACHE`` or ``~/.cache/dagr_lite``."""
    return Path(os.environ.get("DAGR_LITE_CACHE", Path.home() / ".cache" / "dagr_lite"))


def stub_root(cache_dir: Path | str | None = None) -> Path:
    """The stub dataset, generated on first use into the cache folder (atomically)."""
    return cached_dataset(f"stub-v{STUB_VERSION}", generate_stub, "stub", cache_dir)


def cached_dataset(folder: str, generate: Callable[[Path], Path], label: str,
                   cache_dir: Path | str | None = None) -> Path:
    """``<cache>/<folder>``, made by ``generate(tmp)`` on first use and renamed into place, so a
    half-written dataset is never read and two processes making it at once both end with one copy."""
    root = Path(cache_dir or default_cache_dir()) / folder
    if root.is_dir():
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=root.name + ".tmp", dir=root.parent))
    print(f"generating the {label} dataset into {root} (once)", flush=True)
    try:
        generate(tmp)
        os.rename(tmp, root)
    except OSError:
        if not root.is_dir():  # another process finished first: use its copy
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


# Finger layout of a hand: angle from the hand's axis (rad), length and width relative to the palm.
_FINGERS = ((-0.55, 0.9, 0.22), (-0.2, 1.05, 0.22), (0.12, 1.0, 0.22), (0.42, 0.85, 0.2), (1.2, 0.75, 0.25))


def paint_ellipse(image: np.ndarray, xx: np.ndarray, yy: np.ndarray, ellipse: tuple, colour: np.ndarray
                  ) -> tuple[slice, slice, np.ndarray] | None:
    """Paint ellipse ``(cx, cy, a, b, angle)`` (centre, semi-axes in px, angle in rad) into the
    ``(H, W, 3)`` ``image`` in ``colour``, shaded darker towards its rim (a rounded look); ``xx``,
    ``yy``: the pixel centres. Returns the painted pixels as ``(rows, cols, inside)`` (None when
    the ellipse lies outside the image)."""
    cx, cy, a, b, angle = ellipse
    h, w = image.shape[:2]
    ex, ey = HandScene._extent(a, b, angle)
    c0, c1 = max(int(cx - ex) - 1, 0), min(int(cx + ex) + 2, w)
    r0, r1 = max(int(cy - ey) - 1, 0), min(int(cy + ey) + 2, h)
    if c0 >= c1 or r0 >= r1:
        return None
    dx, dy = xx[r0:r1, c0:c1] - cx, yy[r0:r1, c0:c1] - cy
    u = (dx * np.cos(angle) + dy * np.sin(angle)) / a
    v = (-dx * np.sin(angle) + dy * np.cos(angle)) / b
    r = u * u + v * v
    inside = r <= 1
    shade = colour * (0.7 + 0.3 * (1 - r[..., None]))
    image[r0:r1, c0:c1][inside] = shade[inside]
    return slice(r0, r1), slice(c0, c1), inside


class HandScene:
    """A synthetic egocentric scene, rendered at any time ``t`` (seconds).

    Implements the frame-source interface of :mod:`dagr_lite.synth.video`.
    """

    def __init__(self, seed: int, *, height: int = STUB_HEIGHT, width: int = STUB_WIDTH, seconds: float = STUB_SECONDS,
                 fps: float = fmt.DEFAULT_FPS):
        rng = np.random.default_rng([seed])
        self.height, self.width, self.fps = height, width, fps
        self.num_frames = int(round(seconds * fps))
        # Background: two scales of smooth noise in non-skin colours, larger than the frame for the shake.
        big = (height + 2 * SHAKE_MARGIN, width + 2 * SHAKE_MARGIN)
        coarse = nd_zoom(rng.random((big[0] // 30 + 2, big[1] // 30 + 2)), 30, order=3)[: big[0], : big[1]]
        fine = nd_zoom(rng.random((big[0] // 6 + 2, big[1] // 6 + 2)), 6, order=1)[: big[0], : big[1]]
        tint = rng.uniform([0.25, 0.35, 0.4], [0.45, 0.55, 0.7])
        pattern = np.clip(0.55 * coarse + 0.45 * fine, 0, 1)[..., None]
        self.background = (tint * (0.5 + 0.8 * pattern) * 255).astype(np.float32)  # (H + 2m, W + 2m, 3)
        self.shake_amp = rng.uniform(1.0, 3.0, 2)
        self.shake_freq = rng.uniform(1.5, 4.0, 2)
        self.light_freq, self.light_phase = rng.uniform(0.2, 0.6), rng.uniform(0, 2 * np.pi)
        # Hands.
        n = int(rng.integers(2, 5))
        self.palm = rng.uniform([14, 10], [22, 15], (n, 2))  # palm semi-axes, px
        margin = 2.2 * self.palm[:, 0]
        self.span = np.stack([width + 2 * margin, height + 2 * margin], 1)  # wrap-around period, px
        self.margin = margin
        self.start = rng.uniform(0, 1, (n, 2)) * self.span
        speed = rng.uniform(90, 320, n)  # px/s: 3 to 11 px per frame
        heading = rng.uniform(0, 2 * np.pi, n)
        self.velocity = np.stack([np.cos(heading), 0.45 * np.sin(heading)], 1) * speed[:, None]
        self.wobble = rng.uniform(5, 25, (n, 2))
        self.wobble_freq = rng.uniform(0.5, 2.0, (n, 1))
        self.angle0, self.spin = rng.uniform(0, 2 * np.pi, n), rng.uniform(-2.5, 2.5, n)
        self.grip_freq, self.grip_phase = rng.uniform(0.4, 1.5, n), rng.uniform(0, 2 * np.pi, n)
        self.skin = rng.uniform([200, 140, 110], [245, 190, 160], (n, 3)).astype(np.float32)
        self.yy, self.xx = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5

    # Geometry.

    def _hands(self, t: float):
        pos = self.start + self.velocity * t + self.wobble * np.sin(2 * np.pi * self.wobble_freq * t)
        pos = np.mod(pos, self.span) - self.margin[:, None]  # leaves one side, re-enters the other
        angle = self.angle0 + self.spin * t
        openness = 0.55 + 0.45 * np.sin(2 * np.pi * self.grip_freq * t + self.grip_phase)  # 0.1 .. 1
        return pos, angle, openness

    def _ellipses(self, t: float):
        """Per hand, a list of ellipses ``(cx, cy, a, b, angle)``: the palm and five fingers."""
        out = []
        for (cx, cy), angle, openness, (a, b) in zip(*self._hands(t), self.palm):
            parts = [(cx, cy, a, b, angle)]
            for offset, length, width in _FINGERS:
                direction = angle + offset * (0.6 + 0.6 * openness)
                half = 0.5 * length * a * (0.45 + 0.55 * openness)
                reach = 0.8 * a + half
                parts.append((cx + reach * np.cos(direction), cy + reach * np.sin(direction), half,
                              width * b, direction))
            out.append(parts)
        return out

    @staticmethod
    def _extent(a: float, b: float, angle: float) -> tuple[float, float]:
        return (float(np.hypot(a * np.cos(angle), b * np.sin(angle))),
                float(np.hypot(a * np.sin(angle), b * np.cos(angle))))

    # Rendering.

    def render(self, t: float) -> np.ndarray:
        """``(H, W, 3)`` float32 RGB in digital numbers at time ``t`` (seconds)."""
        h, w, m = self.height, self.width, SHAKE_MARGIN
        shake = self.shake_amp * np.sin(2 * np.pi * self.shake_freq * t + np.array([0.0, 1.3]))
        ox, oy = m + shake[0], m + shake[1]
        x0, y0 = int(np.floor(ox)), int(np.floor(oy))
        fx, fy = ox - x0, oy - y0
        bg = self.background
        image = ((1 - fy) * ((1 - fx) * bg[y0:y0 + h, x0:x0 + w] + fx * bg[y0:y0 + h, x0 + 1:x0 + 1 + w])
                 + fy * ((1 - fx) * bg[y0 + 1:y0 + 1 + h, x0:x0 + w] + fx * bg[y0 + 1:y0 + 1 + h, x0 + 1:x0 + 1 + w]))
        for parts, skin in zip(self._ellipses(t), self.skin):
            for ellipse in parts:
                paint_ellipse(image, self.xx, self.yy, ellipse, skin)
        gain = 0.8 + 0.2 * np.sin(2 * np.pi * self.light_freq * t + self.light_phase)
        return np.clip(image * gain, 0, 255)

    def frame(self, k: int) -> np.ndarray:
        return self.render(k / self.fps)

    def between(self, k: int, alpha: float) -> np.ndarray:
        return self.render((k + alpha) / self.fps)

    def boxes(self, k: int) -> np.ndarray:
        """``(M, 4)`` xywh of the hands visible at frame ``k`` (at least ``MIN_BOX_SIZE`` px each way)."""
        corners = []
        for parts in self._ellipses(k / self.fps):
            extents = [(cx - ex, cy - ey, cx + ex, cy + ey)
                       for cx, cy, a, b, angle in parts for ex, ey in [self._extent(a, b, angle)]]
            x1, y1 = max(min(e[0] for e in extents), 0.0), max(min(e[1] for e in extents), 0.0)
            corners.append((x1, y1, min(max(e[2] for e in extents), float(self.width)),
                            min(max(e[3] for e in extents), float(self.height))))
        return boxes_of(corners, MIN_BOX_SIZE)


def boxes_of(corners, least: float) -> np.ndarray:
    """``(M, 4)`` xywh of the boxes of ``corners`` ``(x1, y1, x2, y2)`` at least ``least`` px each way."""
    out = [[x1, y1, x2 - x1, y2 - y1] for x1, y1, x2, y2 in corners if x2 - x1 >= least and y2 - y1 >= least]
    return np.asarray(out, dtype=np.float64).reshape(-1, 4)


def generate_stub(out: Path | str, *, seconds: float = STUB_SECONDS, splits: Splits | None = None,
                  seed: int = 0, upsample: int = STUB_UPSAMPLE, dvs_model: str = STUB_DVS_MODEL,
                  compression: str | None = "blosc", progress: bool = True, workers: int | None = None) -> Path:
    """Write the stub dataset to ``out``; videos are ``stub_000``, ``stub_001``, ... in split order
    (``workers``: processes, :func:`write_scenes`)."""
    return write_scenes(out, partial(scene_at, HandScene, seed, seconds), "stub", splits or STUB_SPLITS,
                        lambda video: dvs_model, upsample=upsample, seed=seed, compression=compression,
                        progress=progress, workers=workers)


Splits = Mapping[str, int] | Sequence[tuple[str, int]]


def split_of_videos(splits: Splits) -> list[str]:
    """The split of each video in index order. ``splits``: ``{split: count}`` in its order, or
    segments ``[(split, count), ...]`` in which a split may come back, so a later version of a
    dataset can add videos after the others without renaming (and so changing) any of them."""
    segments = list(splits.items()) if isinstance(splits, Mapping) else list(splits)
    jobs = []
    for segment in segments:
        if len(segment) != 2 or segment[0] not in fmt.SPLITS or int(segment[1]) < 0:
            raise ValueError(f"splits: each entry is (split, count) with split one of {fmt.SPLITS} and count >= 0, "
                             f"got {segment!r}")
        jobs += [segment[0]] * int(segment[1])
    return jobs


def scene_at(scene_class: type, seed: int, seconds: float, index: int):
    """Video ``index``'s scene of a generator seeded by ``seed``: ``scene_class(seed * 1000 + index)``.
    A module-level function, so ``partial(scene_at, ...)`` reaches generation's worker processes."""
    return scene_class(seed * 1000 + index, seconds=seconds)


def generation_workers(videos: int, workers: int | None) -> int:
    """Processes that write ``videos`` videos: ``workers``, or with None one per CPU core this
    process may use, with at least two videos each (fewer videos are written in this process)."""
    if workers is not None:
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        return min(workers, max(videos, 1))
    return max(1, min(threads_for(None), videos // 2))


def _write_video(out: Path, split: str, video: str, index: int, scene_of: Callable[[int], "HandScene"],
                 dvs_model: str, upsample: int, seed: int, compression: str | None) -> tuple[str, dict]:
    scene = scene_of(index)
    with VideoWriter(out, split, video, num_frames=scene.num_frames, height=scene.height, width=scene.width,
                     compression=compression) as writer:
        emulate_video(scene, writer, params=preset(dvs_model), upsample=upsample, seed=seed * 1000 + index)
    return video, {k: scene.boxes(k) for k in range(scene.num_frames)}


def write_scenes(out: Path | str, scene_of: Callable[[int], "HandScene"], prefix: str, splits: Splits,
                 dvs_model_of: Callable[[str], str], *, upsample: int, seed: int, compression: str | None,
                 progress: bool, workers: int | None = None) -> Path:
    """Render, emulate and write one synthetic scene per video, ``<prefix>_000``, ... in split order
    (``scene_of(index)``, a frame source with ``boxes(k)``), each with the DVS preset
    ``dvs_model_of(video)``, and every frame's boxes as the labels.

    ``splits``: see :func:`split_of_videos`. Videos are written by :func:`generation_workers`
    processes, started fresh (never forked from this one, which may hold torch's threads), so
    ``scene_of`` must pickle, as ``partial(scene_at, ...)`` does. Each video depends on its index
    alone: the dataset is the same for any number of workers."""
    out = Path(out)
    jobs = [(split, f"{prefix}_{index:03d}", index) for index, split in enumerate(split_of_videos(splits))]
    write = partial(_write_video, out, scene_of=scene_of, upsample=upsample, seed=seed, compression=compression)
    bar = progress_bar(total=len(jobs), desc=f"{prefix} videos", unit="video", disable=not progress)
    labels = {}
    count = generation_workers(len(jobs), workers)
    if count == 1:
        for split, video, index in jobs:
            labels.update([write(split, video, index, dvs_model=dvs_model_of(video))])
            bar.update(1)
    else:
        with ProcessPoolExecutor(count, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(write, split, video, index, dvs_model=dvs_model_of(video))
                       for split, video, index in jobs]
            try:
                for future in futures:  # in index order
                    labels.update([future.result()])
                    bar.update(1)
            except BaseException:  # a failed video or Ctrl-C: the videos not yet started are not written
                for future in futures:
                    future.cancel()
                raise
    bar.close()
    write_labels(out, {video: labels[video] for _, video, _ in jobs})
    return out
