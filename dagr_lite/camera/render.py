"""Pictures of the streaming detector at one moment, and MP4 files of them.

:func:`render_moment` draws the latest image with the current boxes beside the recent events
(ON red, OFF blue on white) with the same boxes, under a caption. :class:`Mp4Writer` writes such
pictures to an H.264 MP4 through PyAV, into a temporary file moved into place when closed.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

TEXT_HEIGHT = 14  # pixels of the caption bar above each frame


def render_moment(image: np.ndarray, events: dict[str, np.ndarray], boxes: np.ndarray, scores: np.ndarray,
                  caption: str) -> np.ndarray:
    """``(14 + H, 2W, 3)`` uint8: the image with the boxes, beside the events (ON red, OFF blue on
    white) with the same boxes, under a caption."""
    height, width = image.shape[:2]
    canvas = np.full((height, width, 3), 255, np.uint8)
    if len(events["x"]):
        on = (events["p"] > 0)[:, None]
        canvas[events["y"].astype(int), events["x"].astype(int)] = np.where(on, [220, 30, 30], [30, 60, 220])
    frame = Image.new("RGB", (2 * width, height + TEXT_HEIGHT), (0, 0, 0))
    for i, array in enumerate((image, canvas)):
        panel = Image.fromarray(np.ascontiguousarray(array))
        draw = ImageDraw.Draw(panel)
        for box, score in zip(boxes.tolist(), scores.tolist()):
            draw.rectangle(box, outline=(0, 230, 0) if i == 0 else (0, 150, 0), width=2)
            score_label(draw, box, f"{score:.2f}", width, height)
        frame.paste(panel, (i * width, TEXT_HEIGHT))
    ImageDraw.Draw(frame).text((4, 1), caption, fill=(255, 255, 255))
    return np.asarray(frame)


def score_label(draw: ImageDraw.ImageDraw, box: list[float], text: str, width: int, height: int) -> None:
    """``text`` in white on black at the box's top-left corner, inside it where the box reaches the
    panel's top edge, and moved left or right to stay inside the ``width x height`` panel."""
    left, top, right, bottom = draw.textbbox((0, 0), text)
    w, h = right - left + 4, bottom - top + 2
    x = min(max(box[0], 0), width - w)
    y = box[1] - h if box[1] - h >= 0 else min(max(box[1], 0), height - h)
    draw.rectangle((x, y, x + w - 1, y + h - 1), fill=(0, 0, 0))
    draw.text((x + 2 - left, y + 1 - top), text, fill=(255, 255, 255))


class Mp4Writer:
    """Pictures of one size to an H.264 MP4 at ``fps`` frames per second (odd sizes padded by a pixel)."""

    def __init__(self, path: Path | str, fps: float = 30.0):
        import av

        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part.mp4")
        self.container = av.open(str(self.tmp), mode="w")
        self.stream = self.container.add_stream("libx264", rate=round(fps))
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": "23", "preset": "veryfast"}
        self.frames = 0
        self._size: tuple[int, int] | None = None

    def write(self, picture: np.ndarray) -> None:
        import av

        height, width = picture.shape[:2]
        even = (height + height % 2, width + width % 2)
        if self._size is None:
            self._size = even
            self.stream.height, self.stream.width = even
        elif even != self._size:
            raise ValueError(f"every picture of {self.path} must be {self._size[1]}x{self._size[0]}, got {width}x{height}")
        if even != (height, width):
            picture = np.pad(picture, ((0, even[0] - height), (0, even[1] - width), (0, 0)))
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(picture), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)
        self.frames += 1

    def discard(self) -> None:
        """Stop, leaving no file (a run that failed)."""
        self.container.close()
        self.tmp.unlink(missing_ok=True)

    def close(self) -> Path | None:
        """Finish the file; None (and no file) if no picture was written."""
        if self.frames:
            for packet in self.stream.encode():
                self.container.mux(packet)
        self.container.close()
        if not self.frames:
            self.tmp.unlink(missing_ok=True)
            return None
        os.replace(self.tmp, self.path)
        return self.path
