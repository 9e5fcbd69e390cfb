"""From video frames to a dataset video: scaling, temporal upsampling and DVS emulation.

A frame source gives the frames of one video at its frame rate (``frame(k)``) and any moment
between two frames (``between(k, alpha)``). :func:`emulate_video` walks a source, runs the DVS
emulator on ``upsample - 1`` in-between frames per frame interval plus the frames themselves,
and streams frames and events into a :class:`~dagr_lite.data.writer.VideoWriter`.

v2e makes its in-between frames with the learned SuperSloMo interpolator. Its weights are not
shipped here: :class:`FolderSource` blends neighbouring frames linearly in intensity, and any
function with the signature of :func:`linear_interpolate` can replace that. Synthetic scenes
(the stub dataset) render the true in-between frames instead.
"""
from __future__ import annotations

import re
import zlib
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.frames import read_frame
from dagr_lite.data.writer import VideoWriter
from dagr_lite.synth.dvs import DVSEmulator, DVSParams

FRAME_SUFFIXES = (".jpg", ".jpeg", ".png")
Interpolator = Callable[[np.ndarray, np.ndarray, float], np.ndarray]


def linear_interpolate(frame_a: np.ndarray, frame_b: np.ndarray, alpha: float) -> np.ndarray:
    """``(1 - alpha) * a + alpha * b`` of two float RGB frames (linear in intensity)."""
    return (1.0 - alpha) * frame_a + alpha * frame_b


def downscale_area(frame: np.ndarray, scale: int) -> np.ndarray:
    """Area-average an ``(H, W, C)`` frame by an integer factor (float64 out).

    The output is ``(H // scale, W // scale)``; rows and columns beyond a multiple of ``scale``
    are dropped.
    """
    frame = np.asarray(frame, dtype=np.float64)
    if scale == 1:
        return frame
    if scale < 1 or int(scale) != scale:
        raise UserError(f"scale must be a positive integer, got {scale}")
    h, w = frame.shape[0] // scale, frame.shape[1] // scale
    if h == 0 or w == 0:
        raise UserError(f"a {frame.shape[1]}x{frame.shape[0]} frame is too small for scale {scale}")
    cropped = frame[: h * scale, : w * scale]
    return cropped.reshape(h, scale, w, scale, *frame.shape[2:]).mean(axis=(1, 3))


