"""The hybrid event + image detector: image CNN, event GCN branch, fusion, YOLOX head.

Fusion happens twice: image features sampled (bilinearly) at the event nodes join the node
features at the event branch's input and at each pooled stage (beside each node's time since
the image), and at each head stride the event branch's dense map, the recency maps (how
recently each cell saw events, at the query time), the image map and the image's age (a
constant plane, in ``time_scale_us``) are concatenated and mixed by a 1x1 convolution, so the
head can move from the stale image to the events as the image ages. With ``late_query`` the
recency maps and the age (the query maps) join the head after its towers instead, and the
head gets towers of its own over the image maps, gated by the age (:class:`YOLOXHead`): its
towers then see nothing that depends on the query time. Only the dense maps depend on the
query time; node features never do (docs/design.md, "The event graph").
``use_events=False`` or ``use_image=False`` switch a branch off (the events-only and image-only
variants); nothing else changes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dagr_lite.data.collate import Batch
from dagr_lite.data.dataset import PICTURE_CHANNELS, RGB_CHANNELS
from dagr_lite.graph.pool import recency_maps
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.blocks import Residual, conv_bn_act
from dagr_lite.nn.event_branch import EventBranch
from dagr_lite.nn.kernels import bilinear_at, channels_last, compiled_inference
from dagr_lite.nn.head import TowerCache, YOLOXHead, block_rows, flat_map, postprocess, yolox_losses


IMAGE_STEMS = ("patch", "conv")


class ImageBranch(nn.Module):
    """A small CNN from scratch: a stride-4 stem, then one downsampling stage per doubling of
    the stride up to the largest head stride.

    Args:
        width: ``w``; the stem gives ``2w`` channels, the stage at stride ``4 * 2^(i + 1)`` ``2^(i + 2) w``.
        strides: the head's strides, each twice the one before, starting at 8 or above.
        stem: ``"patch"``: one 4x4 convolution of stride 4 (each stride-4 cell reads its own 4x4
            pixels), then a residual block; ``"conv"``: two 3x3 convolutions of stride 2 (``w``
            then ``2w`` channels), then the residual block. Both give the same stride-4 map
            size; the patch stem never computes a map at half resolution, which makes training
            steps on a CPU faster (``benchmarks/cpu_step.py``).
        in_channels: the image's channels (3: RGB; more with a picture of events beside it).

    Shapes:
        images ``(B, in_channels, H, W)`` uint8 -> maps at strides ``(4, *strides)`` (the stride-4 map is
        what event nodes sample at the input level), with ``channels = (2w, ...)``.
    """

    def __init__(self, width: int, strides: Sequence[int], stem: str = "patch", in_channels: int = 3):
        super().__init__()
        if stem not in IMAGE_STEMS:
            raise ValueError(f"image_stem must be one of {list(IMAGE_STEMS)}, got {stem!r}")
        strides = [int(s) for s in strides]
        first = strides[0] if strides else 0
        if (not strides or first < 8 or first & (first - 1)
                or strides != [first * 2 ** i for i in range(len(strides))]):
            raise ValueError(f"the image branch needs strides that double, starting at a power of two >= 8 "
                             f"(e.g. [8, 16, 32] or [16, 32]), got {list(strides)}")
        self.strides, self.stem_kind = (4, *strides), stem
        stage_strides = [8 * 2 ** i for i in range(int(math.log2(strides[-1] // 4)))]  # 8, 16, ..., largest
        stage_channels = [2 * width] + [4 * width * 2 ** i for i in range(len(stage_strides))]
        self.read = [0] + [1 + stage_strides.index(s) for s in strides]  # which maps are given out
        self.channels = tuple(stage_channels[i] for i in self.read)
        if stem == "patch":
            self.stem = nn.Sequential(conv_bn_act(in_channels, 2 * width, stride=4, k=4), Residual(2 * width))
        else:
            self.stem = nn.Sequential(conv_bn_act(in_channels, width, stride=2), conv_bn_act(width, 2 * width, stride=2),
                                      Residual(2 * width))
        self.stages = nn.ModuleList(nn.Sequential(conv_bn_act(c_in, c_out, stride=2), Residual(c_out))
                                    for c_in, c_out in zip(stage_channels[:-1], stage_channels[1:]))

    # True once :meth:`read_raw_pixels` folded the pixels' scaling into the stem.
    raw_pixels = False

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(self._pixels(images))  # (B, 2w, ceil(H/4), ceil(W/4))
        return self._stages(x)

    def _pixels(self, images: torch.Tensor) -> torch.Tensor:
        """The stem's input: the images in the weights' dtype (in their layout: channels last stays), scaled
        unless :meth:`read_raw_pixels` folded the scaling, a patch stem's edge padded with grey."""
        x = images.to(self.stem[0][0].weight.dtype)
        if not self.raw_pixels:
            x = x / 255.0 - 0.5
        if self.stem_kind == "patch" and (x.shape[-1] % 4 or x.shape[-2] % 4):  # whole 4x4 patches: grey at the edge
            x = F.pad(x, (0, -x.shape[-1] % 4, 0, -x.shape[-2] % 4), value=127.5 if self.raw_pixels else 0.0)
        return x

    def split_stem(self, fixed: int) -> "ImageBranch":
        """For inference, in place, after :meth:`read_raw_pixels` and before convolutions are packed: the
        patch stem's first convolution as two, over the first ``fixed`` input channels (with the bias)
        and over the rest, so that a part of the input that stays (a carry branch's camera frame) is
        convolved once (:meth:`fixed_part`) and each call convolves the rest (:meth:`forward_from`)."""
        block = self.stem[0]
        conv = block[0]
        if not (self.raw_pixels and type(conv) is nn.Conv2d and conv.bias is not None and isinstance(block[1], nn.Identity)
                and isinstance(block[2], nn.SiLU) and 0 < fixed < conv.in_channels):
            raise ValueError(f"split_stem needs a patch stem reading raw pixels whose batch norm is folded, not packed "
                             f"yet, and 0 < fixed < {conv.in_channels}, got fixed={fixed}")
        parts = []
        for lo, hi, bias in ((0, fixed, True), (fixed, conv.in_channels, False)):
            part = nn.Conv2d(hi - lo, conv.out_channels, conv.kernel_size, conv.stride, conv.padding, bias=bias,
                             device=conv.weight.device, dtype=conv.weight.dtype)
            with torch.no_grad():
                part.weight.copy_(conv.weight[:, lo:hi])
                if bias:
                    part.bias.copy_(conv.bias)
            parts.append(part)
        self.stem_fixed, self.stem_rest = parts
        return self

    def fixed_part(self, images: torch.Tensor) -> torch.Tensor:
        """After :meth:`split_stem`: the stem convolution's share of the fixed channels ``images (B, fixed, H, W)``."""
        return self.stem_fixed(self._pixels(images))

    def forward_from(self, fixed: torch.Tensor, images: torch.Tensor) -> list[torch.Tensor]:
        """After :meth:`split_stem`: :meth:`forward` of the fixed channels, whose :meth:`fixed_part` is
        ``fixed``, joined with ``images (B, C - fixed, H, W)``, the rest."""
        x = self.stem[1](F.silu(self.stem_rest(self._pixels(images)) + fixed))  # the SiLU, then the residual block
        return self._stages(x)

    def _stages(self, x: torch.Tensor) -> list[torch.Tensor]:
        maps = [x]
        for stage in self.stages:
            x = stage(x)
            maps.append(x)
        return [maps[i] for i in self.read]

    def read_raw_pixels(self) -> "ImageBranch":
        """Folds the pixels' scaling (``x / 255 - 0.5``) into the patch stem's weight and bias, in place
        (``W / 255``, ``b - 0.5 sum W``, in float64), so :meth:`forward` reads the uint8 values as they
        are: one operation less per call, and a channels-last input is never copied. The same function
        up to rounding; for inference (the streaming detector's copy). A ``"conv"`` stem, whose zero
        padding lies in the scaled pixels, is refused."""
        if self.stem_kind != "patch":
            raise ValueError(f"only the patch stem reads raw pixels (its 4x4 patches have no padding), not {self.stem_kind!r}")
        if self.raw_pixels:
            return self
        conv = self.stem[0][0]
        weight = conv.weight.detach().double()
        bias = conv.bias.detach().double() if conv.bias is not None else torch.zeros(conv.out_channels, dtype=torch.float64,
                                                                                     device=weight.device)
        with torch.no_grad():
            new_bias = (bias - 0.5 * weight.sum(dim=(1, 2, 3))).to(conv.weight.dtype)
            conv.weight.copy_((weight / 255.0).to(conv.weight.dtype))
        if conv.bias is None:
            conv.bias = nn.Parameter(new_bias, requires_grad=conv.weight.requires_grad)
        else:
            with torch.no_grad():
                conv.bias.copy_(new_bias)
        self.raw_pixels = True
        return self


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


