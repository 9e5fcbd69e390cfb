"""Frames of the layout: decoding one, its size from the JPEG header alone, checking a folder's
frames, listing them."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image

from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError, Problem

# JPEG markers: start and end of image, start of scan, and the frame headers (SOF0..SOF15 but
# DHT, JPG and DAC), which hold the image size.
_SOI, _EOI, _SOS = 0xD8, 0xD9, 0xDA


def read_frame(path: Path | str, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Decode one frame to an ``(H, W, 3)`` uint8 RGB array; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFormatError.at(path, "frame file is missing")
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB"))
    except (OSError, SyntaxError, ValueError) as err:
        raise DatasetFormatError.at(path, f"cannot decode image ({err})") from err
    if expected_hw is not None and array.shape[:2] != tuple(expected_hw):
        raise DatasetFormatError.at(path, f"frame is {array.shape[1]}x{array.shape[0]} (WxH), "
                                          f"expected {expected_hw[1]}x{expected_hw[0]}")
    return array


def frame_size(path: Path | str) -> tuple[int, int]:
    """``(H, W)`` of a frame from its header alone (no decoding)."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            width, height = image.size
    except FileNotFoundError as err:
        raise DatasetFormatError.at(path, "frame file is missing") from err
    except (OSError, SyntaxError, ValueError) as err:
        raise DatasetFormatError.at(path, f"cannot read image header ({err})") from err
    return height, width


_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


_STANDALONE_MARKERS = frozenset({0x01, *range(0xD0, 0xD8)})


_JPEG_READ = 4096


_JPEG_TAIL = 32


def jpeg_size(path: Path | str) -> tuple[int, int]:
    """``(H, W)`` of a JPEG file from its frame header, without decoding; errors name the file.

    Reads the first few KB (more only when large metadata segments come first) and the last
    bytes: a file that does not start as a JPEG, has no frame header before its image data,
    or lacks the end-of-image marker near its end (a truncated file) is an error.
    """
    try:
        with open(path, "rb", buffering=0) as f:
            size = _jpeg_frame_size(f)
            f.seek(max(0, f.seek(0, os.SEEK_END) - _JPEG_TAIL))
            tail = f.read(_JPEG_TAIL)
    except FileNotFoundError as err:
        raise DatasetFormatError.at(path, "frame file is missing") from err
    except OSError as err:
        raise DatasetFormatError.at(path, f"cannot read the frame ({err})") from err
    except _NotJpeg as err:
        raise DatasetFormatError.at(path, f"not a readable JPEG: {err}") from err
    if bytes((0xFF, _EOI)) not in tail:
        raise DatasetFormatError.at(path, "not a readable JPEG: no end-of-image marker at the end (truncated file?)")
    return size


class _NotJpeg(Exception):
    pass


def _jpeg_frame_size(f) -> tuple[int, int]:
    """``(H, W)`` from the first frame header of the JPEG stream in binary file ``f``."""
    data, base = f.read(_JPEG_READ), 0  # data holds the bytes from offset base on
    if data[:2] != bytes((0xFF, _SOI)):
        raise _NotJpeg("does not start with the JPEG start-of-image marker")
    pos = 2
    while True:
        if pos + 9 > base + len(data):  # the next segment's head lies beyond what was read
            f.seek(pos)
            data, base = f.read(_JPEG_READ), pos
            if len(data) < 4:
                raise _NotJpeg(f"file ends at byte {pos} before the frame header (truncated header)")
        i = pos - base
        if data[i] != 0xFF:
            raise _NotJpeg(f"expected a marker at byte {pos}, found 0x{data[i]:02x}")
        marker = data[i + 1]
        if marker == 0xFF or marker in _STANDALONE_MARKERS:
            pos += 1 if marker == 0xFF else 2
            continue
        if marker in (_SOS, _EOI, _SOI):
            raise _NotJpeg(f"no frame header before marker 0x{marker:02x} at byte {pos}")
        if marker in _SOF_MARKERS:
            if len(data) < i + 9:
                raise _NotJpeg(f"file ends inside the frame header at byte {pos} (truncated header)")
            height, width = int.from_bytes(data[i + 5:i + 7], "big"), int.from_bytes(data[i + 7:i + 9], "big")
            if height == 0 or width == 0:
                raise _NotJpeg(f"frame header gives a size of {width}x{height} (WxH)")
            return height, width
        pos += 2 + int.from_bytes(data[i + 2:i + 4], "big")


def frame_header_problems(frames: dict[int, Path], expected_hw: tuple[int, int] | None,
                          expected_from: str = "", read_size=None) -> tuple[list[Problem], tuple[int, int] | None]:
    """Every frame's JPEG header read (:func:`jpeg_size`) and its size compared, in frame order.

    ``frames``: frame index -> file. ``expected_hw``: the size every frame must have; None takes
    the first readable frame's. ``expected_from`` says where the expected size comes from
    (``"as configured"``), for the messages. ``read_size(path) -> (H, W)`` replaces
    :func:`jpeg_size` (to decode the frames, say). Returns the problems and the size.
    """
    read_size = read_size or jpeg_size
    problems = []
    for k in sorted(frames):
        path = frames[k]
        try:
            hw = read_size(path)
        except DatasetFormatError as err:
            problems += err.problems
            continue
        if expected_hw is None:
            expected_hw, expected_from = hw, f"as {path.name}"
        elif hw != expected_hw:
            problems.append(Problem(path, "", f"frame is {hw[1]}x{hw[0]} (WxH), expected {expected_hw[1]}x"
                                              f"{expected_hw[0]}{' ' + expected_from if expected_from else ''}"))
    return problems, expected_hw


def list_frames(directory: Path | str) -> dict[int, str]:
    """``{k: file name}`` of the ``frame_<k>.jpg`` files in a video's frame folder."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetFormatError.at(directory, "frame folder is missing")
    frames = {}
    for name in os.listdir(directory):
        k = fmt.parse_frame_name(name)
        if k is not None:
            frames[k] = name
    return frames
