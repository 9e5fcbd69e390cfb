"""Writing AEDAT4 recordings with an events track and a frame track, as a DAVIS records them.

faery reads AEDAT4 frame tracks but writes events only, so frames are written here. An AEDAT4
file is the magic line ``#!AER-DAT4.0\\r\\n``, a size-prefixed ``IOHeader`` flatbuffer (compression,
the data table's position, and an XML description of the tracks), then packets: an 8-byte header
(``int32`` track id, ``int32`` body size) and a size-prefixed flatbuffer body, ``EVTS`` (a vector
of 16-byte events) or ``FRME`` (one frame). Files are written uncompressed and without the
optional data table (``dataTablePosition = -1``); readers walk the packets.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Iterable

import flatbuffers
import numpy as np

from dagr_lite.data.writer import temporary_name

MAGIC = b"#!AER-DAT4.0\r\n"
EVENT_STRUCT = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("on", "u1"), ("pad", "u1", (3,))])
FRAME_FORMAT = {1: 0, 3: 16}  # channels -> AEDAT4 FrameFormat (GRAY = 0, BGR = 16)
EVENTS_PER_PACKET = 4096


def _track_xml(track: int, kind: str, name: str, width: int, height: int) -> str:
    path = f"/mainloop/Recorder/outInfo/{track}/"
    return (f'<node name="{track}" path="{path}">'
            '<attr key="compression" type="string">NONE</attr>'
            f'<attr key="originalOutputName" type="string">{name}</attr>'
            f'<attr key="typeIdentifier" type="string">{kind}</attr>'
            f'<node name="info" path="{path}info/">'
            f'<attr key="sizeX" type="int">{width}</attr><attr key="sizeY" type="int">{height}</attr>'
            '<attr key="source" type="string">dagr_lite</attr></node></node>')


def _header(width: int, height: int, with_frames: bool) -> bytes:
    tracks = _track_xml(0, "EVTS", "events", width, height)
    if with_frames:
        tracks += _track_xml(1, "FRME", "frames", width, height)
    xml = f'<dv version="2.0"><node name="outInfo" path="/mainloop/Recorder/outInfo/">{tracks}</node></dv>'
    builder = flatbuffers.Builder(len(xml) + 64)
    info = builder.CreateString(xml)
    builder.StartObject(3)
    builder.PrependInt32Slot(0, 0, -1)  # compression: NONE (forced: 0 is the schema's default)
    builder.PrependInt64Slot(1, -1, 0)  # dataTablePosition: none
    builder.PrependUOffsetTRelativeSlot(2, info, 0)
    builder.FinishSizePrefixed(builder.EndObject(), b"IOHE")
    return bytes(builder.Output())


def _events_body(t: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray) -> bytes:
    packed = np.zeros(len(t), EVENT_STRUCT)
    packed["t"], packed["x"], packed["y"], packed["on"] = t, x, y, on
    raw = packed.tobytes()
    builder = flatbuffers.Builder(len(raw) + 64)
    builder.StartVector(EVENT_STRUCT.itemsize, len(t), 8)
    builder.head -= len(raw)
    builder.Bytes[builder.head: builder.head + len(raw)] = raw
    elements = builder.EndVector()
    builder.StartObject(1)
    builder.PrependUOffsetTRelativeSlot(0, elements, 0)
    builder.FinishSizePrefixed(builder.EndObject(), b"EVTS")
    return bytes(builder.Output())


def _frame_body(t_us: int, image: np.ndarray, exposure_us: int) -> bytes:
    channels = 1 if image.ndim == 2 else image.shape[2]
    pixels = image if channels == 1 else image[..., ::-1]  # AEDAT4 colour frames are BGR
    builder = flatbuffers.Builder(pixels.size + 128)
    data = builder.CreateNumpyVector(np.ascontiguousarray(pixels, dtype=np.uint8).reshape(-1))
    builder.StartObject(11)
    times = (t_us, t_us, t_us + exposure_us, t_us, t_us + exposure_us)  # timestamp, frame start/end, exposure
    for slot, value in enumerate(times):
        builder.PrependInt64Slot(slot, int(value), -1)
    builder.PrependInt8Slot(5, FRAME_FORMAT[channels], -1)
    builder.PrependInt16Slot(6, image.shape[1], -1)
    builder.PrependInt16Slot(7, image.shape[0], -1)
    builder.PrependInt16Slot(8, 0, -1)
    builder.PrependInt16Slot(9, 0, -1)
    builder.PrependUOffsetTRelativeSlot(10, data, 0)
    builder.FinishSizePrefixed(builder.EndObject(), b"FRME")
    return bytes(builder.Output())


def _check_frame(t_us: int, image: np.ndarray, width: int, height: int) -> None:
    if image.shape[:2] != (height, width) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"frame at {t_us} us is {image.shape} {image.dtype}; expected ({height}, {width}[, 3]) "
                         "uint8, the events' sensor size")


def write_aedat4(path: Path | str, events: dict[str, np.ndarray] | Iterable[dict[str, np.ndarray]],
                 size: tuple[int, int], frames: Iterable[tuple[int, np.ndarray]] | None = None, *,
                 exposure_us: int = 1000, overwrite: bool = False) -> Path:
    """Write ``events`` (``x, y, t, p``, sorted by ``t`` in microseconds; one dict, or time-ordered
    chunks of them) of a ``size = (width, height)`` sensor, and ``frames`` (``(t_us, (H, W, 3) or
    (H, W) uint8)``, sorted), as one AEDAT4 file; packets of both tracks are interleaved by time, as
    a camera writes them, a chunk and a frame in memory at a time. Returns the path."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (nothing is overwritten)")
    width, height = int(size[0]), int(size[1])
    chunks = [events] if isinstance(events, dict) else events
    frames = iter(frames or ())
    next_frame = next(frames, None)
    tmp = temporary_name(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "wb") as out:
            out.write(MAGIC)
            out.write(_header(width, height, next_frame is not None))

            def packet(track: int, body: bytes) -> None:
                out.write(struct.pack("<ii", track, len(body)))
                out.write(body)

            def write_frame() -> None:
                nonlocal next_frame
                _check_frame(*next_frame, width, height)
                packet(1, _frame_body(next_frame[0], next_frame[1], exposure_us))
                next_frame = next(frames, None)

            for chunk in chunks:
                t = np.asarray(chunk["t"], np.int64)
                columns = (t, np.asarray(chunk["x"]), np.asarray(chunk["y"]), np.asarray(chunk["p"]))
                start = 0
                while start < len(t):
                    if next_frame is not None and next_frame[0] <= t[start]:  # a frame before these events
                        write_frame()
                        continue
                    stop = min(start + EVENTS_PER_PACKET, len(t))
                    if next_frame is not None:
                        stop = min(stop, int(np.searchsorted(t, next_frame[0], side="left")))
                    packet(0, _events_body(*(c[start:stop] for c in columns)))
                    start = stop
            while next_frame is not None:
                write_frame()
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
    return path
