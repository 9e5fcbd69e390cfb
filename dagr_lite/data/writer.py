"""Writing datasets in the released EventEgoHands layout (see :mod:`dagr_lite.data.format`).

Files are written under a temporary name and renamed when complete, so an interrupted write
never leaves a file that looks finished. Existing files are never replaced unless asked.
A video's events file is written last: its presence marks the video as complete.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

import h5py
import hdf5plugin
import numpy as np
from PIL import Image

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.frames import list_frames
from dagr_lite.data.labels import load_labels_json

# Events per HDF5 chunk. A window read decompresses the chunks it touches, about
# n / CHUNK + 1 per array, so small chunks keep the constant part of a slice read low; 8192
# events (64 KiB of int64 timestamps) compress as well as larger ones. Measured with
# benchmarks/slice_read.py (20M events, Blosc): constant 0.37 ms at 8192, 0.53 ms at 32768,
# 1.65 ms at 131072 per 33 ms window read, with the same file size.
DEFAULT_CHUNK_EVENTS = 1 << 13

COMPRESSIONS = (None, "gzip", "blosc")

X_DTYPE, Y_DTYPE, T_DTYPE, P_DTYPE = np.uint16, np.uint16, np.int64, np.uint8


def _compression_kwargs(compression: str | None) -> dict:
    if compression is None:
        return {}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    if compression == "blosc":
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))
    raise UserError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")


def temporary_name(path: Path) -> Path:
    """The name a file is written under before :func:`os.replace` moves it to ``path``."""
    return path.with_name(path.name + f".tmp{os.getpid()}")


def write_text_atomically(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` under a temporary name, then rename: never half-written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def _check_target(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass overwrite=True to replace it)")


class _Transaction:
    """``with`` support: :meth:`close` on success, :meth:`abort` when the block raises."""

    def close(self):
        raise NotImplementedError

    def abort(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class EventFileWriter(_Transaction):
    """Writes one ``<video>.h5`` event file, in appended pieces of any size.

    ``timeidx`` is counted as the pieces arrive (for each frame, how many events lie before its
    time), so the whole stream is never held in memory. Frame times are always those of the
    ``round`` convention (:data:`dagr_lite.data.format.WRITTEN_CONVENTION`). The file appears
    under its final name only on :meth:`close`; leaving the ``with`` block through an exception
    removes it.

    Args:
        path: target ``.h5`` file.
        num_frames: number of frames of the video (length of ``timeidx``).
        fps: frame rate defining the frame times.
        compression: None, ``"gzip"`` or ``"blosc"`` (LZ4 with byte shuffle; readers need
            ``import hdf5plugin``).
        chunk_events: events per HDF5 chunk.
        height, width: when given, every event must lie inside the image.
        overwrite: replace an existing file.
    """

    def __init__(self, path: Path | str, *, num_frames: int, fps: float = fmt.DEFAULT_FPS,
                 compression: str | None = "blosc", chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 height: int | None = None, width: int | None = None, overwrite: bool = False):
        self.path = Path(path)
        _check_target(self.path, overwrite)
        if num_frames < 0:
            raise UserError(f"num_frames must be >= 0, got {num_frames}")
        options = _compression_kwargs(compression)
        self.height, self.width = height, width
        self._frame_times = fmt.frame_time_us(np.arange(num_frames), fps, fmt.WRITTEN_CONVENTION)  # (K,)
        self._timeidx = np.zeros(num_frames, dtype=np.int64)  # (K,)
        self._count = 0
        self._last_t: int | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp_path = temporary_name(self.path)
        self._h5 = h5py.File(self._tmp_path, "w")
        self._datasets = {
            key: self._h5.create_dataset(key, shape=(0,), maxshape=(None,), dtype=dtype,
                                         chunks=(int(chunk_events),), **options)
            for key, dtype in zip(fmt.EVENT_KEYS, (X_DTYPE, Y_DTYPE, T_DTYPE, P_DTYPE))
        }

    def append(self, x, y, t, p) -> None:
        """Append events; ``t`` must be sorted and not earlier than anything appended before."""
        arrays = [np.asarray(a).reshape(-1) for a in (x, y, t, p)]
        n = len(arrays[2])
        for name, a in zip("xytp", arrays):
            if len(a) != n:
                raise UserError(f"{self.path}: events/{name} has {len(a)} values, events/t has {n}")
        if n == 0:
            return
        x, y, t, p = arrays
        if not all(np.issubdtype(a.dtype, np.integer) for a in arrays):
            raise UserError(f"{self.path}: events must be integers, got dtypes "
                             f"{[str(a.dtype) for a in arrays]} for x, y, t, p")
        x, y, t = x.astype(np.int64), y.astype(np.int64), t.astype(np.int64)
        if np.any(t[1:] < t[:-1]) or (self._last_t is not None and t[0] < self._last_t):
            raise UserError(f"{self.path}: events/t must be sorted ascending across appends")
        if t[0] < 0:
            raise UserError(f"{self.path}: events/t must be >= 0 (microseconds from the video start), "
                             f"found {t[0]}")
        if not np.all((p == 0) | (p == 1)):
            raise UserError(f"{self.path}: events/p must be 0 or 1, found {np.unique(p).tolist()}")
        for name, a, size in (("x", x, self.width), ("y", y, self.height)):
            limit = size if size is not None else np.iinfo(X_DTYPE).max + 1
            if a.min() < 0 or a.max() >= limit:
                raise UserError(f"{self.path}: events/{name} must lie in [0, {limit}), "
                                 f"found [{a.min()}, {a.max()}]")
        for key, a in zip(fmt.EVENT_KEYS, (x, y, t, p)):
            dataset = self._datasets[key]
            dataset.resize((self._count + n,))
            dataset[self._count:] = a.astype(dataset.dtype)
        self._timeidx += np.searchsorted(t, self._frame_times, side="left")
        self._count += n
        self._last_t = int(t[-1])

    def close(self) -> Path:
        """Write ``timeidx``, close, and move the file to its final name."""
        if self._h5 is None:
            return self.path
        if self._count == 0:
            self.abort()
            raise UserError(f"{self.path}: no events were written (a dataset video needs at least one)")
        self._h5.create_dataset(fmt.KEY_TIMEIDX, data=self._timeidx)
        self._h5.close()
        self._h5 = None
        os.replace(self._tmp_path, self.path)
        return self.path

    def abort(self) -> None:
        """Discard what was written."""
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None
        self._tmp_path.unlink(missing_ok=True)


def write_events(path: Path | str, x, y, t, p, *, num_frames: int, **kwargs) -> Path:
    """Write a whole event stream to ``path`` in one go (see :class:`EventFileWriter` for options)."""
    with EventFileWriter(path, num_frames=num_frames, **kwargs) as writer:
        writer.append(x, y, t, p)
    return writer.path


def write_frame(path: Path | str, image: np.ndarray, *, quality: int = 95, overwrite: bool = False) -> Path:
    """Write an ``(H, W, 3)`` uint8 RGB frame as JPEG (atomically)."""
    path = Path(path)
    _check_target(path, overwrite)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise UserError(f"{path}: expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    Image.fromarray(image).save(tmp, format="JPEG", quality=quality)
    os.replace(tmp, path)
    return path


def write_labels(root: Path | str, labels: dict[str, dict[int, np.ndarray]], *, merge: bool = False,
                 overwrite: bool = False) -> Path:
    """Write ``bounding_boxes.json`` from ``{video: {k: (M, 4) x_tl, y_tl, w, h}}``.

    Every frame given gets a key, an empty list when it has no boxes. ``merge`` keeps the other
    videos of an existing file and replaces all labels of the videos given; otherwise an
    existing file is an error unless ``overwrite``.
    """
    path = fmt.labels_path(root)
    content: dict[str, list] = {}
    if path.exists():
        if merge:
            content = {key: value for key, value in load_labels_json(root).items()
                       if fmt.label_video(key) not in labels}
        elif not overwrite:
            raise FileExistsError(f"{path}: already exists (pass merge=True or overwrite=True)")
    for video, frames in labels.items():
        for k, boxes in sorted(frames.items()):
            boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
            content[fmt.label_key(video, k)] = [[round(float(v), 3) for v in box] for box in boxes]
    return write_text_atomically(path, json.dumps(content))


class VideoWriter(_Transaction):
    """Writes one video of a split as it is produced: frames one by one, events in pieces.

    Frames go straight to their JPEG files; the events file is created under a temporary name
    and appears only on :meth:`close`, after all ``num_frames`` frames were added, so a video
    whose events file exists is complete. Leaving the ``with`` block through an exception
    discards the events; frames left by an incomplete video are removed when it is written again.

    Args:
        root, split, video: where the video goes.
        num_frames: how many frames will be added.
        height, width: frame size (events must lie inside it).
        fps, compression: as for :class:`EventFileWriter`.
        overwrite: replace an existing video (its old frames are removed first).
    """

    def __init__(self, root: Path | str, split: str, video: str, *, num_frames: int, height: int, width: int,
                 fps: float = fmt.DEFAULT_FPS, compression: str | None = "blosc", overwrite: bool = False):
        if split not in fmt.SPLITS:
            raise UserError(f"split must be one of {', '.join(fmt.SPLITS)}, got {split!r}")
        if num_frames <= 0:
            raise UserError(f"{fmt.frames_dir(root, split, video)}: a video needs at least one frame, "
                             f"got num_frames={num_frames}")
        self.root, self.split, self.video = Path(root), split, video
        self.num_frames, self.height, self.width = int(num_frames), int(height), int(width)
        self.folder = fmt.frames_dir(root, split, video)
        self._events = EventFileWriter(fmt.events_path(root, split, video), num_frames=num_frames, fps=fps,
                                       compression=compression, height=height, width=width, overwrite=overwrite)
        # Either the video is being replaced (overwrite) or it never completed (no events file):
        # in both cases frames left in its folder are stale.
        if self.folder.is_dir():
            for name in list_frames(self.folder).values():
                (self.folder / name).unlink()
        self.frames_written = 0

    def add_frame(self, image: np.ndarray) -> None:
        """Write the next frame, an ``(H, W, 3)`` uint8 RGB image."""
        if self.frames_written >= self.num_frames:
            raise UserError(f"{self.folder}: more than the {self.num_frames} frames announced")
        if image.shape[:2] != (self.height, self.width):
            raise UserError(f"{self.folder}: frame {self.frames_written} is {image.shape[1]}x{image.shape[0]} "
                             f"(WxH), expected {self.width}x{self.height}")
        write_frame(self.folder / fmt.frame_name(self.frames_written), image, overwrite=True)
        self.frames_written += 1

    def add_events(self, x, y, t, p) -> None:
        """Append events (sorted by ``t``, not earlier than those added before)."""
        self._events.append(x, y, t, p)

    def close(self) -> Path:
        if self.frames_written != self.num_frames:
            self.abort()
            raise UserError(f"{self.folder}: {self.frames_written} frames written, {self.num_frames} announced")
        return self._events.close()

    def abort(self) -> None:
        self._events.abort()


def write_video(root: Path | str, split: str, video: str, *, events: dict[str, np.ndarray],
                frames: Iterable[np.ndarray], fps: float = fmt.DEFAULT_FPS,
                compression: str | None = "blosc", overwrite: bool = False) -> int:
    """Write one video's frames and events at once (see :class:`VideoWriter`); returns the frame count.

    ``events`` holds arrays ``x, y, t, p``.
    """
    frames = list(frames)
    if not frames:
        raise UserError(f"{fmt.frames_dir(root, split, video)}: no frames given for video {video!r}")
    height, width = frames[0].shape[:2]
    with VideoWriter(root, split, video, num_frames=len(frames), height=height, width=width, fps=fps,
                     compression=compression, overwrite=overwrite) as writer:
        for image in frames:
            writer.add_frame(image)
        writer.add_events(events["x"], events["y"], events["t"], events["p"])
    return len(frames)
