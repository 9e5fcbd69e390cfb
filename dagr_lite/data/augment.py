"""Training augmentation applied consistently to the image, the events and the boxes.

Coordinates are continuous with pixel ``i`` covering ``[i, i + 1)``: an event at integer pixel
``x`` sits at ``x + 0.5``, a box edge at ``x1`` sits at ``x1``. A horizontal flip maps ``u`` to
``W - u``; a zoom ``s`` with translation ``(tx, ty)`` maps ``u`` to ``s * u + tx``. Events keep
fractional pixel coordinates after a zoom; events whose pixel centre leaves the image are
dropped (the rest stay within ``[0, W - 1] x [0, H - 1]``), boxes are clipped to the image and dropped when thinner than ``min_box_size``.
A crop (:func:`crop`) cuts a smaller frame out at whole-pixel offsets: the model then trains at the
crop's size (its weights do not depend on the frame's size) and is validated at the frame's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from dagr_lite.data.dataset import Sample
from dagr_lite.graph.compiled import KERNEL  # the project's kernel options: cached, GIL released


def hflip(sample: Sample) -> Sample:
    """Mirror the sample left-right."""
    width = sample.width
    events = sample.events.clone()  # (N, 4)
    events[:, 0] = (width - 1) - events[:, 0]
    return sample.replace(events=events, image=sample.image.flip(-1), boxes=flipped_boxes(sample.boxes, width))


def flipped_boxes(boxes: torch.Tensor, width: int) -> torch.Tensor:
    """``boxes (M, 4)`` xyxy mirrored left-right in a frame ``width`` wide (a new tensor)."""
    out = boxes.clone()
    out[:, [0, 2]] = width - boxes[:, [2, 0]]
    return out


def zoomed_boxes(boxes: torch.Tensor, scale: float, tx: float, ty: float) -> torch.Tensor:
    """``boxes (M, 4)`` xyxy mapped by ``u -> scale * u + (tx, ty)`` (a new tensor, not yet clipped)."""
    return boxes * scale + torch.tensor([tx, ty, tx, ty], dtype=torch.float32)


def zoom_translate(sample: Sample, scale: float, tx: float, ty: float, *, min_box_size: float = 2.0,
                   image: bool = True, crop_follows: bool = False) -> Sample:
    """Map ``u -> scale * u + (tx, ty)`` at unchanged image size (``scale > 1`` zooms in).

    The image is resampled bilinearly (zeros outside the source, :func:`warp_image`), events are
    moved and those leaving the frame dropped, boxes are moved, clipped and dropped when thinner
    than ``min_box_size`` pixels. ``image=False`` leaves the image as it was (for a caller that
    resamples only the part it keeps: :class:`TrainAugment` with a crop). ``crop_follows``: the
    events are moved and not yet kept to the frame, for a :func:`crop` that keeps them to its
    part, which lies in the frame: the crop's events are the same either way, kept once.
    """
    height, width = sample.height, sample.width
    if image:
        sample = sample.replace(image=warp_image(sample.image, scale, tx, ty))
    events = sample.events.clone()  # (N, 4)
    events[:, 0] = scale * (events[:, 0] + 0.5) + tx - 0.5
    events[:, 1] = scale * (events[:, 1] + 0.5) + ty - 0.5
    boxes = zoomed_boxes(sample.boxes, scale, tx, ty)  # (M, 4)
    if crop_follows:
        return _boxes_inside(sample.replace(events=events), boxes, width, height, min_box_size)
    return _inside(sample, events, boxes, width, height, min_box_size)


def warp_image(image: torch.Tensor, scale: float, tx: float, ty: float,
               window: tuple[int, int, int, int] | None = None, *, flip: bool = False) -> torch.Tensor:
    """``(C, H, W)`` uint8 ``image`` resampled bilinearly by ``u -> scale * u + (tx, ty)`` (zeros outside
    the source; what ``grid_sample`` gives with ``align_corners=False``, to within one grey level of its
    float32 rounding). ``window = (x0, y0, width, height)``: only those output pixels, ``(C, height,
    width)``, each the same to the bit as in the whole warped image (its sampling position is computed
    from the same frame-wide coordinates). ``flip``: the image mirrored left-right first, to the bit
    (:func:`hflip`). An image of no channels (a frameless sample) comes back cut alone."""
    channels, height, width = image.shape
    x0, y0, w, h = window if window is not None else (0, 0, width, height)
    out = torch.empty((channels, h, w), dtype=torch.uint8)
    if channels:
        _warp_window(image.contiguous().numpy(), flip, float(scale), float(tx), float(ty), x0, y0, out.numpy())
    return out


@numba.njit(**KERNEL)
def _warp_window(image, flip, scale, tx, ty, x0, y0, out):  # pragma: no cover - compiled
    """Fills ``out (C, h, w)`` uint8 with output pixels ``[x0, x0 + w) x [y0, y0 + h)`` of ``image (C, H,
    W)`` (mirrored left-right first if ``flip``) resampled by ``u -> scale * u + (tx, ty)``: each output
    pixel centre ``u + 0.5`` reads the source at ``(u + 0.5 - t) / scale``, bilinearly between pixel
    centres, zero outside; rounded half to even, in float64."""
    channels, height, width = image.shape
    h, w = out.shape[1], out.shape[2]
    col, col_weight = _taps(x0, w, tx, scale, width)
    if flip:
        col = width - 1 - col
    row, row_weight = _taps(y0, h, ty, scale, height)
    for c in range(channels):
        for i in range(h):
            top, bottom = image[c, row[i, 0]], image[c, row[i, 1]]
            for j in range(w):
                upper = col_weight[j, 0] * top[col[j, 0]] + col_weight[j, 1] * top[col[j, 1]]
                lower = col_weight[j, 0] * bottom[col[j, 0]] + col_weight[j, 1] * bottom[col[j, 1]]
                value = row_weight[i, 0] * upper + row_weight[i, 1] * lower
                out[c, i, j] = np.uint8(min(max(np.rint(value), 0.0), 255.0))


@numba.njit(**KERNEL)
def _taps(first, count, shift, scale, size):  # pragma: no cover - compiled
    """For output pixels ``first .. first + count - 1`` along one axis: the two source pixels each reads
    (``(count, 2)``, 0 where outside the source) and their bilinear weights (0 where outside)."""
    index = np.zeros((count, 2), np.int64)
    weight = np.zeros((count, 2))
    for j in range(count):
        s = (first + j + 0.5 - shift) / scale - 0.5
        low = np.floor(s)
        frac = s - low
        for k in range(2):
            q = np.int64(low) + k
            if 0 <= q < size:
                index[j, k] = q
                weight[j, k] = frac if k else 1.0 - frac
    return index, weight


@numba.njit(**KERNEL)
def _move_events(events, flip, width, warp, scale, tx, ty, x0, y0, out_width, out_height, out):  # pragma: no cover
    """Writes to ``out`` the rows of ``events (N, 4)`` as :func:`hflip` (``flip``, a frame
    ``width`` wide), :func:`zoom_translate` (``warp``: ``scale, tx, ty``) and :func:`crop` (whole
    offsets ``x0, y0``, an ``out_width x out_height`` frame) leave them, operation for operation in
    the events' precision (``scale, tx, ty`` given in it): events whose pixel centre lies in the
    output frame, clamped to its pixels; returns how many."""
    half = np.float32(0.5)
    mirror = np.float32(width - 1)
    shift_x, shift_y = np.float32(x0), np.float32(y0)
    right, bottom = np.float32(out_width) - half, np.float32(out_height) - half
    last_x, last_y = np.float32(out_width - 1), np.float32(out_height - 1)
    kept = 0
    for i in range(events.shape[0]):
        x, y = events[i, 0], events[i, 1]
        if flip:
            x = mirror - x
        if warp:
            x = (scale * (x + half) + tx) - half
            y = (scale * (y + half) + ty) - half
        x, y = x - shift_x, y - shift_y
        if x >= -half and x < right and y >= -half and y < bottom:
            out[kept, 0] = min(max(x, np.float32(0.0)), last_x)
            out[kept, 1] = min(max(y, np.float32(0.0)), last_y)
            out[kept, 2], out[kept, 3] = events[i, 2], events[i, 3]
            kept += 1
    return kept


def _moved_boxes(sample: Sample, flip: bool, warp: tuple[float, float, float] | None, min_box_size: float) -> Sample:
    """The sample's boxes (and labels) as :func:`hflip` and :func:`zoom_translate` leave them (the events
    and the image are left as they were)."""
    boxes = flipped_boxes(sample.boxes, sample.width) if flip else sample.boxes
    if warp is None:
        return sample.replace(boxes=boxes)
    return _boxes_inside(sample, zoomed_boxes(boxes, *warp), sample.width, sample.height, min_box_size)


def _inside(sample: Sample, events: torch.Tensor, boxes: torch.Tensor, width: int, height: int,
            min_box_size: float) -> Sample:
    """``sample`` with moved ``events (N, 4)`` and ``boxes (M, 4)`` kept to a ``width x height``
    frame: events whose pixel centre lies inside, at pixel coordinates in ``[0, W - 1]``; boxes
    clipped to it and dropped when thinner than ``min_box_size``."""
    inside = ((events[:, 0] >= -0.5) & (events[:, 0] < width - 0.5)
              & (events[:, 1] >= -0.5) & (events[:, 1] < height - 0.5))
    events = events[inside]
    events[:, 0].clamp_(0, width - 1)
    events[:, 1].clamp_(0, height - 1)
    return _boxes_inside(sample.replace(events=events), boxes, width, height, min_box_size)


def _boxes_inside(sample: Sample, boxes: torch.Tensor, width: int, height: int, min_box_size: float) -> Sample:
    """``sample`` with ``boxes (M, 4)`` clipped to a ``width x height`` frame and dropped when thinner
    than ``min_box_size`` (with their labels). In NumPy: a handful of boxes costs torch's per-call overhead."""
    array = boxes.numpy()
    np.clip(array[:, 0::2], 0, width, out=array[:, 0::2])
    np.clip(array[:, 1::2], 0, height, out=array[:, 1::2])
    keep = ((array[:, 2] - array[:, 0]) >= min_box_size) & ((array[:, 3] - array[:, 1]) >= min_box_size)
    if keep.all():
        return sample.replace(boxes=boxes)
    return sample.replace(boxes=torch.from_numpy(array[keep]), labels=torch.from_numpy(sample.labels.numpy()[keep]))


