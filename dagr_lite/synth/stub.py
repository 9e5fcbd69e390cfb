"""A small deterministic EventEgoHands-like dataset for tests and the default run.

Skin-toned elliptical "hands" move and rotate over a textured background; frames are rendered
at 30 fps and events come from log-intensity changes between finely spaced sub-frames
(a change of one contrast threshold gives one event, timestamps spread across the
sub-frame interval). Boxes are the exact extents of the visible hands at each frame.
Everything is written with :mod:`dagr_lite.data.writer`, in the release layout.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import zoom as nd_zoom
from tqdm import tqdm

from dagr_lite.data import format as fmt
from dagr_lite.data.writer import write_labels, write_video

# Bump when the generated data changes, so caches made by an older recipe are not reused.
STUB_VERSION = 1
STUB_HEIGHT, STUB_WIDTH = 180, 320
STUB_SPLITS = {"train": 4, "valid": 1, "test": 1}
STUB_SECONDS = 3.0
STUB_UPSAMPLE = 5
CONTRAST_THRESHOLD = 0.2


def default_cache_dir() -> Path:
    """Folder for generated data: ``$DAGR_LITE_CACHE`` or ``~/.cache/dagr_lite``."""
    return Path(os.environ.get("DAGR_LITE_CACHE", Path.home() / ".cache" / "dagr_lite"))


def stub_root(cache_dir: Path | str | None = None) -> Path:
    """The stub dataset, generated on first use into the cache folder (atomically)."""
    root = Path(cache_dir or default_cache_dir()) / f"stub-v{STUB_VERSION}"
    if root.is_dir():
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=root.name + ".tmp", dir=root.parent))
    print(f"generating the stub dataset into {root} (once)", flush=True)
    try:
        generate_stub(tmp)
        os.rename(tmp, root)
    except OSError:
        if not root.is_dir():
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


class _Scene:
    """Hands (ellipses) over a textured background, rendered at any time ``t`` in seconds."""

    def __init__(self, rng: np.random.Generator, height: int, width: int):
        self.height, self.width = height, width
        texture = nd_zoom(rng.random((height // 12 + 4, width // 12 + 4, 3)), (12, 12, 1), order=1)
        self.background = (0.25 + 0.5 * texture[: height + 24, : width + 24]).astype(np.float32)
        self.num_hands = int(rng.integers(2, 4))
        self.centre = rng.uniform([0.15 * width, 0.2 * height], [0.85 * width, 0.8 * height], (self.num_hands, 2))
        self.velocity = rng.uniform(-60, 60, (self.num_hands, 2))  # px/s
        self.wobble = rng.uniform(10, 40, (self.num_hands, 2))  # px
        self.freq = rng.uniform(0.3, 1.2, (self.num_hands, 1))  # Hz
        self.axes = rng.uniform([14, 9], [30, 18], (self.num_hands, 2))  # semi-axes, px
        self.spin = rng.uniform(-1.5, 1.5, self.num_hands)  # rad/s
        self.angle0 = rng.uniform(0, np.pi, self.num_hands)
        self.colour = rng.uniform([0.75, 0.5, 0.4], [0.95, 0.7, 0.55], (self.num_hands, 3)).astype(np.float32)
        self.shake = rng.uniform(2, 6)
        self.yy, self.xx = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5

    def hands(self, t: float):
        centre = self.centre + self.velocity * t + self.wobble * np.sin(2 * np.pi * self.freq * t)
        centre = np.stack([np.mod(centre[:, 0], self.width * 1.3) - 0.15 * self.width,
                           np.clip(centre[:, 1], 0, self.height)], axis=1)
        opening = 1 + 0.25 * np.sin(2 * np.pi * self.freq[:, 0] * 1.7 * t)
        axes = self.axes * np.stack([opening, np.ones_like(opening)], axis=1)
        return centre, axes, self.angle0 + self.spin * t

    def render(self, t: float) -> np.ndarray:
        """``(H, W, 3)`` float32 RGB in [0, 1]."""
        dx, dy = (np.round(12 + self.shake * np.sin([3.1 * t, 2.3 * t + 1])).astype(int))
        image = self.background[dy: dy + self.height, dx: dx + self.width].copy()
        image *= 0.85 + 0.15 * np.sin(0.9 * t)  # slow brightness change
        for (cx, cy), (a, b), angle, colour in zip(*self.hands(t), self.colour):
            # Only the pixels of the hand's bounding square can change.
            x0, x1 = max(int(cx - a) - 1, 0), min(int(cx + a) + 2, self.width)
            y0, y1 = max(int(cy - a) - 1, 0), min(int(cy + a) + 2, self.height)
            if x0 >= x1 or y0 >= y1:
                continue
            xx, yy = self.xx[y0:y1, x0:x1] - cx, self.yy[y0:y1, x0:x1] - cy
            u = xx * np.cos(angle) + yy * np.sin(angle)
            v = -xx * np.sin(angle) + yy * np.cos(angle)
            r = (u / a) ** 2 + (v / b) ** 2
            shade = (1.0 - 0.3 * np.clip(r, 0, 1))[..., None] * colour
            image[y0:y1, x0:x1] = np.where((r <= 1)[..., None], shade, image[y0:y1, x0:x1])
        return image

    def boxes(self, t: float) -> np.ndarray:
        """``(M, 4)`` xywh of the visible hands at time ``t``."""
        out = []
        for (cx, cy), (a, b), angle in zip(*self.hands(t)):
            hx = np.sqrt((a * np.cos(angle)) ** 2 + (b * np.sin(angle)) ** 2)
            hy = np.sqrt((a * np.sin(angle)) ** 2 + (b * np.cos(angle)) ** 2)
            x1, y1 = max(cx - hx, 0.0), max(cy - hy, 0.0)
            x2, y2 = min(cx + hx, self.width), min(cy + hy, self.height)
            if x2 - x1 >= 3 and y2 - y1 >= 3:
                out.append([x1, y1, x2 - x1, y2 - y1])
        return np.asarray(out, dtype=np.float64).reshape(-1, 4)


def _log_luma(rgb: np.ndarray) -> np.ndarray:
    luma = rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return np.log(luma * 255.0 + 1.0)


def simulate_video(seed: int, *, num_frames: int, height: int = STUB_HEIGHT, width: int = STUB_WIDTH,
                   fps: float = fmt.DEFAULT_FPS, upsample: int = STUB_UPSAMPLE):
    """Frames (uint8), events (x, y, t, p) and per-frame xywh boxes of one synthetic video."""
    rng = np.random.default_rng(seed)
    scene = _Scene(rng, height, width)
    frames, boxes, chunks = [], {}, []
    memory = _log_luma(scene.render(0.0))
    t_prev = 0
    for k in range(num_frames):
        frames.append((scene.render(k / fps) * 255).round().astype(np.uint8))
        boxes[k] = scene.boxes(k / fps)
        if k == num_frames - 1:
            break
        for j in range(1, upsample + 1):
            t_now = fmt.frame_time_us(k, fps) + round((1e6 / fps) * j / upsample)
            change = _log_luma(scene.render(t_now * 1e-6)) - memory
            count = np.minimum(np.floor(np.abs(change) / CONTRAST_THRESHOLD), 8).astype(np.int64)
            memory += np.sign(change) * count * CONTRAST_THRESHOLD
            ys, xs = np.nonzero(count)
            n = count[ys, xs]
            rep = np.repeat(np.arange(len(n)), n)
            order = np.arange(len(rep)) - np.repeat(np.cumsum(n) - n, n)  # j-th event of its pixel
            t = t_prev + ((order + 1) / (n[rep] + 1) * (t_now - t_prev)).astype(np.int64)
            p = (change[ys, xs] > 0).astype(np.uint8)[rep]
            sort = np.argsort(t, kind="stable")
            chunks.append((xs[rep][sort], ys[rep][sort], t[sort], p[sort]))
            t_prev = t_now
    x, y, t, p = (np.concatenate(c) for c in zip(*chunks)) if chunks else (np.zeros(0, np.int64),) * 4
    return frames, {"x": x, "y": y, "t": t, "p": p}, boxes


def generate_stub(out: Path | str, *, seconds: float = STUB_SECONDS, splits: dict[str, int] | None = None,
                  seed: int = 0, compression: str | None = "blosc") -> Path:
    """Write the stub dataset to ``out`` (must not hold a dataset already)."""
    out = Path(out)
    num_frames = int(round(seconds * fmt.DEFAULT_FPS))
    jobs = [split for split, count in (splits or STUB_SPLITS).items() for _ in range(count)]
    labels = {}
    for index, split in enumerate(tqdm(jobs, desc="stub videos", unit="video")):
        video = f"stub_{index:03d}"
        frames, events, boxes = simulate_video(seed * 1000 + index, num_frames=num_frames)
        write_video(out, split, video, events=events, frames=frames, compression=compression)
        labels[video] = boxes
    write_labels(out, labels)
    return out
