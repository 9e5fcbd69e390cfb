"""Run the streaming detector over one recording and write a video a person can play.

    python -m dagr_lite.apps.demo ckpt=runs/train/<run>/checkpoints/best.pt [video=<name>] [split=test]
        [rate_hz=300] [out=runs/demo/<date>/<time>/<video>.webp] [seconds=null] [dataset=...]

Images reach the detector at the camera's rate, events in updates of ``1 / rate_hz`` seconds,
and the detector answers after every update. Each frame of the animation (WebP or GIF, by the
file's suffix) shows the latest image with the current boxes beside the last ``events_ms`` of
events with the same boxes, and the time, the image's age and the update's latency. A PNG strip
beside it (``<out>.strip.png``) shows ``strip_moments`` moments between two frames.
"""
from __future__ import annotations

import os
import time
from datetime import datetime
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from dagr_lite.camera.render import render_moment
from dagr_lite.apps.cli import hydra_command
from dagr_lite.config import ConfigError, check_values, dataset_root
from dagr_lite.data import format as fmt
from dagr_lite.data.events import EventFile
from dagr_lite.data.frames import list_frames, read_frame
from dagr_lite.data.labels import list_videos
from dagr_lite.data.writer import temporary_name
from dagr_lite.engine.runs import resolve_device
from dagr_lite.progress import progress_bar
from dagr_lite.stream import StreamingDetector

FORMATS = {".webp": "WEBP", ".gif": "GIF"}


class Recording:
    """One video of a dataset split: its events, frames and frame times."""

    def __init__(self, root: Path, split: str, video: str | None):
        videos = list_videos(root, split)
        if not videos:
            raise ConfigError(f"{root / split}: no videos in this split")
        self.video = video or videos[0]
        if self.video not in videos:
            raise ConfigError(f"video={self.video!r} is not in {root / split} (it holds {videos})")
        frames_dir = fmt.frames_dir(root, split, self.video)
        count = len(list_frames(frames_dir))
        file = EventFile(fmt.events_path(root, split, self.video), num_frames=count)
        try:
            self.frame_times = np.asarray(file.frame_times, dtype=np.int64)
            raw = file.window(0, int(self.frame_times[-1]) + 1)
        finally:
            file.close()
        self.events = {key: np.asarray(raw[key]) for key in ("x", "y", "t", "p")}
        self.frames = [read_frame(fmt.frame_path(root, split, self.video, k)) for k in range(count)]

    @property
    def height(self) -> int:
        return self.frames[0].shape[0]

    @property
    def width(self) -> int:
        return self.frames[0].shape[1]

    def events_between(self, t_a: float, t_b: float) -> dict[str, np.ndarray]:
        t = self.events["t"]
        part = slice(int(np.searchsorted(t, t_a)), int(np.searchsorted(t, t_b)))
        return {key: values[part] for key, values in self.events.items()}


def check_output(out: Path) -> None:
    if out.suffix.lower() not in FORMATS:
        raise ConfigError(f"out={out}: the animation is written as {' or '.join(FORMATS)} (by its suffix)")
    for path in (out, strip_path(out)):
        if path.exists():
            raise ConfigError(f"{path} already exists; choose another out= (nothing is overwritten)")


def strip_path(out: Path) -> Path:
    return out.with_name(out.stem + ".strip.png")