def crop(sample: Sample, x0: int, y0: int, width: int, height: int, *, min_box_size: float = 2.0,
         image: torch.Tensor | None = None) -> Sample:
    """The part ``[x0, x0 + width) x [y0, y0 + height)`` of the sample as a frame of its own.

    Whole-pixel offsets: the image is sliced, events whose pixel centre falls inside are kept and
    moved by ``(-x0, -y0)`` (within ``[0, width - 1] x [0, height - 1]``), boxes are moved,
    clipped to the crop and dropped when thinner than ``min_box_size`` pixels. ``image``: that part
    of the image, made by the caller (``(C, height, width)``), in place of the slice.
    """
    if not (0 <= x0 and 0 <= y0 and width > 0 and height > 0 and x0 + width <= sample.width
            and y0 + height <= sample.height):
        raise ValueError(f"a crop of {width}x{height} at ({x0}, {y0}) must lie inside the "
                         f"{sample.width}x{sample.height} frame")
    events = sample.events - torch.tensor([x0, y0, 0, 0], dtype=sample.events.dtype)  # (N, 4), whole pixels: exact
    boxes = sample.boxes - torch.tensor([x0, y0, x0, y0], dtype=sample.boxes.dtype)  # (M, 4)
    if image is None:
        image = sample.image[:, y0:y0 + height, x0:x0 + width]
    elif tuple(image.shape) != (len(sample.image), height, width):
        raise ValueError(f"the crop's image must be ({len(sample.image)}, {height}, {width}), got {tuple(image.shape)}")
    return _inside(sample.replace(image=image), events, boxes, width, height, min_box_size)


