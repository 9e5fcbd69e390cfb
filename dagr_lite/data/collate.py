"""Batching samples with different numbers of events and boxes."""
from __future__ import annotations

import multiprocessing
from dataclasses import dataclass, fields
from typing import Sequence

import torch

from dagr_lite.data.dataset import Sample
from dagr_lite.graph.spec import EventGraphSpec


@dataclass
class Batch:
    """A batch of ``B`` samples.

    Attributes:
        events: ``(N, 4)`` float32 x, y, t, p of all samples, concatenated in sample order.
        batch_index: ``(N,)`` int64 sample of each event.
        ptr: ``(B + 1,)`` int64 offsets: the events of sample ``b`` are ``events[ptr[b]:ptr[b + 1]]``.
        images: ``(B, 3, H, W)`` uint8.
        boxes: ``B`` tensors ``(M_b, 4)`` float32 x1, y1, x2, y2 in pixels.
        labels: ``B`` tensors ``(M_b,)`` int64.
        videos, frames, image_frames: names of the samples (video and label frame).
        t_start_us, t_end_us: ``(B,)`` int64 event windows; ``t_end_us`` is when the boxes hold.
        t_image_us: ``(B,)`` int64 image times; event ``t`` counts from its sample's image time.
        edge_index: ``(2, E)`` causal event graph over ``events`` (see :class:`GraphCollate`), or None.
    """

    events: torch.Tensor
    batch_index: torch.Tensor
    ptr: torch.Tensor
    images: torch.Tensor
    boxes: list[torch.Tensor]
    labels: list[torch.Tensor]
    videos: list[str]
    frames: torch.Tensor
    image_frames: torch.Tensor
    t_start_us: torch.Tensor
    t_end_us: torch.Tensor
    t_image_us: torch.Tensor
    edge_index: torch.Tensor | None = None  # (2, E) event graph, when the loader builds it

    def __len__(self) -> int:
        return len(self.videos)

    @property
    def age_us(self) -> torch.Tensor:
        """``(B,)`` how old each sample's image is when its boxes are asked for, in microseconds."""
        return self.t_end_us - self.t_image_us

    def _map(self, fn) -> "Batch":
        values = {}
        for field in fields(self):
            value = getattr(self, field.name)
            if isinstance(value, torch.Tensor):
                value = fn(value)
            elif isinstance(value, list) and value and isinstance(value[0], torch.Tensor):
                value = [fn(v) for v in value]
            values[field.name] = value
        return Batch(**values)

    def to(self, device, non_blocking: bool = False) -> "Batch":
        return self._map(lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "Batch":
        return self._map(lambda t: t.pin_memory())

    def pooled(self) -> torch.Tensor | None:
        """``(N,)`` bool: the events of each sample's own window ``[t_start_us, t_end_us)``, which
        the event branch pools; the others are its graph context (read as neighbours only). None
        when every event is pooled."""
        start = (self.t_start_us - self.t_image_us).to(self.events.dtype)  # in the events' own time
        mask = self.events[:, 2] >= start[self.batch_index]
        return None if bool(mask.all()) else mask

    def padded_boxes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes padded to ``(B, M_max, 4)`` with a ``(B, M_max)`` bool mask of real boxes."""
        m_max = max((len(b) for b in self.boxes), default=0)
        padded = self.images.new_zeros((len(self), m_max, 4), dtype=torch.float32)  # (B, M_max, 4)
        mask = torch.zeros((len(self), m_max), dtype=torch.bool, device=self.images.device)  # (B, M_max)
        for b, boxes in enumerate(self.boxes):
            padded[b, : len(boxes)] = boxes
            mask[b, : len(boxes)] = True
        return padded, mask


def collate(samples: Sequence[Sample]) -> Batch:
    """Concatenate events (with a sample index per event), stack images, list boxes."""
    if not samples:
        raise ValueError("cannot collate an empty list of samples")
    sizes = {tuple(s.image.shape) for s in samples}
    if len(sizes) != 1:
        names = ", ".join(f"{s.video} frame {s.frame}: {tuple(s.image.shape)}" for s in samples)
        raise ValueError(f"images of one batch must have the same shape, got {names}")
    counts = torch.tensor([len(s.events) for s in samples], dtype=torch.int64)  # (B,)
    ptr = torch.zeros(len(samples) + 1, dtype=torch.int64)  # (B + 1,)
    torch.cumsum(counts, 0, out=ptr[1:])
    return Batch(
        events=torch.cat([s.events for s in samples]),  # (N, 4)
        batch_index=torch.repeat_interleave(torch.arange(len(samples)), counts),  # (N,)
        ptr=ptr,
        images=torch.stack([s.image for s in samples]),  # (B, 3, H, W)
        boxes=[s.boxes for s in samples],
        labels=[s.labels for s in samples],
        videos=[s.video for s in samples],
        frames=torch.tensor([s.frame for s in samples], dtype=torch.int64),
        image_frames=torch.tensor([s.image_frame for s in samples], dtype=torch.int64),
        t_start_us=torch.tensor([s.t_start_us for s in samples], dtype=torch.int64),
        t_end_us=torch.tensor([s.t_end_us for s in samples], dtype=torch.int64),
        t_image_us=torch.tensor([s.t_image_us for s in samples], dtype=torch.int64),
    )


class GraphCollate:
    """Collate and build the causal event graph in the loader's worker processes.

    ``spec`` is the model's own :class:`~dagr_lite.graph.spec.EventGraphSpec`, so the loader's
    graph is the one the model would build; building it in the workers keeps it off the training step.

    :attr:`building` switches the workers' graph off and on while they run (a flag in shared memory
    that they inherit): off, batches come without a graph (``edge_index`` None), as a hybrid's
    ``trainer.dense_first`` phase reads them. Batches made before a switch keep what they were
    made with; :meth:`complete` gives such a batch its graph.
    """

    def __init__(self, spec: EventGraphSpec):
        self.spec = spec
        self._building = multiprocessing.RawValue("b", 1)
        # Compile (or load) the graph builder here, so that the forked workers inherit it.
        spec.edges(torch.tensor([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 1.0, 1.0]]), workers=1)

    @property
    def building(self) -> bool:
        """Whether batches made from now on get their graph (every worker reads the same flag)."""
        return bool(self._building.value)

    @building.setter
    def building(self, on: bool) -> None:
        self._building.value = 1 if on else 0

    def __call__(self, samples: Sequence[Sample]) -> Batch:
        batch = collate(samples)
        if self.building:
            batch.edge_index = self.spec.edges(batch.events, batch.batch_index, workers=1)
        return batch

    def complete(self, batch: Batch) -> Batch:
        """``batch`` with its graph: built here (with the machine's threads) when it came without one."""
        if batch.edge_index is None:
            batch.edge_index = self.spec.edges(batch.events, batch.batch_index)
        return batch
