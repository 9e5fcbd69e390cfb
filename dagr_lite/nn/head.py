"""A YOLOX-style anchor-free decoupled head: SimOTA assignment, losses, decoding and NMS.

Every cell of a stride-``s`` map is an anchor at the cell centre ``((gx + 0.5) s, (gy + 0.5) s)``
in pixels (the same ``s`` in x and y: cells are ``s x s`` pixels). A prediction ``(tx, ty, tw,
th)`` decodes to the box centre ``anchor + (tx, ty) s`` and size ``exp(tw, th) s``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dagr_lite.nn.blocks import conv_bn_act


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU of xyxy boxes.  ``(M, 4), (N, 4) -> (M, N)``."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])  # (M, N, 2)
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])  # (M, N, 2)
    inter = (rb - lt).clamp(min=0).prod(-1)  # (M, N)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter).clamp(min=1e-9)


def aligned_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of matching rows of xyxy boxes.  ``(N, 4), (N, 4) -> (N,)``."""
    lt, rb = torch.maximum(a[:, :2], b[:, :2]), torch.minimum(a[:, 2:], b[:, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    union = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1) + (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1) - inter
    return inter / union.clamp(min=1e-9)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float, labels: torch.Tensor | None = None
        ) -> torch.Tensor:
    """Greedy non-maximum suppression; class-aware when ``labels`` are given.

    Returns the kept indices, by decreasing score.  ``boxes (D, 4) xyxy, scores (D,) -> (K,)``.
    """
    if len(boxes) == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    if boxes.device.type == "cpu":  # numpy's operations on a few boxes cost a few microseconds each, torch's tens
        return torch.from_numpy(_nms_numpy(boxes.detach().numpy(), scores.detach().numpy(), iou_threshold,
                                           None if labels is None else labels.detach().numpy()))
    order = torch.argsort(scores, descending=True, stable=True)
    boxes = boxes[order]
    iou = box_iou(boxes, boxes)  # (D, D)
    if labels is not None:
        labels = labels[order]
        iou = iou * (labels[:, None] == labels[None, :])
    overlap = (iou > iou_threshold).triu(diagonal=1).cpu().numpy()  # i suppresses later j; the loop runs on CPU
    keep = np.ones(len(boxes), dtype=bool)
    for i in range(len(boxes)):  # numpy rows: a few microseconds each, where tensor indexing costs tens
        if keep[i]:
            keep &= ~overlap[i]
    return order[torch.from_numpy(keep).to(order.device)]


def _nms_numpy(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, labels: np.ndarray | None) -> np.ndarray:
    """:func:`nms` on numpy arrays: the same operations as :func:`box_iou` in the same order, so the
    same overlaps to the bit and the same boxes kept."""
    order = np.argsort(-scores, kind="stable")  # by decreasing score, ties in index order
    boxes = boxes[order]
    lt = np.maximum(boxes[:, None, :2], boxes[None, :, :2])
    rb = np.minimum(boxes[:, None, 2:], boxes[None, :, 2:])
    wh = np.maximum(rb - lt, 0)
    inter = wh[..., 0] * wh[..., 1]
    size = np.maximum(boxes[:, 2:] - boxes[:, :2], 0)
    area = size[:, 0] * size[:, 1]
    iou = inter / np.maximum(area[:, None] + area[None, :] - inter, boxes.dtype.type(1e-9))
    overlap = np.triu(iou > iou_threshold, 1)
    if labels is not None:
        labels = labels[order]
        overlap &= labels[:, None] == labels[None, :]
    keep = np.ones(len(boxes), dtype=bool)
    for i in range(len(boxes)):
        if keep[i]:
            keep &= ~overlap[i]
    return order[keep].astype(np.int64)


_ANCHORS: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}  # per (shapes, strides, device), at most 32