def crop_size(height: int, width: int, fraction: float, multiple: int) -> tuple[int, int]:
    """``(height, width)`` of a training crop: ``fraction`` of each side of a ``height x width`` frame,
    rounded up to a multiple of ``multiple`` pixels (the head's largest stride, so its maps tile the
    crop) and never larger than the frame; the frame's own size when ``fraction`` is 1."""
    if not 0 < fraction <= 1:
        raise ValueError(f"the crop fraction must be in (0, 1], got {fraction}")
    if fraction == 1:
        return height, width
    return tuple(min(side, multiple * math.ceil(fraction * side / multiple)) for side in (height, width))


@dataclass
class TrainAugment:
    """Random horizontal flip, zoom/crop and translation, drawn from the generator it is given.

    Args:
        flip_prob: probability of a horizontal flip.
        zoom: ``(min, max)`` zoom factor; 1 keeps the scale, above 1 crops a random part and
            enlarges it.
        translate: largest extra shift, as a fraction of the image size, in each direction.
        min_box_size: boxes thinner than this many pixels after the transform are dropped.
        image_dropout: probability of replacing the image by mid-grey, so that a hybrid model
            learns to detect from its events alone too (drawn last: the geometry draws are
            the same with or without it).
        event_drop: each sample drops a fraction of its events drawn uniformly from
            ``[0, event_drop]`` (each event independently; drawn after the rest), so the event
            branch meets sparser and denser scenes than the data holds; 0: none. A picture of
            the events since the image (``carry_picture``, made before augmentation) keeps them.
        crop: < 1: each sample is cut to a part of this fraction of each side, :func:`crop_size`
            with ``crop_multiple`` (the head's largest stride), at a uniformly drawn place (after
            the flip, zoom and translation; :func:`crop`), and the model trains at that size; 1:
            the whole frame.
        crop_boxes: the probability that a crop is placed around a box: among the places whose
            crop holds the centre of one of the sample's boxes, drawn uniformly (a sample without
            boxes is cropped anywhere), so more of the crops hold a hand.
    """

    flip_prob: float
    zoom: tuple[float, float]
    translate: float
    min_box_size: float
    image_dropout: float
    event_drop: float
    crop: float
    crop_multiple: int
    crop_boxes: float

    def __post_init__(self):
        low, high = self.zoom
        if not 0 < low <= high:
            raise ValueError(f"zoom must be (min, max) with 0 < min <= max, got {tuple(self.zoom)}")
        if not 0 <= self.flip_prob <= 1:
            raise ValueError(f"flip_prob must be in [0, 1], got {self.flip_prob}")
        if self.translate < 0:
            raise ValueError(f"translate must be >= 0, got {self.translate}")
        if not 0 <= self.image_dropout <= 1:
            raise ValueError(f"image_dropout must be in [0, 1], got {self.image_dropout}")
        if not 0 <= self.event_drop < 1:
            raise ValueError(f"event_drop must be in [0, 1), got {self.event_drop}")
        if not 0 < self.crop <= 1:
            raise ValueError(f"crop must be a fraction in (0, 1], got {self.crop}")
        if not 0 <= self.crop_boxes <= 1:
            raise ValueError(f"crop_boxes must be in [0, 1], got {self.crop_boxes}")

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        flip, warp = self._draw_geometry(sample, rng)
        if self.crop == 1 and warp is None:  # the whole frame, perhaps mirrored: nothing leaves it
            return self._drop(hflip(sample) if flip else sample, rng)
        moved = _moved_boxes(sample, flip, warp, self.min_box_size)  # the events and the image: below, once
        x0, y0, width, height = (self._crop_place(moved, rng) if self.crop < 1  # the crop's pixels only
                                 else (0, 0, sample.width, sample.height))
        if warp is not None:
            image = warp_image(sample.image, *warp, window=(x0, y0, width, height), flip=flip)
        else:
            image = sample.image.flip(-1) if flip else sample.image
            image = image[:, y0:y0 + height, x0:x0 + width]
        scale, tx, ty = warp if warp is not None else (1.0, 0.0, 0.0)
        events = sample.events.contiguous().numpy()
        out = np.empty_like(events)
        real = events.dtype.type  # the factors in the events' own precision, as torch applies a Python float
        kept = _move_events(events, flip, sample.width, warp is not None, real(scale), real(tx), real(ty), x0, y0,
                            width, height, out)
        boxes = moved.boxes - torch.tensor([x0, y0, x0, y0], dtype=moved.boxes.dtype)  # (M, 4)
        sample = _boxes_inside(moved.replace(image=image, events=torch.from_numpy(out[:kept])), boxes, width,
                               height, self.min_box_size)
        return self._drop(sample, rng)

    def _drop(self, sample: Sample, rng: np.random.Generator) -> Sample:
        """The sample with its frame blanked (``image_dropout``) and events dropped (``event_drop``), as drawn."""
        if self.image_dropout and rng.random() < self.image_dropout:
            sample = sample.blank_frame()
        if self.event_drop:
            fraction = rng.uniform(0.0, self.event_drop)
            keep = torch.from_numpy(rng.random(len(sample.events)) >= fraction)
            sample = sample.replace(events=sample.events[keep])
        return sample

    def _crop_place(self, sample: Sample, rng: np.random.Generator) -> tuple[int, int, int, int]:
        """``(x0, y0, width, height)`` of the sample's crop (its boxes where the crop is placed around one)."""
        height, width = crop_size(sample.height, sample.width, self.crop, self.crop_multiple)
        around = rng.random() < self.crop_boxes and len(sample.boxes)
        centre = sample.boxes[int(rng.integers(len(sample.boxes)))].view(2, 2).mean(0).tolist() if around else None
        origin = []
        for axis, (size, part) in enumerate(((sample.width, width), (sample.height, height))):
            low, high = 0, size - part
            if centre is not None:  # the places whose crop holds the box's centre
                at = min(math.floor(centre[axis]), size - 1)
                low, high = max(low, at - part + 1), min(high, at)
            origin.append(int(rng.integers(low, high + 1)))
        return origin[0], origin[1], width, height

    def _draw_geometry(self, sample: Sample, rng: np.random.Generator) -> tuple[bool, tuple[float, float, float] | None]:
        """Whether to flip, and the zoom's ``(scale, tx, ty)`` (None: the identity)."""
        flip = rng.random() < self.flip_prob
        scale = float(rng.uniform(*self.zoom))
        offsets = []
        for size in (sample.width, sample.height):
            crop = rng.uniform(min(0.0, size * (1 - scale)), max(0.0, size * (1 - scale)))  # keep the crop inside
            offsets.append(crop + rng.uniform(-self.translate, self.translate) * size)
        if scale == 1.0 and offsets == [0.0, 0.0]:
            return flip, None
        return flip, (scale, offsets[0], offsets[1])
