"""The hybrid event + image detector: image CNN, event GCN branch, fusion, YOLOX head.

Fusion happens twice: image features sampled (bilinearly) at the event nodes join the node
features at the event branch's input and at each pooled stage, and at each head stride the
event branch's dense map is concatenated with the image map and mixed by a 1x1 convolution.
``use_events=False`` or ``use_image=False`` switch a branch off (the events-only and image-only
variants); nothing else changes.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dagr_lite.data.collate import Batch
from dagr_lite.nn.event_branch import EventBranch
from dagr_lite.nn.head import YOLOXHead, postprocess, yolox_losses

STRIDES = (8, 16, 32)


def _conv(c_in: int, c_out: int, stride: int = 1, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False), nn.BatchNorm2d(c_out), nn.SiLU())


class _Residual(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(_conv(channels, channels, k=1), _conv(channels, channels))

    def forward(self, x):
        return x + self.body(x)


class ImageBranch(nn.Module):
    """A small CNN from scratch: stride-4 stem, then one downsampling stage per head stride.

    Shapes:
        images ``(B, 3, H, W)`` uint8 -> maps at strides 4, 8, 16, 32 with
        ``channels = (2w, 4w, 8w, 16w)`` for ``width = w``.
    """

    def __init__(self, width: int = 16):
        super().__init__()
        self.channels = (2 * width, 4 * width, 8 * width, 16 * width)
        self.stem = nn.Sequential(_conv(3, width, 2), _conv(width, 2 * width, 2), _Residual(2 * width))
        self.stages = nn.ModuleList(nn.Sequential(_conv(c_in, c_out, 2), _Residual(c_out))
                                    for c_in, c_out in zip(self.channels[:-1], self.channels[1:]))

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(images.float() / 255.0 - 0.5)  # (B, 2w, H/4, W/4)
        maps = [x]
        for stage in self.stages:
            x = stage(x)
            maps.append(x)
        return maps


def sample_at(feature: torch.Tensor, xy: torch.Tensor, batch: torch.Tensor, stride: int) -> torch.Tensor:
    """Bilinear samples of a ``(B, C, h, w)`` map at pixel positions ``xy (N, 2)`` of samples ``batch (N,)``.

    Pixel ``(x, y)`` is the centre ``(x + 0.5, y + 0.5)``; map cell ``i`` covers pixels
    ``[i s, (i + 1) s)``. Positions beyond the outer cell centres take the edge value.
    Returns ``(N, C)``; gradient flows to ``feature``.
    """
    _, channels, h, w = feature.shape
    u = ((xy[:, 0] + 0.5) / stride - 0.5).clamp(0, w - 1)  # (N,) in cell units
    v = ((xy[:, 1] + 0.5) / stride - 0.5).clamp(0, h - 1)
    u0, v0 = u.floor().long().clamp(max=w - 1), v.floor().long().clamp(max=h - 1)
    u1, v1 = (u0 + 1).clamp(max=w - 1), (v0 + 1).clamp(max=h - 1)
    fu, fv = (u - u0).unsqueeze(1), (v - v0).unsqueeze(1)
    flat = feature.permute(0, 2, 3, 1).reshape(-1, channels)  # (B h w, C)
    base = batch * (h * w)

    def at(vv, uu):
        return flat[base + vv * w + uu]

    top = at(v0, u0) * (1 - fu) + at(v0, u1) * fu
    bottom = at(v1, u0) * (1 - fu) + at(v1, u1) * fu
    return top * (1 - fv) + bottom * fv  # (N, C)


@dataclass
class DetectorConfig:
    """Model hyper-parameters (see ``conf/model/``)."""

    height: int
    width: int
    use_events: bool = True
    use_image: bool = True
    image_width: int = 16
    event_channels: tuple[int, ...] = (16, 32, 48, 64)
    event_blocks: int = 1
    fuse_channels: int = 8
    head_hidden: int = 64
    num_classes: int = 1
    radius: float = 5.0
    beta: float = 5e-4
    max_neighbors: int = 16
    window_us: float = 33333.0


class Detector(nn.Module):
    """Event + image detector. ``forward(batch)``: losses (training) or detections (evaluation)."""

    def __init__(self, cfg: DetectorConfig):
        super().__init__()
        if not (cfg.use_events or cfg.use_image):
            raise ValueError("a detector needs at least one branch: use_events or use_image")
        self.cfg = cfg
        self.strides = list(STRIDES)
        self.image = ImageBranch(cfg.image_width) if cfg.use_image else None
        head_in = []
        if cfg.use_events:
            fuse = (cfg.fuse_channels,) * 4 if cfg.use_image else None
            self.events = EventBranch(height=cfg.height, width=cfg.width, channels=cfg.event_channels,
                                      strides=STRIDES, radius=cfg.radius, beta=cfg.beta,
                                      max_neighbors=cfg.max_neighbors, window_us=cfg.window_us,
                                      blocks=cfg.event_blocks, image_channels=fuse)
        else:
            self.events = None
        if cfg.use_image and cfg.use_events:
            # 1x1 projections of the image maps (strides 4, 8, 16, 32) sampled at event nodes.
            self.to_nodes = nn.ModuleList(nn.Conv2d(c, cfg.fuse_channels, 1) for c in self.image.channels)
            self.fuse = nn.ModuleList(_conv(ci + ce, ci, k=1) for ci, ce in
                                      zip(self.image.channels[1:], self.events.out_channels))
            head_in = list(self.image.channels[1:])
        elif cfg.use_image:
            head_in = list(self.image.channels[1:])
        else:
            head_in = list(self.events.out_channels)
        self.head = YOLOXHead(head_in, self.strides, hidden=cfg.head_hidden, num_classes=cfg.num_classes)

    def features(self, batch: Batch) -> list[torch.Tensor]:
        """The fused maps the head reads, one per stride."""
        image_maps = self.image(batch.images) if self.image is not None else None
        if self.events is None:
            return image_maps[1:]
        sampler = self._node_sampler(image_maps) if image_maps is not None else None
        event_maps = self.events(batch.events, batch.batch_index, len(batch), image_sampler=sampler,
                                 edge_index=batch.edge_index)
        if image_maps is None:
            return event_maps
        fused = []
        for fuse, image_map, event_map in zip(self.fuse, image_maps[1:], event_maps):
            if event_map.shape[-2:] != image_map.shape[-2:]:  # ceil vs floor on odd sizes
                event_map = F.interpolate(event_map, size=image_map.shape[-2:], mode="nearest")
            fused.append(fuse(torch.cat([image_map, event_map], dim=1)))
        return fused

    def _node_sampler(self, image_maps: list[torch.Tensor]):
        """Image features at event nodes: level 0 from the stride-4 map, pooled levels from theirs."""
        node_maps = [proj(m) for proj, m in zip(self.to_nodes, image_maps)]
        strides = (4, *STRIDES)

        def sampler(xy: torch.Tensor, node_batch: torch.Tensor, level: int) -> torch.Tensor:
            return sample_at(node_maps[level], xy, node_batch, strides[level])

        return sampler

    def forward(self, batch: Batch, *, conf_threshold: float = 0.001, nms_threshold: float = 0.65):
        raw, shapes = self.head(self.features(batch))
        if self.training:
            return yolox_losses(raw, shapes, self.strides, batch.boxes, batch.labels)
        return postprocess(raw, shapes, self.strides, conf_threshold=conf_threshold, nms_threshold=nms_threshold,
                           image_size=(self.cfg.height, self.cfg.width))