def anchors_of(shapes: list[tuple[int, int]], strides: list[int], device) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor centres ``(A, 2)`` in pixels and their strides ``(A,)``, maps flattened row-major.

    Made once per shapes, strides and device and shared: read them, never change them in place."""
    key = (tuple((int(h), int(w)) for h, w in shapes), tuple(int(s) for s in strides), str(torch.device(device)))
    kept = _ANCHORS.get(key)
    if kept is not None:
        return kept
    centres, stride_of = [], []
    with torch.inference_mode(False):  # ordinary tensors, which training's autograd may also read
        for (h, w), s in zip(shapes, strides):
            gy, gx = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
            centres.append(torch.stack([gx.flatten(), gy.flatten()], 1).float().add(0.5).mul(s))  # (h w, 2)
            stride_of.append(torch.full((h * w,), float(s), device=device))
        kept = torch.cat(centres), torch.cat(stride_of)
    if len(_ANCHORS) >= 32:
        _ANCHORS.clear()
    _ANCHORS[key] = kept
    return kept


def decode_boxes(raw: torch.Tensor, centres: torch.Tensor, strides: torch.Tensor) -> torch.Tensor:
    """``(..., A, 4)`` raw ``(tx, ty, tw, th)`` -> xyxy pixels."""
    xy = centres + raw[..., :2] * strides[:, None]
    wh = torch.exp(raw[..., 2:].clamp(max=10.0)) * strides[:, None]
    return torch.cat([xy - wh / 2, xy + wh / 2], dim=-1)


@dataclass
class Assignment:
    """SimOTA result for one image: foreground anchors, their GT and the IoU of their prediction."""

    fg: torch.Tensor  # (A,) bool
    gt_index: torch.Tensor  # (F,) matched GT of each foreground anchor, in anchor order
    iou: torch.Tensor  # (F,)


@torch.no_grad()
def simota_assign(pred_boxes: torch.Tensor, obj_logits: torch.Tensor, cls_logits: torch.Tensor,
                  gt_boxes: torch.Tensor, gt_labels: torch.Tensor, centres: torch.Tensor, strides: torch.Tensor,
                  *, center_radius: float = 2.5, iou_weight: float = 3.0, top_candidates: int = 10) -> Assignment:
    """SimOTA (YOLOX): centre prior, cost = class + ``iou_weight`` * (-log IoU), dynamic k per GT.

    Shapes:
        pred_boxes ``(A, 4)``, obj_logits ``(A,)``, cls_logits ``(A, C)``, gt_boxes ``(M, 4)``,
        gt_labels ``(M,)``, centres ``(A, 2)``, strides ``(A,)``.
    """
    num_anchors, device = len(centres), centres.device
    empty = Assignment(torch.zeros(num_anchors, dtype=torch.bool, device=device),
                       torch.zeros(0, dtype=torch.int64, device=device), torch.zeros(0, device=device))
    if len(gt_boxes) == 0:
        return empty
    # Centre prior: anchor centre inside the GT box, or within center_radius strides of its centre.
    cx, cy = centres[:, 0], centres[:, 1]  # (A,)
    in_box = ((cx[None] > gt_boxes[:, None, 0]) & (cx[None] < gt_boxes[:, None, 2])
              & (cy[None] > gt_boxes[:, None, 1]) & (cy[None] < gt_boxes[:, None, 3]))  # (M, A)
    gt_centre = (gt_boxes[:, :2] + gt_boxes[:, 2:]) / 2  # (M, 2)
    radius = center_radius * strides[None]  # (1, A)
    in_centre = ((cx[None] - gt_centre[:, None, 0]).abs() < radius) & ((cy[None] - gt_centre[:, None, 1]).abs() < radius)
    candidate = (in_box | in_centre).any(0)  # (A,)
    if not candidate.any():
        return empty
    both = (in_box & in_centre)[:, candidate]  # (M, A_c)
    iou = box_iou(gt_boxes, pred_boxes[candidate].float())  # (M, A_c)
    scores = (torch.sigmoid(cls_logits[candidate].float()) * torch.sigmoid(obj_logits[candidate].float())[:, None]).sqrt()
    target = F.one_hot(gt_labels, cls_logits.shape[1]).float()  # (M, C)
    cls_cost = F.binary_cross_entropy(scores[None].expand(len(gt_boxes), -1, -1).clamp(1e-6, 1 - 1e-6),
                                      target[:, None].expand(-1, scores.shape[0], -1), reduction="none").sum(-1)
    cost = cls_cost + iou_weight * -torch.log(iou + 1e-8) + 1e5 * (~both)  # (M, A_c)
    # Dynamic k: each GT takes as many anchors as the sum of its top IoUs (at least one).
    k = torch.clamp(torch.topk(iou, min(top_candidates, iou.shape[1]), dim=1).values.sum(1).int(), min=1)
    matching = torch.zeros_like(cost, dtype=torch.bool)
    for g in range(len(gt_boxes)):
        matching[g, torch.topk(cost[g], int(k[g]), largest=False).indices] = True
    shared = matching.sum(0) > 1  # an anchor claimed by several GTs keeps the cheapest
    if shared.any():
        cheapest = cost[:, shared].argmin(0)
        matching[:, shared] = False
        matching[cheapest, torch.nonzero(shared).flatten()] = True
    fg_c = matching.any(0)  # (A_c,)
    fg = torch.zeros(num_anchors, dtype=torch.bool, device=device)
    fg[torch.nonzero(candidate).flatten()[fg_c]] = True
    gt_index = matching[:, fg_c].int().argmax(0)
    return Assignment(fg, gt_index, iou[gt_index, torch.nonzero(fg_c).flatten()])


class YOLOXHead(nn.Module):
    """Decoupled head, one set of branches per stride: stem, then class / box + objectness.

    Args:
        in_channels: channels of each input map; hidden: branch width; num_classes: classes.
        strides: the stride of each input map, in pixels.
        late_channels: > 0: each branch's tower output is joined with ``late_channels`` query
            maps and mixed by a 1x1 convolution (``late``) before the predictions. What the
            query maps carry (the query time) then never reaches the 3x3 towers, whose output
            changes only where the input maps change.
        image_channels: with ``late_channels``, channels of each map of a second input, the
            image's, which gets towers of its own; their output is scaled per channel by
            ``2 sigmoid(w a + b)`` of the image's age ``a`` (the last query map, a constant
            plane; 1 at initialisation) and joins the late layers. The head can so turn down
            what a stale image says, while the image's towers run once per image.

    Shapes:
        maps: list of ``(B, C_s, H_s, W_s)`` (query: list of ``(B, late_channels, H_s, W_s)``,
        image: list of ``(B, image_channels[s], H_s, W_s)``) -> raw ``(B, A, 5 + num_classes)``
        with ``A = sum H_s W_s``: box ``(tx, ty, tw, th)``, objectness logit, class logits.
    """

    def __init__(self, in_channels: list[int], strides: list[int], *, hidden: int, num_classes: int,
                 late_channels: int = 0, image_channels: list[int] | None = None):
        super().__init__()
        self.strides, self.num_classes = list(strides), num_classes

        def branch():
            return nn.Sequential(conv_bn_act(hidden, hidden), conv_bn_act(hidden, hidden))

        self.stems = nn.ModuleList(conv_bn_act(c, hidden, k=1) for c in in_channels)
        self.cls_branches = nn.ModuleList(branch() for _ in strides)
        self.reg_branches = nn.ModuleList(branch() for _ in strides)
        if image_channels is not None and not late_channels:
            raise ValueError("the head's image towers are gated by the image's age, a query map: "
                             "image_channels needs late_channels > 0")
        self.late_channels, self.has_image = late_channels, image_channels is not None
        if self.has_image:
            self.image_stems = nn.ModuleList(conv_bn_act(c, hidden, k=1) for c in image_channels)
            self.image_cls_branches = nn.ModuleList(branch() for _ in strides)
            self.image_reg_branches = nn.ModuleList(branch() for _ in strides)
            # Per stride, the age's gates of the class and the box image towers' channels.
            self.gates = nn.ModuleList(nn.Conv2d(1, 2 * hidden, 1) for _ in strides)
            for gate in self.gates:
                nn.init.zeros_(gate.weight)
                nn.init.zeros_(gate.bias)
        if late_channels:
            late_in = hidden * (2 if self.has_image else 1) + late_channels
            self.cls_late = nn.ModuleList(conv_bn_act(late_in, hidden, k=1) for _ in strides)
            self.reg_late = nn.ModuleList(conv_bn_act(late_in, hidden, k=1) for _ in strides)
        self.cls_preds = nn.ModuleList(nn.Conv2d(hidden, num_classes, 1) for _ in strides)
        self.reg_preds = nn.ModuleList(nn.Conv2d(hidden, 4, 1) for _ in strides)
        self.obj_preds = nn.ModuleList(nn.Conv2d(hidden, 1, 1) for _ in strides)
        prior = -4.6  # sigmoid(-4.6) ~ 0.01: rare objects at the start
        for layer in (*self.cls_preds, *self.obj_preds):
            nn.init.constant_(layer.bias, prior)
        # Per stride, after merge_branches: the two towers as one (the class tower's channels first) and the
        # predictions as one 1x1 convolution; None: the branches apart.
        self.merged: nn.ModuleList | None = None

    def forward(self, maps: list[torch.Tensor], query: list[torch.Tensor] | None = None,
                image: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        if (query is not None) != bool(self.late_channels) or (image is not None) != self.has_image:
            raise ValueError(f"this head reads {self.late_channels} query channels after its towers and "
                             f"{'an' if self.has_image else 'no'} image input, got "
                             f"{'no' if query is None else 'some'} query maps and {'no' if image is None else 'an'} image")
        if self.merged is not None:
            return self._merged_forward(maps)
        towers = [self.towers(i, x) for i, x in enumerate(maps)]
        image_towers = None if image is None else [self.image_towers(i, x) for i, x in enumerate(image)]
        return self.predict(towers, query, image_towers)

    def merge_branches(self) -> "YOLOXHead":
        """For inference, in place: at each stride the class and box towers as one tower of twice the
        width (the first layer one convolution to ``2 hidden`` channels, the second a convolution of two
        groups, one per tower) and the box, objectness and class predictions as one 1x1 convolution over
        both towers' channels (each output's weights zero over the other tower's). Half the convolutions
        an answer runs, of the same function up to the order of the sums. Needs batch norms folded
        into the convolutions (:func:`~dagr_lite.nn.blocks.fold_batch_norms`); a head with query maps
        after its towers keeps its branches."""
        if self.late_channels:
            raise ValueError("a head whose query maps join after its towers keeps its branches apart")
        if self.merged is not None:
            return self
        merged = nn.ModuleList()
        for cls_branch, reg_branch, cls_pred, reg_pred, obj_pred in zip(
                self.cls_branches, self.reg_branches, self.cls_preds, self.reg_preds, self.obj_preds):
            layers = []
            for depth, (c, r) in enumerate(zip(cls_branch, reg_branch)):
                cc, rc = c[0], r[0]
                if not (isinstance(c[1], nn.Identity) and isinstance(r[1], nn.Identity) and cc.bias is not None
                        and isinstance(c[2], nn.SiLU) and isinstance(r[2], nn.SiLU) and cc.groups == rc.groups == 1):
                    raise ValueError("merge_branches needs each tower block one convolution with a bias and a SiLU: "
                                     "fold the batch norms first (nn.blocks.fold_batch_norms)")
                groups = 1 if depth == 0 else 2  # the first layer reads the stem; the second each its tower's half
                conv = nn.Conv2d(cc.in_channels * (1 if depth == 0 else 2), 2 * cc.out_channels, cc.kernel_size,
                                 cc.stride, cc.padding, groups=groups, bias=True,
                                 device=cc.weight.device, dtype=cc.weight.dtype)
                with torch.no_grad():
                    conv.weight.copy_(torch.cat([cc.weight, rc.weight]))
                    conv.bias.copy_(torch.cat([cc.bias, rc.bias]))
                layers += [conv, nn.SiLU()]
            hidden = cls_pred.in_channels
            outputs = [(reg_pred, hidden), (obj_pred, hidden), (cls_pred, 0)]  # the raw output's order; where each reads
            pred = nn.Conv2d(2 * hidden, sum(layer.out_channels for layer, _ in outputs), 1,
                             device=cls_pred.weight.device, dtype=cls_pred.weight.dtype)
            with torch.no_grad():
                pred.weight.zero_()
                row = 0
                for layer, at in outputs:
                    pred.weight[row:row + layer.out_channels, at:at + hidden] = layer.weight
                    pred.bias[row:row + layer.out_channels] = layer.bias
                    row += layer.out_channels
            merged.append(nn.Sequential(nn.Sequential(*layers), pred))
        self.merged = merged
        return self

    def _merged_forward(self, maps: list[torch.Tensor]) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        return raw_output([self.merged[i](self.stems[i](x)) for i, x in enumerate(maps)])

    def towers(self, i: int, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The class and box towers' outputs ``(B, hidden, H_s, W_s)`` at stride ``i`` for input ``x``."""
        x = self.stems[i](x)
        return self.cls_branches[i](x), self.reg_branches[i](x)

    def image_towers(self, i: int, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The image towers' outputs ``(B, hidden, H_s, W_s)`` at stride ``i`` for the image map ``x``."""
        x = self.image_stems[i](x)
        return self.image_cls_branches[i](x), self.image_reg_branches[i](x)

    def predict(self, towers: list[tuple[torch.Tensor, torch.Tensor]], query: list[torch.Tensor] | None = None,
                image_towers: list[tuple[torch.Tensor, torch.Tensor]] | None = None
                ) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        """The raw output from the towers' outputs of every stride (and the query maps and image towers)."""
        outputs = []
        for i, (cls_feat, reg_feat) in enumerate(towers):
            if self.late_channels:
                cls_parts, reg_parts = [cls_feat], [reg_feat]
                if image_towers is not None:
                    cls_gate, reg_gate = (2 * torch.sigmoid(self.gates[i](query[i][:, -1:]))).chunk(2, dim=1)
                    cls_parts.append(image_towers[i][0] * cls_gate)
                    reg_parts.append(image_towers[i][1] * reg_gate)
                cls_feat = self.cls_late[i](torch.cat([*cls_parts, query[i]], dim=1))
                reg_feat = self.reg_late[i](torch.cat([*reg_parts, query[i]], dim=1))
            outputs.append(torch.cat([self.reg_preds[i](reg_feat), self.obj_preds[i](reg_feat),
                                      self.cls_preds[i](cls_feat)], 1))
        return raw_output(outputs)


def raw_output(maps: list[torch.Tensor]) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    """The raw output ``(B, A, 5 + C)`` of per-stride prediction maps ``(B, 5 + C, H_s, W_s)``, each
    flattened row-major, and the maps' shapes."""
    return torch.cat([m.flatten(2).transpose(1, 2) for m in maps], 1), [tuple(m.shape[-2:]) for m in maps]


def yolox_losses(raw: torch.Tensor, shapes: list[tuple[int, int]], strides: list[int], gt_boxes: list[torch.Tensor],
                 gt_labels: list[torch.Tensor], *, iou_weight: float = 5.0,
                 normaliser: Callable[[float], float] | None = None) -> dict:
    """Training losses: IoU (1 - IoU^2) on foreground boxes, BCE objectness on all anchors and BCE class
    (target = IoU) on foreground anchors, each normalised by the foreground count (at least 1).

    ``normaliser``: maps this batch's foreground count to the normaliser to use instead (several
    processes normalise by their global batch's count). ``loss = iou_weight * iou_loss + obj_loss
    + cls_loss``; also returns the parts (detached) and ``num_fg``.
    """
    # Assignment and losses in float32 even inside a mixed-precision step (BCE is not autocast-safe).
    with torch.autocast(raw.device.type, enabled=False):
        return _yolox_losses(raw.float(), shapes, strides, gt_boxes, gt_labels, iou_weight=iou_weight,
                             normaliser=normaliser)


def _yolox_losses(raw, shapes, strides, gt_boxes, gt_labels, *, iou_weight, normaliser) -> dict:
    batch, device = raw.shape[0], raw.device
    centres, stride_of = anchors_of(shapes, strides, device)
    boxes = decode_boxes(raw[..., :4], centres, stride_of)  # (B, A, 4)
    obj_logits, cls_logits = raw[..., 4], raw[..., 5:]
    obj_targets = torch.zeros_like(obj_logits)
    fg_boxes, fg_targets, cls_fg, cls_targets = [], [], [], []
    for b in range(batch):
        a = simota_assign(boxes[b].detach(), obj_logits[b].detach(), cls_logits[b].detach(), gt_boxes[b].float(),
                          gt_labels[b], centres, stride_of)
        obj_targets[b, a.fg] = 1.0
        if a.fg.any():
            fg_boxes.append(boxes[b, a.fg])
            fg_targets.append(gt_boxes[b].float()[a.gt_index])
            cls_fg.append(cls_logits[b, a.fg])
            cls_targets.append(F.one_hot(gt_labels[b][a.gt_index], cls_logits.shape[-1]).float() * a.iou[:, None])
    num_fg = sum(len(t) for t in fg_targets)
    norm = max(num_fg, 1) if normaliser is None else normaliser(num_fg)
    obj_loss = F.binary_cross_entropy_with_logits(obj_logits, obj_targets, reduction="sum") / norm
    if num_fg:
        iou = aligned_iou(torch.cat(fg_boxes), torch.cat(fg_targets))
        iou_loss = (1 - iou ** 2).sum() / norm
        cls_loss = F.binary_cross_entropy_with_logits(torch.cat(cls_fg), torch.cat(cls_targets), reduction="sum") / norm
    else:
        iou_loss = cls_loss = raw.sum() * 0.0
    loss = iou_weight * iou_loss + obj_loss + cls_loss
    return {"loss": loss, "iou_loss": iou_loss.detach(), "obj_loss": obj_loss.detach(), "cls_loss": cls_loss.detach(),
            "num_fg": torch.tensor(float(num_fg), device=device)}


def postprocess(raw: torch.Tensor, shapes: list[tuple[int, int]], strides: list[int], *, conf_threshold: float,
                nms_threshold: float, max_detections: int = 100, pre_nms: int = 1000,
                image_size: tuple[int, int] | None = None) -> list[dict]:
    """Decoded, class-aware NMS-filtered detections per image: ``boxes (D, 4)``, ``scores (D,)``, ``labels (D,)``.

    On a CPU in numpy's operations (:func:`_postprocess_numpy`: an answer's few thousand anchors cost
    a few microseconds an operation there, tens in torch's), elsewhere in torch's; the two agree to
    the rounding of their exponentials (``tests/nn/test_head.py``)."""
    centres, stride_of = anchors_of(shapes, strides, raw.device)
    raw = raw if raw.dtype == torch.float64 else raw.float()  # float64 stays (exactness tests)
    if raw.device.type == "cpu":
        return _postprocess_numpy(raw.detach().numpy(), centres.numpy(), stride_of.numpy(), conf_threshold,
                                  nms_threshold, max_detections, pre_nms, image_size)
    return _postprocess_tensors(raw, centres, stride_of, conf_threshold, nms_threshold, max_detections, pre_nms,
                                image_size)


def _postprocess_tensors(raw, centres, stride_of, conf_threshold, nms_threshold, max_detections, pre_nms, image_size):
    """:func:`postprocess` in torch's operations, on any device."""
    obj = torch.sigmoid(raw[..., 4])
    cls_prob = torch.sigmoid(raw[..., 5:])
    results = []
    for b in range(raw.shape[0]):
        scores, labels = (cls_prob[b] * obj[b, :, None]).max(-1)  # (A,)
        keep = torch.nonzero(scores >= conf_threshold).squeeze(1)  # only these anchors' boxes are decoded
        bx = decode_boxes(raw[b, keep, :4], centres[keep], stride_of[keep])
        if image_size is not None:
            height, width = image_size
            bx = torch.stack([bx[:, 0].clamp(0, width), bx[:, 1].clamp(0, height),
                              bx[:, 2].clamp(0, width), bx[:, 3].clamp(0, height)], -1)
        sc, lb = scores[keep], labels[keep]
        if len(sc) > pre_nms:
            top = torch.topk(sc, pre_nms).indices
            bx, sc, lb = bx[top], sc[top], lb[top]
        kept = nms(bx, sc, nms_threshold, lb)[:max_detections]
        results.append({"boxes": bx[kept], "scores": sc[kept], "labels": lb[kept]})
    return results


def _postprocess_numpy(raw, centres, stride_of, conf_threshold, nms_threshold, max_detections, pre_nms, image_size):
    """:func:`postprocess` of a CPU tensor's ``raw`` numpy array: the operations of
    :func:`_postprocess_tensors` in the same dtypes and order (the candidates above ``pre_nms`` by a
    stable sort instead of ``topk``), results as tensors."""
    def sigmoid(v):
        return 1 / (1 + np.exp(-v))

    obj = sigmoid(raw[..., 4])
    cls_prob = sigmoid(raw[..., 5:])
    results = []
    for b in range(raw.shape[0]):
        products = cls_prob[b] * obj[b, :, None]  # (A, C)
        labels = products.argmax(1)
        scores = np.take_along_axis(products, labels[:, None], 1)[:, 0]
        keep = np.flatnonzero(scores >= conf_threshold)  # only these anchors' boxes are decoded
        box, step = raw[b, keep, :4], stride_of[keep, None]
        xy = centres[keep] + box[:, :2] * step
        wh = np.exp(np.minimum(box[:, 2:], 10.0)) * step
        bx = np.concatenate([xy - wh / 2, xy + wh / 2], axis=1)
        if image_size is not None:
            height, width = image_size
            bx = np.stack([np.clip(bx[:, 0], 0, width), np.clip(bx[:, 1], 0, height),
                           np.clip(bx[:, 2], 0, width), np.clip(bx[:, 3], 0, height)], axis=1)
        sc, lb = scores[keep], labels[keep]
        if len(sc) > pre_nms:
            top = np.argsort(-sc, kind="stable")[:pre_nms]
            bx, sc, lb = bx[top], sc[top], lb[top]
        kept = _nms_numpy(bx, sc, nms_threshold, lb)[:max_detections] if len(bx) else np.zeros(0, dtype=np.int64)
        results.append({"boxes": torch.from_numpy(np.ascontiguousarray(bx[kept])).reshape(-1, 4),
                        "scores": torch.from_numpy(np.ascontiguousarray(sc[kept])),
                        "labels": torch.from_numpy(lb[kept].astype(np.int64))})
    return results


# ------------------------------------------------------------------ incremental computation
# Rows: a map channels-last, ``(h w, C)``, cells row-major. A 1x1 or 3x3 convolution applies to rows
# as a matrix product with its weight laid out ``(C_out, row, column, C_in)``.

def conv_rows(conv: nn.Conv2d) -> torch.Tensor:
    """The weight of ``conv`` as a matrix over rows: ``(C_out, k k C_in)``."""
    return conv.weight.permute(0, 2, 3, 1).reshape(conv.out_channels, -1)


def norm_act_rows(block: nn.Sequential, y: torch.Tensor) -> torch.Tensor:
    """A :func:`~dagr_lite.nn.blocks.conv_bn_act` block's batch norm (evaluation mode) and
    activation on rows ``y (n, C)`` of its convolution's output (without its bias: a block whose
    batch norm :func:`~dagr_lite.nn.blocks.fold_batch_norms` folded adds its convolution's bias)."""
    conv, bn, act = block
    if isinstance(bn, nn.Identity):
        return act(y + conv.bias)
    return act(F.batch_norm(y, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps))


def block_rows(block: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """A 1x1 :func:`~dagr_lite.nn.blocks.conv_bn_act` block on rows ``x (n, C_in)``."""
    return norm_act_rows(block, x @ conv_rows(block[0]).T)


def flat_map(x: torch.Tensor) -> torch.Tensor:
    """``(B, C, h, w) -> (B h w, C)``, cells row-major (a map channels-last; a view of a channels-last map)."""
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1])