class CarryAttention(nn.Module):
    """Local attention from the events' now to the image's then, at one map stride.

    Each cell ``x`` of a query map (the carry branch's: the events since the image, and the frame)
    attends to the image map's cells ``x + d``, ``|d| <= radius`` each way (cells beyond the map
    are left out), and to a "nothing" slot of logit 0 and value 0; its output is the attention-
    weighted sum of the image cells' values::

        a(x, d) = softmax_d [0, <q(x), k(x + d)> / sqrt(D)],   out(x) = sum_d a(x, d) v(x + d)

    with 1x1 projections ``q``, ``k`` (``dim`` channels) and ``v`` (``value_channels``). A hand that
    moved since the image by up to ``radius`` cells can so bring the image's features of it to
    where its events are now. Shapes: query ``(B, Cq, h, w)``, image ``(B, Ci, h, w)`` ->
    ``(B, value_channels, h, w)``.
    """

    def __init__(self, query_channels: int, image_channels: int, radius: int, dim: int = 16,
                 value_channels: int = 16):
        super().__init__()
        if not (isinstance(radius, int) and radius >= 1):
            raise ValueError(f"carry_attend must be an integer >= 1 (cells each way), got {radius!r}")
        self.radius, self.dim, self.value_channels = radius, dim, value_channels
        self.query = nn.Conv2d(query_channels, dim, 1)
        self.key = nn.Conv2d(image_channels, dim, 1)
        self.value = nn.Conv2d(image_channels, value_channels, 1)

    def forward(self, query_map: torch.Tensor, image_map: torch.Tensor) -> torch.Tensor:
        if query_map.shape[-2:] != image_map.shape[-2:]:
            raise ValueError(f"carry attention: query map {tuple(query_map.shape[-2:])} and image map "
                             f"{tuple(image_map.shape[-2:])} differ in size")
        b, _, h, w = query_map.shape
        size, pad = 2 * self.radius + 1, self.radius
        q = self.query(query_map).reshape(b, self.dim, 1, h * w)
        k = F.unfold(self.key(image_map), size, padding=pad).reshape(b, self.dim, size * size, h * w)
        v = F.unfold(self.value(image_map), size, padding=pad).reshape(b, self.value_channels, size * size, h * w)
        logits = (q * k).sum(1) / math.sqrt(self.dim)  # (B, S, hw)
        inside = F.unfold(query_map.new_ones(1, 1, h, w), size, padding=pad) > 0  # (1, S, hw): d within the map
        logits = logits.masked_fill(~inside, float("-inf"))
        weights = torch.softmax(torch.cat([logits.new_zeros(b, 1, h * w), logits], dim=1), dim=1)[:, 1:]
        return (weights.unsqueeze(1) * v).sum(2).reshape(b, self.value_channels, h, w)


# The stride whose maps the carry attention reads; its output joins the fusion at every head stride.
ATTEND_STRIDE = 16


