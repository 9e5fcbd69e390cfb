"""A camera's sensor to the model's input, and boxes back to the sensor's pixels.

A :class:`Sensor` applies, in this order: ``crop = [x0, y0, w, h]`` (sensor pixels), ``rotate`` (0,
90, 180 or 270 degrees, clockwise), ``flip_x`` / ``flip_y`` (mirror the columns / rows), then an
integer ``scale`` that bins ``scale x scale`` pixels into one (an event keeps its time and polarity
at ``x // scale, y // scale``; a frame's pixels are averaged by the dataset builder's
:func:`~dagr_lite.synth.video.downscale_area`), as the dataset versions were made
from 1280x720 EgoHands (scale 2: 640x360, scale 4: 320x180). Events and frames go through the same
steps; :meth:`Sensor.boxes_to_sensor` undoes them for boxes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.synth.video import downscale_area

ROTATIONS = (0, 90, 180, 270)


class SensorError(UserError):
    """A sensor setting that does not fit the sensor or the model; the message names the setting."""


@dataclass(frozen=True)
class Sensor:
    """The steps from a ``size = (width, height)`` sensor to the model's input (see the module)."""

    size: tuple[int, int]
    crop: tuple[int, int, int, int] | None = None
    scale: int = 1
    rotate: int = 0
    flip_x: bool = False
    flip_y: bool = False

    def __post_init__(self):
        width, height = self.size
        if self.crop is not None:
            x0, y0, w, h = (int(v) for v in self.crop)
            if len(self.crop) != 4 or w <= 0 or h <= 0 or x0 < 0 or y0 < 0 or x0 + w > width or y0 + h > height:
                raise SensorError(f"sensor.crop={list(self.crop)} must be [x0, y0, w, h] with w, h > 0 inside the "
                                  f"{width}x{height} sensor")
            object.__setattr__(self, "crop", (x0, y0, w, h))
        if isinstance(self.scale, bool) or int(self.scale) != self.scale or self.scale < 1:
            raise SensorError(f"sensor.scale={self.scale!r} must be a positive integer")
        if self.rotate not in ROTATIONS:
            raise SensorError(f"sensor.rotate={self.rotate!r} must be one of {ROTATIONS}")
        w, h = self.cropped_size
        if w % self.scale or h % self.scale:
            raise SensorError(f"sensor.scale={self.scale} must divide the cropped {w}x{h} sensor; crop it to a "
                              "multiple of the scale")

    @property
    def cropped_size(self) -> tuple[int, int]:
        return (self.crop[2], self.crop[3]) if self.crop is not None else tuple(self.size)

    @property
    def output_size(self) -> tuple[int, int]:
        """``(width, height)`` of what the model reads."""
        w, h = self.cropped_size
        if self.rotate in (90, 270):
            w, h = h, w
        return w // self.scale, h // self.scale

    def _oriented(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cropped pixel coordinates after rotation and flips (before scaling)."""
        w, h = self.cropped_size
        if self.rotate == 90:
            x, y = h - 1 - y, x
        elif self.rotate == 180:
            x, y = w - 1 - x, h - 1 - y
        elif self.rotate == 270:
            x, y = y, w - 1 - x
        ow, oh = (h, w) if self.rotate in (90, 270) else (w, h)
        if self.flip_x:
            x = ow - 1 - x
        if self.flip_y:
            y = oh - 1 - y
        return x, y

    def events(self, events: dict) -> dict:
        """The events inside the crop, in the model's pixels (times and polarities kept)."""
        x, y = np.asarray(events["x"], np.int64), np.asarray(events["y"], np.int64)
        keep = None
        if self.crop is not None:
            x0, y0, w, h = self.crop
            x, y = x - x0, y - y0
            keep = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            x, y = x[keep], y[keep]
        x, y = self._oriented(x, y)
        out = {"x": x // self.scale, "y": y // self.scale}
        for key in ("t", "p"):
            out[key] = events[key] if keep is None else events[key][keep]
        return out

    def frame(self, image: np.ndarray) -> np.ndarray:
        """An ``(H, W, C)`` frame of the sensor as the model reads it (pixels binned by ``scale``)."""
        if image.shape[:2] != (self.size[1], self.size[0]):
            raise SensorError(f"a {image.shape[1]}x{image.shape[0]} frame does not come from the "
                              f"{self.size[0]}x{self.size[1]} sensor")
        if self.crop is not None:
            x0, y0, w, h = self.crop
            image = image[y0:y0 + h, x0:x0 + w]
        image = np.rot90(image, k=-(self.rotate // 90), axes=(0, 1))  # clockwise
        if self.flip_x:
            image = image[:, ::-1]
        if self.flip_y:
            image = image[::-1]
        if self.scale > 1:
            image = np.clip(np.round(downscale_area(image, self.scale)), 0, 255).astype(np.uint8)
        return np.ascontiguousarray(image)

    def boxes_to_sensor(self, boxes: np.ndarray) -> np.ndarray:
        """``(D, 4)`` xyxy boxes in the model's pixels to xyxy boxes in the sensor's pixels."""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4) * self.scale
        w, h = self.cropped_size
        ow, oh = (h, w) if self.rotate in (90, 270) else (w, h)
        x1, y1, x2, y2 = boxes.T
        if self.flip_x:  # box edges, not pixel centres: a pixel [x, x + 1) maps to [ow - x - 1, ow - x)
            x1, x2 = ow - x2, ow - x1
        if self.flip_y:
            y1, y2 = oh - y2, oh - y1
        if self.rotate == 90:  # x' = h - 1 - y, y' = x  =>  y = h - x'' (edges), x = y'
            x1, y1, x2, y2 = y1, h - x2, y2, h - x1
        elif self.rotate == 180:
            x1, y1, x2, y2 = w - x2, h - y2, w - x1, h - y1
        elif self.rotate == 270:  # x' = y, y' = w - 1 - x  =>  x = w - y'' (edges), y = x'
            x1, y1, x2, y2 = w - y2, x1, w - y1, x2
        out = np.stack([x1, y1, x2, y2], axis=1)
        if self.crop is not None:
            out += np.array([self.crop[0], self.crop[1], self.crop[0], self.crop[1]], np.float64)
        return out


def fitting_settings(sensor_size: tuple[int, int], model_size: tuple[int, int], rotate: int = 0,
                     cropped: bool = False) -> str | None:
    """The largest ``sensor.scale`` and a centred ``sensor.crop`` that turn the sensor, turned by
    ``rotate`` degrees after the crop, into the model's input, as settings to type (``sensor.crop=null``
    where the whole sensor fits and a crop was ``cropped``); None if none does."""
    width, height = sensor_size
    mw, mh = model_size if rotate in (0, 180) else model_size[::-1]  # the crop is taken before the rotation
    scale = min(width // mw, height // mh)
    if scale < 1:
        return None
    w, h = mw * scale, mh * scale
    x0, y0 = (width - w) // 2, (height - h) // 2
    whole = (w, h) == (width, height)
    crop = (" sensor.crop=null" if cropped else "") if whole else f" sensor.crop=[{x0},{y0},{w},{h}]"
    return f"sensor.scale={scale}{crop}"


def fit_sensor(sensor: Sensor, model_size: tuple[int, int]) -> None:
    """Refuse a sensor whose output is not the model's size, naming both and a setting that fits."""
    if tuple(sensor.output_size) == tuple(model_size):
        return
    out_w, out_h = sensor.output_size
    hint = fitting_settings(sensor.size, model_size, sensor.rotate, cropped=sensor.crop is not None)
    fix = f"; {hint} fits" if hint else "; the sensor is smaller than the model's input: no crop and scale fit"
    raise SensorError(f"the {sensor.size[0]}x{sensor.size[1]} sensor gives {out_w}x{out_h} after crop, rotation and "
                      f"scale, but the model reads {model_size[0]}x{model_size[1]}{fix} (or sensor.model_size=sensor "
                      "to run the model at the sensor's size)")