def grow(mask: torch.Tensor) -> torch.Tensor:
    """``mask (h, w)`` bool grown by one cell in each direction (its 3x3 neighbourhoods)."""
    return F.max_pool2d(mask[None, None].to(torch.float32), 3, stride=1, padding=1)[0, 0] > 0


_OFFSETS: dict[int, torch.Tensor] = {}  # per padded map width: the flat offsets of a 3x3 neighbourhood


def conv3x3_at(padded: torch.Tensor, width: int, weight: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """A 3x3 convolution ("same" padding, no bias) at some cells of a map, from the map zero-padded
    by one cell and flattened channels-last, ``padded ((h + 2) (w + 2), C)``: ``cells (n,)`` are
    indices into it (``(row + 1) (w + 2) + column + 1``), ``weight (C_out, 3 3 C)`` the convolution's
    weight as :func:`conv_rows` lays it out. Returns ``(n, C_out)``."""
    offsets = _OFFSETS.get(width)
    if offsets is None:
        offsets = _OFFSETS[width] = torch.tensor([dy * (width + 2) + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    patches = padded[(cells[:, None] + offsets.to(cells.device)[None, :]).reshape(-1)].reshape(len(cells), -1)
    return patches @ weight.T


class TowerCache:
    """A :class:`YOLOXHead` whose query maps enter after its towers (``late_channels``) over a
    stream of event maps, its towers recomputed only where the maps changed.

    Nothing before the towers' outputs depends on the query time: a cell's fused input changes
    only where its event map does, a first tower layer's output within one cell of such a cell,
    the second layer's within two. :meth:`update` compares the new event maps with the last ones
    (exact equality), runs the pointwise fusion and stem at the changed cells and each 3x3 layer at
    the cells it can change, from the cached (zero-padded, channels-last) outputs of the layer
    before; where that is most of a map, the whole map is run instead. A hybrid's image towers run
    once per image. :meth:`answer` runs what reads the query maps, all 1x1 (the age gates, the late
    layers and the predictions), over every cell from the cached tower outputs.

    ``fuse_map(i, image_map, event_map)`` and ``fuse_rows(i, image_rows, event_rows)``: the
    detector's fusion at stride ``i`` of maps and of rows (a hybrid's; None for events-only).
    """

    FULL_FRACTION = 0.5  # run the whole map when the cells to recompute are more than this share of it

    def __init__(self, head: "YOLOXHead", fuse_map: Callable | None = None, fuse_rows: Callable | None = None):
        if not head.late_channels:
            raise ValueError("a tower cache needs a head whose query maps enter after its towers (late_query)")
        self.head, self.fuse_map, self.fuse_rows = head, fuse_map, fuse_rows
        self.event_maps: list[torch.Tensor] | None = None
        self.image_towers: list[tuple[torch.Tensor, torch.Tensor]] | None = None  # flat, per stride
        self.cache: list[dict] = []  # per stride: flat stem and tower outputs (the stem and first layers padded)
        self.weights = [self._weights(i) for i in range(len(head.stems))]

    def _weights(self, i: int) -> dict[str, torch.Tensor]:
        """Stride ``i``'s weights as matrices over rows; a late layer's split by what it reads:
        ``[tower, (gated image tower,) query maps]``."""
        head = self.head
        hidden = head.stems[i][0].out_channels
        w = {}
        for name, branch, late in (("cls", head.cls_branches[i], head.cls_late[i]),
                                   ("reg", head.reg_branches[i], head.reg_late[i])):
            w[name + "1"], w[name + "2"] = conv_rows(branch[0][0]), conv_rows(branch[1][0])
            late_w = conv_rows(late[0])
            towers = 2 * hidden if head.has_image else hidden
            w[name + "_tower"], w[name + "_image"], w[name + "_query"] = \
                late_w[:, :hidden], late_w[:, hidden:towers], late_w[:, towers:]
        for name in ("reg", "obj", "cls"):
            w[name + "_pred"] = conv_rows(getattr(head, name + "_preds")[i])
        if head.has_image:
            w["gate"] = conv_rows(head.gates[i])
        return w

    def update(self, image_maps: list[torch.Tensor] | None, event_maps: list[torch.Tensor]) -> None:
        """Bring the towers up to the event maps ``(1, C, h, w)`` per stride (the image's are fixed)."""
        if self.event_maps is None:
            self.cache = [self._full(i, image_maps, event_maps) for i in range(len(event_maps))]
            if self.head.has_image:  # once per image
                self.image_towers = [tuple(flat_map(t) for t in self.head.image_towers(i, m))
                                     for i, m in enumerate(image_maps[1:])]
        else:
            for i, (new, old) in enumerate(zip(event_maps, self.event_maps)):
                if new is old:
                    continue
                changed = (new != old).any(dim=1)[0]  # (h, w)
                if not changed.any():
                    continue
                near = grow(changed)
                reach = grow(near)
                if (image_maps is not None and image_maps[i + 1].shape[-2:] != new.shape[-2:]) or \
                        int(reach.sum()) > self.FULL_FRACTION * reach.numel():
                    self.cache[i] = self._full(i, image_maps, event_maps)
                else:
                    self._partial(i, new, changed, near, reach)
        self.event_maps = list(event_maps)

    def answer(self, query: list[torch.Tensor]) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        """The head's raw output ``(1, A, 5 + C)`` and map shapes for the query maps ``(1, q, h, w)``."""
        head, outputs, shapes, linear = self.head, [], [], F.linear
        for i, (cache, q) in enumerate(zip(self.cache, query)):
            w, q = self.weights[i], flat_map(q)
            cls = cache["cls2"] @ w["cls_tower"].T + q @ w["cls_query"].T
            reg = cache["reg2"] @ w["reg_tower"].T + q @ w["reg_query"].T
            if head.has_image:  # the image towers, scaled by the age's gates (one age at every cell)
                gate = linear(q[:1, -1:], w["gate"], head.gates[i].bias)
                cls_gate, reg_gate = (2 * torch.sigmoid(gate)).chunk(2, dim=1)
                cls = cls + (self.image_towers[i][0] * cls_gate) @ w["cls_image"].T
                reg = reg + (self.image_towers[i][1] * reg_gate) @ w["reg_image"].T
            cls, reg = norm_act_rows(head.cls_late[i], cls), norm_act_rows(head.reg_late[i], reg)
            outputs.append(torch.cat([linear(reg, w["reg_pred"], head.reg_preds[i].bias),
                                      linear(reg, w["obj_pred"], head.obj_preds[i].bias),
                                      linear(cls, w["cls_pred"], head.cls_preds[i].bias)], dim=1))  # (h w, 5 + C)
            shapes.append(cache["shape"])
        return torch.cat(outputs)[None], shapes

    def _full(self, i: int, image_maps, event_maps) -> dict:
        head = self.head
        fused = event_maps[i] if image_maps is None else self.fuse_map(i, image_maps[i + 1], event_maps[i])
        stem = head.stems[i](fused)
        h, wd = stem.shape[-2:]
        cache = {"shape": (h, wd), "width": wd,
                 "image": None if image_maps is None else flat_map(image_maps[i + 1]),
                 "stem": flat_map(F.pad(stem, (1, 1, 1, 1)))}
        for name, branch in (("cls", head.cls_branches[i]), ("reg", head.reg_branches[i])):
            first = branch[0](stem)
            cache[name + "1"] = flat_map(F.pad(first, (1, 1, 1, 1)))
            cache[name + "2"] = flat_map(branch[1](first))
        return cache

    def _partial(self, i: int, event_map: torch.Tensor, changed: torch.Tensor, near: torch.Tensor,
                 reach: torch.Tensor) -> None:
        """Recompute the stem at the ``changed`` cells, the towers' first layers at the cells ``near``
        them (one cell away at most) and their second layers within ``reach`` (two)."""
        head, cache, w = self.head, self.cache[i], self.weights[i]
        width = cache["width"]

        def cells(mask):
            flat = torch.nonzero(mask.flatten()).flatten()  # row-major cell indices
            return flat, (flat // width + 1) * (width + 2) + flat % width + 1  # and in the padded map
        flat, padded = cells(changed)
        x = event_map[0].reshape(event_map.shape[1], -1).index_select(1, flat).T  # (n, C)
        if cache["image"] is not None:
            x = self.fuse_rows(i, cache["image"][flat], x)
        cache["stem"][padded] = block_rows(head.stems[i], x)
        _, padded = cells(near)
        for name, branch in (("cls", head.cls_branches[i]), ("reg", head.reg_branches[i])):
            cache[name + "1"][padded] = norm_act_rows(branch[0], conv3x3_at(cache["stem"], width, w[name + "1"], padded))
        flat, padded = cells(reach)
        for name, branch in (("cls", head.cls_branches[i]), ("reg", head.reg_branches[i])):
            cache[name + "2"][flat] = norm_act_rows(branch[1], conv3x3_at(cache[name + "1"], width, w[name + "2"],
                                                                          padded))