@dataclass(frozen=True)
class DetectorConfig:
    """Everything that defines a detector's architecture (defaults: ``conf/model/hybrid.yaml``).

    Saved in every checkpoint (:meth:`as_dict`), so a checkpoint rebuilds its own model.

    Args:
        height, width: frame size in pixels.
        use_events, use_image: which branches exist (at least one).
        image_width: the image CNN's stem width.
        event_channels: event-branch features of the input stage and of each pooled stage.
        event_blocks: GCN blocks per event stage.
        fuse_channels: image channels sampled at event nodes, per level (hybrid only).
        head_hidden: the head's width; num_classes: object classes.
        strides: the head's output strides in pixels.
        graph: the event graph (None without an event branch).
        time_scale_us: the time unit of the image's age and of the nodes' time since the image.
        recency_us: time constants of the recency maps read beside the event maps (see
            :func:`~dagr_lite.graph.pool.recency_maps`); empty for none.
        event_head_weight: in a hybrid, > 0 adds a second head that reads the event branch and
            the recency maps alone (as an events-only model's head does, at half its width); in training its loss,
            times this weight, joins the fused head's, so the events learn to detect by
            themselves. 0: no such head.
        event_answers: with an event head, its boxes join the fused head's in every answer (its
            anchors beside the fused head's, before one NMS): the events' own detections, which
            find hands that moved since the image where the fused head still trusts the image.
            False: detection reads the fused head alone (the event head trains only).
        image_stem: the image branch's stride-4 stem, ``"patch"`` or ``"conv"`` (see :class:`ImageBranch`).
        late_query: the recency maps and the image's age enter the head after its towers, and a
            hybrid's head has image towers gated by the age (true), so that a streaming answer
            recomputes the towers only where event maps changed; false: they join the fusion
            before the towers (as in checkpoints saved before the key).
        geometry: event nodes also carry the shape of their causal neighbourhood
            (:func:`~dagr_lite.nn.event_branch.neighbourhood_geometry`); false in checkpoints saved
            before the key.
        directional: the event branch's first stage weights each message by the neighbour's
            offset (:class:`~dagr_lite.nn.event_branch.EventBranch`); false in checkpoints saved
            before the key.
        image_channels: the channels the image branch reads: 3 (RGB), or 6 or 7 with a picture of the
            events since the image (``data.carry_picture``) read by its stem.
        carry_width: > 0 (a hybrid): the images hold the camera frame and, in the channels after it, the
            picture of every event since the image (``data.carry_picture``); a carry branch of this
            width (an :class:`ImageBranch` of its own) reads the picture, and its maps join the
            fusion beside the event maps, while the image branch and the event nodes read the frame
            alone. 0: none.
        carry_channels: the channels of the picture the carry branch reads: 3, or 4 with the
            recency over a recent window (``data.carry_recent_us``), 3 more of the confirmed
            events (``data.carry_confirm_us``), 3 more of the frame moved by the camera's motion
            (``data.carry_align_us``), one per span of time since the image (``data.carry_spans_us``)
            and one of each pixel's first event (``data.carry_onset``).
        carry_frame: the carry branch also reads the camera frame beside the picture (its stem
            joins them at the first layer, as the dense peer's image branch does); false: the
            picture alone (as in checkpoints saved before the key). Read only with a carry branch.
        carry_attend: > 0 (with a carry branch): each cell of the carry branch's stride-16 map
            attends to the image's stride-16 cells up to this many cells away each way
            (:class:`CarryAttention`), and what it gathers joins the fusion at every stride beside
            the carry maps, so the image's features of a hand that moved can follow its events.
            0: none (as in checkpoints saved before the key).
        event_dense: > 0: the event branch's pooled stages are convolutions over its nodes max-pooled
            into cells of this many pixels and written out as a map (the first stride, or that
            halved; :class:`~dagr_lite.nn.event_branch.EventBranch` ``dense``); 0: GCN blocks over
            the pooled graphs (as in checkpoints saved before the key).
    """

    height: int
    width: int
    use_events: bool
    use_image: bool
    image_width: int
    event_channels: tuple[int, ...]
    event_blocks: int
    fuse_channels: int
    head_hidden: int
    num_classes: int
    strides: tuple[int, ...]
    graph: EventGraphSpec | None
    time_scale_us: float
    recency_us: tuple[float, ...]
    late_query: bool
    event_head_weight: float = 0.0
    event_answers: bool = False
    image_stem: str = "patch"
    geometry: bool = False
    directional: bool = False
    image_channels: int = 3
    carry_width: int = 0
    carry_channels: int = PICTURE_CHANNELS
    carry_frame: bool = False
    carry_attend: int = 0
    event_dense: int = 0

    def __post_init__(self):
        if not (self.use_events or self.use_image):
            raise ValueError("a detector needs at least one branch: use_events or use_image")
        if not (math.isfinite(self.event_head_weight) and self.event_head_weight >= 0):
            raise ValueError(f"event_head_weight must be a number >= 0, got {self.event_head_weight!r}")
        if self.event_answers and not (self.use_image and self.use_events and self.event_head_weight > 0
                                       and not self.late_query):
            raise ValueError("event_answers needs a hybrid with an event head (event_head_weight > 0) whose query maps "
                             "join at the fusion (late_query false)")
        if self.use_events and self.graph is None:
            raise ValueError("a detector with an event branch needs an event-graph spec (graph)")
        if not (isinstance(self.image_channels, int) and self.image_channels >= 1):
            raise ValueError(f"image_channels must be a positive integer, got {self.image_channels!r}")
        if not (isinstance(self.carry_channels, int) and self.carry_channels >= 1):
            raise ValueError(f"carry_channels must be a positive integer, got {self.carry_channels!r}")
        if not (isinstance(self.carry_width, int) and self.carry_width >= 0):
            raise ValueError(f"carry_width must be an integer >= 0, got {self.carry_width!r}")
        if self.carry_width and not (self.use_image and self.use_events and not self.late_query):
            raise ValueError(f"carry_width={self.carry_width} (a carry branch) needs a hybrid whose query maps join at "
                             "the fusion (late_query false), since its maps join the fusion beside the event maps; "
                             "carry_width=0 for any other model")
        if not (isinstance(self.carry_attend, int) and self.carry_attend >= 0):
            raise ValueError(f"carry_attend must be an integer >= 0, got {self.carry_attend!r}")
        if self.carry_attend and not (self.carry_width and ATTEND_STRIDE in self.strides):
            raise ValueError(f"carry_attend={self.carry_attend} needs a carry branch (carry_width > 0) and the "
                             f"head stride {ATTEND_STRIDE} among strides {list(self.strides)}")
        if self.image_stem not in IMAGE_STEMS:
            raise ValueError(f"image_stem must be one of {list(IMAGE_STEMS)}, got {self.image_stem!r}")

    def as_dict(self) -> dict:
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["event_channels"], values["strides"] = list(self.event_channels), list(self.strides)
        values["recency_us"] = list(self.recency_us)
        values["graph"] = None if self.graph is None else self.graph.as_dict()
        return values

    @classmethod
    def from_dict(cls, values: dict) -> "DetectorConfig":
        """The config of :meth:`as_dict`'s output; a missing or unknown key is an error naming it
        (a checkpoint's config from before a key was added is upgraded where checkpoints are read,
        :func:`dagr_lite.engine.checkpoint.upgrade`)."""
        names = {f.name for f in fields(cls)}
        if set(values) != names:
            missing, unknown = sorted(names - set(values)), sorted(set(values) - names)
            raise ValueError(f"detector config: missing keys {missing}, unknown keys {unknown}")
        graph = values["graph"]
        return cls(**{**values, "event_channels": tuple(values["event_channels"]), "strides": tuple(values["strides"]),
                      "recency_us": tuple(values["recency_us"]),
                      "graph": None if graph is None else EventGraphSpec.from_dict(dict(graph))})