def scale_boxes(boxes_xywh: np.ndarray, scale: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of a ``scale``-times larger frame, in pixels of the scaled frame, clipped to it.

    Returns the boxes left with an area and the ``(M,)`` bool mask of which input boxes they are.
    """
    xyxy = fmt.xywh_to_xyxy(boxes_xywh) / scale
    xyxy = np.clip(xyxy, 0, [width, height, width, height])
    kept = (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])
    return fmt.xyxy_to_xywh(xyxy[kept]), kept


def to_uint8(frame: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


class FrameSource(Protocol):
    """The frames of one video: ``num_frames`` frames at ``fps``, each ``(height, width, 3)``."""

    num_frames: int
    height: int
    width: int

    def frame(self, k: int) -> np.ndarray:
        """Frame ``k`` as float RGB in digital numbers 0..255."""

    def between(self, k: int, alpha: float) -> np.ndarray:
        """The scene at ``alpha`` (0 < alpha < 1) of the way from frame ``k`` to frame ``k + 1``."""


def frame_number(path: Path) -> int | None:
    """The last number in a frame file's name (``frame_0012.jpg`` -> 12), or None."""
    numbers = re.findall(r"\d+", path.stem)
    return int(numbers[-1]) if numbers else None


def list_frame_files(folder: Path | str) -> list[Path]:
    """Image files of a frame folder in frame order (by the last number in each name).

    Accepts ``frame_<k>.jpg`` (the release), ``frame_0001.jpg`` (EgoHands) and similar names.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetFormatError.at(folder, "frame folder is missing")
    numbered = []
    for path in folder.iterdir():
        if path.suffix.lower() in FRAME_SUFFIXES:
            number = frame_number(path)
            if number is None:
                raise DatasetFormatError.at(path, "frame file name holds no frame number")
            numbered.append((number, path))
    if not numbered:
        raise DatasetFormatError.at(folder, f"no frames ({', '.join(FRAME_SUFFIXES)}) found")
    numbered.sort()
    numbers = [n for n, _ in numbered]
    if len(set(numbers)) != len(numbers):
        raise DatasetFormatError.at(folder, "two frame files carry the same frame number")
    if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
        gap = next(a + 1 for a, b in zip(numbers, numbers[1:]) if b != a + 1)
        raise DatasetFormatError.at(folder, f"frame numbers are not contiguous: frame {gap} is missing")
    return [p for _, p in numbered]


class _TwoFrameSource:
    """Frames loaded by ``_load(k)`` on demand, keeping the two of the current interval; in-between
    frames by ``interpolator``."""

    interpolator: Interpolator
    _cache: dict[int, np.ndarray]

    def _load(self, k: int) -> np.ndarray:
        raise NotImplementedError

    def frame(self, k: int) -> np.ndarray:
        if k not in self._cache:
            self._cache[k] = self._load(k)
            while len(self._cache) > 2:
                self._cache.pop(next(iter(self._cache)))
        return self._cache[k]

    def between(self, k: int, alpha: float) -> np.ndarray:
        return self.interpolator(self.frame(k), self.frame(k + 1), alpha)


class FolderSource(_TwoFrameSource):
    """Frames of a folder of images, downscaled by ``scale``, in-between frames by ``interpolator``."""

    def __init__(self, folder: Path | str, *, scale: int = 1, interpolator: Interpolator = linear_interpolate):
        self.folder, self.scale, self.interpolator = Path(folder), int(scale), interpolator
        self.files = list_frame_files(self.folder)
        self.num_frames = len(self.files)
        self.height = self.width = None
        self._cache: dict[int, np.ndarray] = {}  # the two frames of the current interval
        self.height, self.width = self.frame(0).shape[:2]

    def _load(self, k: int) -> np.ndarray:
        path = self.files[k]
        rgb = read_frame(path)
        frame = downscale_area(rgb, self.scale)
        if self.height is not None and frame.shape[:2] != (self.height, self.width):
            raise DatasetFormatError.at(path, f"frame is {rgb.shape[1]}x{rgb.shape[0]} (WxH), unlike the first "
                                              f"frame of {self.folder}")
        return frame


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")


def video_fps(path: Path | str) -> float:
    """The frame rate a video file's container states; an unreadable file is an error naming it."""
    with _open_video(Path(path)) as container:
        rate = container.streams.video[0].average_rate or container.streams.video[0].guessed_rate
        if not rate:
            raise DatasetFormatError.at(path, "the container states no frame rate; give --fps")
        return float(rate)


def _open_video(path: Path):
    try:
        import av
    except ImportError as err:  # a dependency, so only a broken install lands here
        raise ImportError("reading video files needs PyAV: pip install av") from err
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, UnicodeDecodeError) as err:
        raise DatasetFormatError.at(path, f"cannot open as a video ({err})") from err
    if not container.streams.video:
        container.close()
        raise DatasetFormatError.at(path, "holds no video stream")
    return container