def write_pictures(out: Path, frames: list, strip: list, playback_fps: float) -> Path:
    """The animation to ``out`` and the strip beside it (each written whole, then renamed); the strip's path."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(out)
    frames[0].save(tmp, format=FORMATS[out.suffix.lower()], save_all=True, append_images=frames[1:],
                   duration=round(1000 / playback_fps), loop=0)
    os.replace(tmp, out)
    strip_file = strip_path(out)
    tmp = temporary_name(strip_file)
    Image.fromarray(np.concatenate(strip, axis=0)).save(tmp, format="PNG")
    os.replace(tmp, strip_file)
    return strip_file


def demo(cfg: DictConfig) -> dict:
    """Stream one recording through the detector; write the animation and the strip. Returns their
    paths and the update latencies (seconds)."""
    print(OmegaConf.to_yaml(cfg), flush=True)
    check_values(cfg)
    if cfg.out is not None and Path(cfg.out).suffix.lower() not in FORMATS:  # before the work below
        check_output(Path(cfg.out))
    rec = Recording(dataset_root(cfg.dataset), cfg.split, cfg.video)
    stream = StreamingDetector.from_checkpoint(cfg.ckpt, device=resolve_device(cfg.device),
                                               score=cfg.operating.score, nms_iou=cfg.operating.nms_iou)
    # Like every run, a folder of its own unless out= is given: a second demo never meets the first's files.
    out = Path(cfg.out if cfg.out is not None else f"runs/demo/{datetime.now():%Y-%m-%d/%H-%M-%S-%f}/{rec.video}.webp")
    check_output(out)
    print(f"{cfg.ckpt}: answers at {stream.operating.describe()}", flush=True)
    if rec.frames[0].shape[:2] != (stream.height, stream.width):
        raise ConfigError(f"{cfg.ckpt}: the model takes {stream.width}x{stream.height} frames, the video "
                          f"{rec.video} has {rec.frames[0].shape[1]}x{rec.frames[0].shape[0]}")
    stream.warm_up()  # the compiled kernels ready before the first update's latency is taken
    step_us = 1e6 / cfg.rate_hz
    t_first = float(rec.frame_times[0])
    t_last = float(rec.frame_times[-1]) if cfg.seconds is None else min(float(rec.frame_times[-1]),
                                                                          t_first + 1e6 * cfg.seconds)
    k_strip = int(cfg.strip_frame) if cfg.strip_frame is not None else len(rec.frames) // 2
    if not 0 <= k_strip < len(rec.frames) - 1:
        raise ConfigError(f"strip_frame must be in [0, {len(rec.frames) - 2}], got {k_strip}")
    t_a, t_b = rec.frame_times[k_strip], rec.frame_times[k_strip + 1]
    strip_times = [t_a + (t_b - t_a) * j / cfg.strip_moments for j in range(cfg.strip_moments)]
    stops = sorted(set(np.arange(t_first + step_us, t_last + 1e-6, step_us).tolist()) | set(strip_times))
    frames, strip, latencies = [], [], []
    pushed_until, image_k = t_first, -1
    for now in progress_bar(stops, desc=f"streaming {rec.video} at {cfg.rate_hz:g} Hz", unit="update"):
        tic = time.perf_counter()
        while image_k + 1 < len(rec.frames) and rec.frame_times[image_k + 1] <= now:
            image_k += 1
            stream.push_image(rec.frames[image_k], rec.frame_times[image_k])
        stream.push_events(**rec.events_between(pushed_until, now))
        answer = stream.detect(now)
        latency = time.perf_counter() - tic
        pushed_until = now
        latencies.append(latency)
        age_ms = (now - rec.frame_times[image_k]) / 1e3
        caption = (f"t {(now - t_first) / 1e6:6.3f} s  image age {age_ms:5.1f} ms  "
                   f"update {1e3 * latency:5.1f} ms  {len(answer['boxes'])} hands")
        picture = render_moment(rec.frames[image_k], rec.events_between(now - 1e3 * cfg.events_ms, now),
                                answer["boxes"], answer["scores"], caption)
        if now in strip_times:
            strip.append(picture)
        else:
            frames.append(Image.fromarray(picture))
    strip_file = write_pictures(out, frames, strip, cfg.playback_fps)
    latency = np.array(latencies)
    print(f"{len(latency)} updates: {len(frames)} frames -> {out}; the strip's {len(strip)} moments, frame {k_strip} "
          f"to {k_strip + 1} -> {strip_file}\n"
          f"update latency: median {1e3 * np.median(latency):.1f} ms, p95 {1e3 * np.percentile(latency, 95):.1f} ms",
          flush=True)
    return {"out": out, "strip": strip_file, "latencies": latency}


main = hydra_command("demo", demo)


if __name__ == "__main__":
    main()