class Detector(nn.Module):
    """Event + image detector. ``forward(batch)``: losses (training) or detections (evaluation)."""

    def __init__(self, cfg: DetectorConfig):
        super().__init__()
        self.cfg = cfg
        self.strides = list(cfg.strides)
        self.image = ImageBranch(cfg.image_width, cfg.strides, cfg.image_stem, cfg.image_channels) if cfg.use_image else None
        if cfg.use_events:
            # image features join the nodes at every level (with dense pooled stages, the input level alone)
            fuse = ((cfg.fuse_channels,) + (0 if cfg.event_dense else cfg.fuse_channels,) * len(cfg.strides)
                    if cfg.use_image else None)
            self.events = EventBranch(height=cfg.height, width=cfg.width, channels=cfg.event_channels,
                                      strides=cfg.strides, graph=cfg.graph,
                                      time_scale_us=cfg.time_scale_us if cfg.use_image else None,
                                      blocks=cfg.event_blocks, image_channels=fuse, geometry=cfg.geometry,
                                      directional=cfg.directional, dense=cfg.event_dense)
        else:
            self.events = None
        # The carry branch reads the picture of the events since the image (the channels after the
        # frame's), with carry_frame the frame beside it.
        self.carry = (ImageBranch(cfg.carry_width, cfg.strides, "patch",
                                  cfg.carry_channels + (RGB_CHANNELS if cfg.carry_frame else 0)) if cfg.carry_width
                      else None)
        self.attend = None
        if cfg.carry_attend:
            at = cfg.strides.index(ATTEND_STRIDE)
            self.attend = CarryAttention(self.carry.channels[1 + at], self.image.channels[1 + at], cfg.carry_attend)
        carry = self.carry_widths
        # The query maps (recency, and with an image its age) join before the towers (early: at the
        # fusion, or an events-only head's input) or after them (late_query).
        late = self.num_query if cfg.late_query else 0
        early = 0 if cfg.late_query else self.num_recency  # the recency maps, where they join early
        if cfg.use_image and cfg.use_events:
            # 1x1 projections of the image maps (strides 4, 8, 16, 32) sampled at event nodes.
            self.to_nodes = nn.ModuleList(nn.Conv2d(c, cfg.fuse_channels, 1) for c, k in
                                          zip(self.image.channels, self.events.image_channels) if k)
            # The fusion mixes the image and event maps (and, early, the recency maps and the age plane).
            age = 0 if cfg.late_query else 1
            self.fuse = nn.ModuleList(conv_bn_act(ci + ce + early + cc + age, ci, k=1) for ci, ce, cc in
                                      zip(self.image.channels[1:], self.events.out_channels, carry))
        head_in = (list(self.image.channels[1:]) if cfg.use_image
                   else [c + early for c in self.events.out_channels])
        self.head = YOLOXHead(head_in, self.strides, hidden=cfg.head_hidden, num_classes=cfg.num_classes,
                              late_channels=late, image_channels=(list(self.image.channels[1:]) if late and
                                                                  cfg.use_image and cfg.use_events else None))
        # Training only: the events' own head (deep supervision of the event branch in a hybrid), at
        # half the width: a quarter of the main head's cost, and the event maps must do more of the work.
        self.event_head = (YOLOXHead([c + early for c in self.events.out_channels], self.strides,
                                     hidden=max(cfg.head_hidden // 2, 1), num_classes=cfg.num_classes,
                                     late_channels=self.num_recency if cfg.late_query else 0)
                           if cfg.use_image and cfg.use_events and cfg.event_head_weight > 0 else None)
        # Training on several processes sets this: the loss normaliser of the global batch (see yolox_losses).
        self.loss_normaliser = None
        # Inference only: each stride's fusion split by its inputs (split_fusion, the streaming detector's copy).
        self.fuse_parts: nn.ModuleList | None = None

    @property
    def num_recency(self) -> int:
        """Channels of the recency maps (two polarities per time constant; none without events)."""
        return 2 * len(self.cfg.recency_us) if self.cfg.use_events else 0

    @property
    def num_query(self) -> int:
        """Channels of the query maps: the recency maps, and in a hybrid the image's age."""
        return self.num_recency + (1 if self.cfg.use_image and self.cfg.use_events else 0)

    @property
    def graph_spec(self) -> EventGraphSpec | None:
        """The event graph this model reads (None without an event branch)."""
        return self.cfg.graph

    def features(self, batch: Batch) -> tuple[list[torch.Tensor], list[torch.Tensor] | None,
                                              list[torch.Tensor] | None]:
        """The head's inputs (:meth:`combine`): ``model.head(*model.features(batch))`` gives the fused head's
        raw output (with ``event_answers`` an answer also holds the event head's: :meth:`outputs`)."""
        maps, query, image, _ = self._features(batch)
        return maps, query, image

    def _features(self, batch: Batch, image: bool = True, events: bool = True, graph: bool = True):
        """:meth:`features`, and in training the event head's input (its maps and query maps; else
        None). ``image=False``, ``events=False``, ``graph=False``: see :meth:`forward`."""
        if not events and self.events is not None:
            return self._image_features(batch)
        if self.image is None:
            image_maps = None
        elif image or self.events is None:
            image_maps = self.frame_maps(batch.images)
        else:  # every image feature zero, the image branch not run
            image_maps = [torch.zeros(len(batch), c, math.ceil(self.cfg.height / s), math.ceil(self.cfg.width / s),
                                      device=batch.events.device) for c, s in zip(self.image.channels, self.image.strides)]
        if self.events is None:
            return image_maps[1:], None, None, None
        pooled = batch.pooled()
        if not graph:  # the event branch's maps zero, the branch not run (nor its image features at the nodes)
            if image_maps is None:
                raise ValueError("forward(graph=False) needs a hybrid: this detector has no image branch")
            event_maps = self.zero_event_maps(image_maps)
        else:
            if image_maps is None:
                sampler = None
            elif image:
                sampler = self.node_sampler(self.node_maps(image_maps))
            else:
                sampler = self.blank_sampler
            event_maps = self.events(batch.events, batch.batch_index, len(batch), image_sampler=sampler,
                                     edge_index=batch.edge_index, pooled=pooled)
        events, event_batch = (batch.events, batch.batch_index) if pooled is None else \
            (batch.events[pooled], batch.batch_index[pooled])  # the recency of the sample's own events
        recency = [recency_maps(events, event_batch, batch.age_us, batch_size=len(batch), stride=stride,
                                height=m.shape[-2], width=m.shape[-1], taus_us=self.cfg.recency_us)
                   for m, stride in zip(event_maps, self.strides)]
        images = batch.images
        if not image and self.cfg.carry_frame:  # the carry branch reads a grey frame too
            images = images.clone()
            images[:, :RGB_CHANNELS] = 128
        maps, query, image_inputs = self.combine(image_maps, event_maps, recency, batch.age_us,
                                                 self.carry_maps(images))
        event_inputs = None
        if self.event_head is not None and (self.training or self.cfg.event_answers):
            event_inputs = self.event_head_inputs(event_maps, recency)
        return maps, query, image_inputs, event_inputs

    def event_head_inputs(self, event_maps: list[torch.Tensor], recency: list[torch.Tensor]) -> tuple:
        """The event head's inputs: the event maps and the recency maps (joined, or apart with ``late_query``)."""
        if self.cfg.late_query:
            return event_maps, recency
        return [torch.cat([m, r], dim=1) for m, r in zip(event_maps, recency)], None

    def _image_features(self, batch: Batch):
        """:meth:`_features` of a hybrid whose event maps and recency maps are all zero, the event
        branch not run (``forward(events=False)``)."""
        if self.image is None:
            raise ValueError("forward(events=False) needs a hybrid: this detector has no image branch")
        image_maps = self.frame_maps(batch.images)
        zeros = self.zero_event_maps(image_maps)
        recency = [m.new_zeros(len(batch), self.num_recency, *m.shape[-2:]) for m in image_maps[1:]]
        carry = None if self.carry is None else [m.new_zeros(len(batch), c, *m.shape[-2:]) for m, c in
                                                 zip(image_maps[1:], self.carry_widths)]
        maps, query, image_inputs = self.combine(image_maps, zeros, recency, batch.age_us, carry, attend=False)
        return maps, query, image_inputs, None

    def zero_event_maps(self, image_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """Event maps of zeros, each the size of the image map of its stride (the event branch's
        own size, ``ceil(H / stride)``), for a hybrid whose event branch is not run."""
        return [m.new_zeros(len(m), c, *m.shape[-2:]) for m, c in zip(image_maps[1:], self.events.out_channels)]

    def frame_maps(self, images: torch.Tensor) -> list[torch.Tensor]:
        """The image branch's maps of ``(B, C, H, W)`` images (the channels it reads: the frame, or
        with ``image_channels`` 6 the frame and the picture beside it)."""
        return self.image(images[:, :self.cfg.image_channels])

    def carry_maps(self, images: torch.Tensor) -> list[torch.Tensor] | None:
        """The carry branch's maps at the head's strides, of the picture beside the frame (None without one)."""
        if self.carry is None:
            return None
        if images.shape[1] != RGB_CHANNELS + self.cfg.carry_channels:
            raise ValueError(f"a detector with a carry branch reads images of {RGB_CHANNELS + self.cfg.carry_channels} "
                             f"channels (the frame, then a picture of the events since it: data.carry_picture), "
                             f"got {images.shape[1]}")
        return self.picture_maps(images if self.cfg.carry_frame else images[:, RGB_CHANNELS:])

    def picture_maps(self, pictures: torch.Tensor) -> list[torch.Tensor]:
        """The carry branch's maps at the head's strides of ``(B, C, H, W)`` uint8 pictures of the
        events since the image (``carry_channels``), with ``carry_frame`` behind the frame's channels."""
        return self.carry(pictures)[1:]

    def split_carry_frame(self) -> bool:
        """For inference (the streaming detector's copy, its carry stem reading raw pixels, before packing):
        with ``carry_frame``, the carry stem split so that the frame's share is convolved once a frame
        (:meth:`carry_frame_part`, :meth:`picture_maps_from`). Whether it was split."""
        if self.carry is None or not self.cfg.carry_frame:
            return False
        self.carry.split_stem(RGB_CHANNELS)
        return True

    def carry_frame_part(self, frame: torch.Tensor) -> torch.Tensor:
        """After :meth:`split_carry_frame`: the carry stem's share of the camera frame ``(B, 3, H, W)`` uint8."""
        return self.carry.fixed_part(frame)

    def picture_maps_from(self, frame_part: torch.Tensor, pictures: torch.Tensor) -> list[torch.Tensor]:
        """:meth:`picture_maps` of the frame whose :meth:`carry_frame_part` is ``frame_part`` and the
        pictures ``(B, carry_channels, H, W)``."""
        return self.carry.forward_from(frame_part, pictures)[1:]

    @property
    def carry_widths(self) -> list[int]:
        """The channels the carry joins the fusion with at each head stride: its maps' and the carry
        attention's output (:meth:`attended`)."""
        if self.carry is None:
            return [0] * len(self.strides)
        extra = 0 if self.attend is None else self.attend.value_channels
        return [c + extra for c in self.carry.channels[1:]]

    def combine(self, image_maps: list[torch.Tensor] | None, event_maps: list[torch.Tensor],
                recency: list[torch.Tensor], age_us: torch.Tensor, carry_maps: list[torch.Tensor] | None = None,
                attend: bool = True, image_parts: list[torch.Tensor] | None = None):
        """The head's inputs from the event maps, the recency maps (``(B, num_recency, h, w)`` per
        stride, how recently each cell saw events at the query time) and, in a hybrid, the image
        maps (all strides of :class:`ImageBranch`) and the image's age ``(B,)`` in microseconds:
        the maps its towers read (:meth:`fuse_maps`), the query maps it reads after them
        (:meth:`query_maps`; None without ``late_query``) and the image maps its own image towers
        read (a hybrid with ``late_query``; else None). ``carry_maps`` (a carry branch's) join the
        fusion after the recency maps, with the carry attention's output behind them (``attend``
        false: they already hold it, as :attr:`carry_widths` counts). ``image_parts``: after
        :meth:`split_fusion`, the image's shares of the fusion (:meth:`fusion_image_part`), which
        the fusion then adds to the product of the rest."""
        if self.cfg.late_query:
            return (self.fuse_maps(image_maps, event_maps), self.query_maps(recency, age_us),
                    None if image_maps is None else image_maps[1:])
        if carry_maps is not None and self.attend is not None and attend:
            carry_maps = self.attended(image_maps, carry_maps)
        if image_parts is not None:
            parts = [list(p) for p in zip(event_maps, recency)] if carry_maps is None else \
                [list(p) for p in zip(event_maps, recency, carry_maps)]
            return self._fuse_split(image_parts, image_maps, parts, age_us), None, None
        joined = [torch.cat([m, r], dim=1) for m, r in zip(event_maps, recency)]
        if carry_maps is not None:
            joined = [torch.cat([j, c], dim=1) for j, c in zip(joined, carry_maps)]
        if image_maps is None:
            return joined, None, None
        return self._fuse(image_maps, joined, self._age_planes(age_us, image_maps[1:])), None, None

    def attended(self, image_maps: list[torch.Tensor], carry_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """The carry maps, each with the carry attention's output (:class:`CarryAttention`, at
        stride 16) behind it, brought to its stride: repeated to finer strides, averaged over
        2x2 cells per doubling to coarser ones."""
        at = self.strides.index(ATTEND_STRIDE)
        gathered = self.attend(carry_maps[at], image_maps[1 + at])
        out = []
        for stride, carry in zip(self.strides, carry_maps):
            g = gathered
            if stride > ATTEND_STRIDE:
                g = F.avg_pool2d(g, stride // ATTEND_STRIDE, ceil_mode=True)
            if g.shape[-2:] != carry.shape[-2:]:
                g = F.interpolate(g, size=carry.shape[-2:], mode="nearest")
            out.append(torch.cat([carry, g], dim=1))
        return out

    def split_fusion(self) -> bool:
        """For inference (the streaming detector's copy, its batch norms folded, before packing): each
        stride's fusion as two matrix products, the image map's share with the bias, computed once an
        image (:meth:`fusion_image_part`), and the rest's, an answer's, with the age plane's weight
        column as a vector (:meth:`combine` given ``image_parts``). Whether it was split (a hybrid
        without ``late_query``, whose fusion reads the query maps)."""
        if self.image is None or self.events is None or self.cfg.late_query:
            return False
        if self.fuse_parts is not None:
            return True
        parts = []
        for i, block in enumerate(self.fuse):
            conv = block[0]
            if not (type(conv) is nn.Conv2d and conv.bias is not None and isinstance(block[1], nn.Identity)
                    and isinstance(block[2], nn.SiLU)):
                raise ValueError("split_fusion needs the fusion's batch norms folded (fold_batch_norms), not packed yet")
            ci = self.image.channels[1 + i]
            weight = conv.weight.detach().reshape(conv.out_channels, conv.in_channels)
            image = nn.Linear(ci, conv.out_channels, device=weight.device, dtype=weight.dtype)
            rest = nn.Linear(conv.in_channels - ci - 1, conv.out_channels, bias=False, device=weight.device,
                             dtype=weight.dtype)
            with torch.no_grad():
                image.weight.copy_(weight[:, :ci])
                image.bias.copy_(conv.bias)
                rest.weight.copy_(weight[:, ci:-1])
            image.requires_grad_(False)
            rest.requires_grad_(False)
            parts.append(nn.ModuleDict({"image": image, "rest": rest}))
            parts[-1].register_buffer("age", weight[:, -1].clone())  # the age plane's column
        self.fuse_parts = nn.ModuleList(parts)
        return True

    def fusion_image_part(self, image_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """After :meth:`split_fusion`: per head stride, the image map's share of the fusion with its
        bias, ``(B h w, C)`` rows, cells row-major (channels last)."""
        return [part["image"](flat_map(image_map)) for part, image_map in zip(self.fuse_parts, image_maps[1:])]

    def _fuse_split(self, image_parts: list[torch.Tensor], image_maps: list[torch.Tensor],
                    joined: list[torch.Tensor], age_us: torch.Tensor) -> list[torch.Tensor]:
        """:meth:`_fuse` from the image's shares (:meth:`fusion_image_part`): the rest's product added to
        them, the age's column times the age, the SiLU; each map channels last."""
        out = []
        for part, image_part, image_map, maps in zip(self.fuse_parts, image_parts, image_maps[1:], joined):
            b, _, h, w = image_map.shape
            if maps[0].shape[-2:] != (h, w):  # ceil vs floor on odd sizes, as fuse_at
                maps = [F.interpolate(m, size=(h, w), mode="nearest") for m in maps]
            rows = torch.cat([m.permute(0, 2, 3, 1) for m in maps], dim=3).reshape(b * h * w, -1)
            y = torch.addmm(image_part, rows, part["rest"].weight.T)
            y.view(b, h * w, -1).add_((age_us.to(y.dtype) / self.cfg.time_scale_us)[:, None, None] * part.age)
            F.silu(y, inplace=True)
            out.append(y.view(b, h, w, -1).permute(0, 3, 1, 2))
        return out

    def fuse_maps(self, image_maps: list[torch.Tensor] | None, event_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """With ``late_query``, the head's input: the event maps, fused with the image maps in a
        hybrid. Nothing here depends on the query time."""
        return event_maps if image_maps is None else self._fuse(image_maps, event_maps, None)

    def query_maps(self, recency: list[torch.Tensor], age_us: torch.Tensor) -> list[torch.Tensor]:
        """With ``late_query``, what the head reads after its towers: the recency maps and, in a
        hybrid, the image's age as a constant plane (in ``time_scale_us``)."""
        if self.image is None:
            return list(recency)
        return [torch.cat([r, a], dim=1) for r, a in zip(recency, self._age_planes(age_us, recency))]

    def _age_planes(self, age_us: torch.Tensor, like: list[torch.Tensor]) -> list[torch.Tensor]:
        """The image's age ``(B,)`` as a ``(B, 1, h, w)`` plane of each map's size and dtype."""
        return [(age_us.to(m.dtype) / self.cfg.time_scale_us)[:, None, None, None].expand(-1, 1, *m.shape[-2:])
                for m in like]

    def _fuse(self, image_maps: list[torch.Tensor], event_maps: list[torch.Tensor],
              age_planes: list[torch.Tensor] | None) -> list[torch.Tensor]:
        """The fusion's 1x1 convolutions over ``[image map, event map(, age plane)]`` per stride."""
        return [self.fuse_at(i, image_map, event_map, None if age_planes is None else age_planes[i])
                for i, (image_map, event_map) in enumerate(zip(image_maps[1:], event_maps))]

    def fuse_at(self, i: int, image_map: torch.Tensor, event_map: torch.Tensor,
                age_plane: torch.Tensor | None = None) -> torch.Tensor:
        """The fusion of head stride ``i``: its 1x1 convolution over ``[image map, event map(, age plane)]``."""
        if event_map.shape[-2:] != image_map.shape[-2:]:  # ceil vs floor on odd sizes
            event_map = F.interpolate(event_map, size=image_map.shape[-2:], mode="nearest")
        parts = [image_map, event_map] if age_plane is None else [image_map, event_map, age_plane]
        return self.fuse[i](torch.cat(parts, dim=1))

    def fuse_rows(self, i: int, image_rows: torch.Tensor, event_rows: torch.Tensor) -> torch.Tensor:
        """:meth:`fuse_at` at some cells: rows ``(n, C)`` of the image and event maps (no age plane)."""
        return block_rows(self.fuse[i], torch.cat([image_rows, event_rows], dim=1))

    def tower_cache(self) -> TowerCache:
        """The head over a stream of event maps, recomputed where they change (``late_query``)."""
        if self.image is None:
            return TowerCache(self.head)
        return TowerCache(self.head, fuse_map=self.fuse_at, fuse_rows=self.fuse_rows)

    def event_node_features(self, batch: Batch) -> torch.Tensor:
        """``(N, C)`` features of the batch's event nodes after the event branch's first stage."""
        if self.events is None:
            raise ValueError("this detector has no event branch (use_events false)")
        sampler = self.node_sampler(self.node_maps(self.frame_maps(batch.images))) if self.image is not None else None
        x, _, _ = self.events.event_nodes(batch.events, batch.batch_index, sampler, batch.edge_index)
        return x

    def blank_sampler(self, xy: torch.Tensor, node_batch: torch.Tensor, level: int) -> torch.Tensor:
        """Zero image features at the nodes (``forward(image=False)``)."""
        return xy.new_zeros(len(xy), self.cfg.fuse_channels)

    def zero_image_weights(self) -> None:
        """Zero every weight through which an image feature reaches the output: the columns of the
        event branch's level inputs that read the image features at the nodes, those of the
        fusion's 1x1 convolutions that read the image maps, (``late_query``) the stems of the
        head's image towers, (``carry_frame``) the carry stem's frame channels and (``carry_attend``) the carry
        attention's key and value projections. The hybrid then answers exactly what
        ``forward(image=False)`` answers, whatever its image, until training moves those weights:
        the start of ``trainer.events_first``, in which they stay zero because every image
        feature is zero (no gradient reaches them, and weight decay keeps a zero at zero)."""
        if self.image is None or self.events is None:
            raise ValueError("only a hybrid (use_events and use_image) has weights that read the image")
        with torch.no_grad():
            for level, stage in enumerate(self.events.stages):
                k = self.events.image_channels[level]
                if not k:
                    continue
                first = stage[0]
                if not isinstance(first.skip, nn.Linear):  # an identity skip would pass the image on
                    raise ValueError(f"event level {level}: its input is as wide as its output, so its skip "
                                     f"passes the image features on unweighted")
                first.conv.weight[-k:].zero_()  # (in, out): the last k inputs are the image's
                first.skip.weight[:, -k:].zero_()  # (out, in)
            for fuse, c in zip(self.fuse, self.image.channels[1:]):
                fuse[0].weight[:, :c].zero_()  # the fusion reads [image map, event map(, age)]
            if self.carry is not None and self.cfg.carry_frame:
                self.carry.stem[0][0].weight[:, :RGB_CHANNELS].zero_()  # the carry stem's frame channels
            if self.attend is not None:  # the carry attention's keys and values read the image map
                self.attend.key.weight.zero_()
                self.attend.value.weight.zero_()
            if self.head.has_image:  # the head's image towers: their stems
                for stem in self.head.image_stems:
                    stem[0].weight.zero_()

    def zero_event_weights(self) -> None:
        """Zero the fusion's weights that read the event maps and the recency maps, the only way
        from the events to the output of a hybrid whose query maps join at the fusion
        (``late_query`` false) and that has no event head. It then answers exactly what
        ``forward(events=False)`` answers, whatever its events, until training moves them: the
        start of ``trainer.image_first``, in which they stay zero because every event feature is
        zero (no gradient reaches them, and weight decay keeps a zero at zero)."""
        if self.image is None or self.events is None:
            raise ValueError("only a hybrid (use_events and use_image) has weights that read the events")
        if self.cfg.late_query or self.event_head is not None:
            raise ValueError("trainer.image_first needs model.late_query=false and model.event_head_weight=0: "
                             "there the fusion is the only way from the events to the output")
        with torch.no_grad():
            for fuse, c, e, k in zip(self.fuse, self.image.channels[1:], self.events.out_channels, self.carry_widths):
                fuse[0].weight[:, c:c + e + self.num_recency + k].zero_()  # [image, event, recency, carry, age]

    def zero_graph_weights(self) -> None:
        """Zero the fusion's weights that read the event branch's maps, the only way from the event
        graph to the output of a hybrid without an event head (the recency maps and a carry branch
        read the events without it). It then answers exactly what ``forward(graph=False)`` answers,
        whatever its graph, until training moves them: the start of ``trainer.dense_first``, in
        which they stay zero because every event map is zero (no gradient reaches them, and weight
        decay keeps a zero at zero)."""
        if self.image is None or self.events is None:
            raise ValueError("only a hybrid (use_events and use_image) has weights that read the event graph")
        if self.event_head is not None:
            raise ValueError("trainer.dense_first needs model.event_head_weight=0: an event head reads the event "
                             "branch's maps beside the fusion")
        with torch.no_grad():
            for fuse, c, e in zip(self.fuse, self.image.channels[1:], self.events.out_channels):
                fuse[0].weight[:, c:c + e].zero_()  # the fusion reads [image, event, ...]

    def node_maps(self, image_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """The image maps projected to the channels joined at the event nodes, one per level."""
        return [proj(m) for proj, m in zip(self.to_nodes, image_maps)]

    def node_sampler(self, node_maps: list[torch.Tensor]):
        """Image features at event nodes: level 0 from the stride-4 map, pooled levels from theirs."""
        strides = self.image.strides
        flats: dict[int, np.ndarray] = {}  # each map laid out channels last once, for the compiled samples

        def sampler(xy: torch.Tensor, node_batch: torch.Tensor, level: int) -> torch.Tensor:
            feature = node_maps[level]
            if not compiled_inference(feature):
                return sample_at(feature, xy, node_batch, strides[level])
            if level not in flats:
                flats[level] = channels_last(feature)
            return bilinear_at(flats[level], *feature.shape[-2:], xy, node_batch, strides[level])

        return sampler

    def forward(self, batch: Batch, *, conf_threshold: float | None = None, nms_threshold: float | None = None,
                image: bool = True, events: bool = True, graph: bool = True):
        """Losses in training, detections in evaluation. ``image=False`` (a hybrid): the image
        branch is not run and every image feature the model reads is zero, at the nodes and in
        the fusion (the ``trainer.events_first`` phase; with :meth:`zero_image_weights` this is
        what the hybrid computes with any image). ``events=False`` (a hybrid): the event branch is
        not run and its maps and the recency maps are zero (the ``trainer.image_first`` phase; with
        :meth:`zero_event_weights`, what the hybrid computes with any events). ``graph=False`` (a
        hybrid): the event branch is not run and its maps are zero, while the recency maps and a
        carry branch read the events as always, so the batch needs no graph (the
        ``trainer.dense_first`` phase; with :meth:`zero_graph_weights`, what the hybrid computes
        with any graph). Detections need ``conf_threshold`` and ``nms_threshold`` (``eval.*`` in ``conf/``)."""
        if not self.training and (conf_threshold is None or nms_threshold is None):
            raise TypeError("Detector in evaluation mode needs conf_threshold= and nms_threshold= (eval.* in conf/)")
        raw, shapes, event_inputs = self.outputs(batch, image=image, events=events, graph=graph)
        if self.training:
            out = yolox_losses(raw, shapes, self.strides, batch.boxes, batch.labels, normaliser=self.loss_normaliser)
            if self.event_head is not None and event_inputs is not None:
                event_raw, event_shapes = self.event_head(*event_inputs)
                events = yolox_losses(event_raw, event_shapes, self.strides, batch.boxes, batch.labels,
                                      normaliser=self.loss_normaliser)
                out["loss"] = out["loss"] + self.cfg.event_head_weight * events["loss"]
                out["event_head_loss"] = events["loss"].detach()
            return out
        return self.detections(raw, shapes, conf_threshold=conf_threshold, nms_threshold=nms_threshold)

    def outputs(self, batch: Batch, *, image: bool = True, events: bool = True, graph: bool = True
                ) -> tuple[torch.Tensor, list[tuple[int, int]], tuple]:
        """The head's raw output ``(B, A, 5 + classes)``, its map shapes, and the event head's inputs."""
        maps, query, image_inputs, event_inputs = self._features(batch, image=image, events=events, graph=graph)
        if self.training:
            raw, shapes = self.head(maps, query, image_inputs)
        else:
            raw, shapes = self.answer_outputs(maps, query, image_inputs, event_inputs)
        return raw, shapes, event_inputs

    def answer_outputs(self, maps: list[torch.Tensor], query, image_inputs, event_inputs
                       ) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        """What an answer decodes: the fused head's raw output ``(B, A, 5 + C)`` and map shapes,
        with ``event_answers`` the event head's anchors behind them (its shapes after the fused
        head's; :meth:`answer_strides` gives the stride of each)."""
        raw, shapes = self.head(maps, query, image_inputs)
        if self.cfg.event_answers and event_inputs is not None:
            event_raw, event_shapes = self.event_head(*event_inputs)
            raw, shapes = torch.cat([raw, event_raw], dim=1), shapes + event_shapes
        return raw, shapes

    def answer_strides(self, shapes: list[tuple[int, int]]) -> list[int]:
        """The stride of each map of an answer's ``shapes`` (:meth:`answer_outputs`)."""
        return list(self.strides) * (len(shapes) // len(self.strides))

    def detections(self, raw: torch.Tensor, shapes: list[tuple[int, int]], *, conf_threshold: float,
                   nms_threshold: float) -> list[dict]:
        """The boxes of :meth:`outputs` of ``conf_threshold`` or more, after NMS at ``nms_threshold``."""
        return postprocess(raw, shapes, self.answer_strides(shapes), conf_threshold=conf_threshold,
                           nms_threshold=nms_threshold,
                           image_size=(self.cfg.height, self.cfg.width))