class VideoFileSource(_TwoFrameSource):
    """Frames of a video file (MP4, AVI, MOV, ... through PyAV's FFmpeg), decoded as they are asked
    for in order and downscaled by ``scale``; only the two frames of the current interval are held.

    The frame count comes from one pass over the file's packets (no decoding) when the container
    does not state it.
    """

    def __init__(self, path: Path | str, *, scale: int = 1, interpolator: Interpolator = linear_interpolate):
        self.path, self.scale, self.interpolator = Path(path), int(scale), interpolator
        with _open_video(self.path) as container:
            stream = container.streams.video[0]
            self.num_frames = stream.frames or sum(1 for packet in container.demux(stream) if packet.size)
        self._container, self._frames, self._next = None, None, 0
        self._cache: dict[int, np.ndarray] = {}
        self.height = self.width = None
        self.height, self.width = self.frame(0).shape[:2]

    def _decoded(self, k: int) -> np.ndarray:
        """Frame ``k``, decoding forward (from the start again if an earlier frame is asked for)."""
        if self._frames is None or k < self._next:
            self.close()
            self._container = _open_video(self.path)
            self._frames, self._next = self._container.decode(video=0), 0
        try:
            while True:
                image = next(self._frames)
                self._next += 1
                if self._next - 1 == k:
                    return image.to_ndarray(format="rgb24")
        except StopIteration:
            raise DatasetFormatError.at(self.path, f"frame {k} could not be decoded (the file gave "
                                                   f"{self._next} of {self.num_frames} frames)") from None
        except Exception as err:  # FFmpeg decoding errors come in many types
            raise DatasetFormatError.at(self.path, f"decoding frame {k} failed ({err})") from err

    def _load(self, k: int) -> np.ndarray:
        frame = downscale_area(self._decoded(k), self.scale)
        if self.height is not None and frame.shape[:2] != (self.height, self.width):
            raise DatasetFormatError.at(self.path, f"frame {k} is {frame.shape[1]}x{frame.shape[0]}, unlike "
                                                   "the first frame")
        return frame

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
        self._container, self._frames = None, None


def open_source(path: Path | str, *, scale: int = 1) -> "FolderSource | VideoFileSource":
    """A video file (by its suffix) or a folder of frames."""
    path = Path(path)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return VideoFileSource(path, scale=scale)
    return FolderSource(path, scale=scale)


def choose_dvs_model(video: str, *, seed: int = 0, clean_fraction: float = 0.5) -> str:
    """``clean`` or ``noisy`` for one video of a ``mixed`` dataset.

    The draw is seeded by ``seed`` and the video's name (CRC-32), so a video gets the same model
    whatever the order or subset of videos built; ``clean_fraction`` is the probability of
    ``clean``.
    """
    if not 0 <= clean_fraction <= 1:
        raise UserError(f"clean_fraction must be in [0, 1], got {clean_fraction}")
    rng = np.random.default_rng([seed, zlib.crc32(video.encode())])
    return "clean" if rng.random() < clean_fraction else "noisy"


def emulate_video(source: FrameSource, writer: VideoWriter, *, params: DVSParams, upsample: int = 1,
                  fps: float = fmt.DEFAULT_FPS, seed: int = 0, progress: Callable[[int], None] | None = None) -> int:
    """Emulate events over ``source`` and write frames and events to ``writer``; returns the event count.

    Each frame interval ``[t_k, t_{k+1})`` is cut into ``upsample`` emulator steps: ``upsample - 1``
    in-between frames and then frame ``k + 1`` (``upsample = 1``: the frames alone). Frame
    times are those of the data contract, ``round(1e6 * k / fps)``; events are time-sorted.
    """
    if upsample < 1 or int(upsample) != upsample:
        raise UserError(f"upsample must be a positive integer, got {upsample}")
    emulator = DVSEmulator(source.height, source.width, params, seed=seed)
    frame = source.frame(0)
    emulator.reset(frame, 0.0)
    writer.add_frame(to_uint8(frame))
    count = 0
    for k in range(source.num_frames - 1):
        t_a, t_b = fmt.frame_time_us(k, fps), fmt.frame_time_us(k + 1, fps)
        for j in range(1, upsample + 1):
            alpha = j / upsample
            step_frame = source.frame(k + 1) if j == upsample else source.between(k, alpha)
            events = emulator.step(step_frame, t_a + alpha * (t_b - t_a))
            writer.add_events(events["x"], events["y"], events["t"], events["p"])
            count += len(events["t"])
        writer.add_frame(to_uint8(source.frame(k + 1)))
        if progress is not None:
            progress(1)
    return count
