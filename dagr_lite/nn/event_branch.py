"""The event branch: causal GCN stages on the event graph, voxel pooling, dense maps per stride.

Events become graph nodes at ``(x, y, beta * t)`` with features polarity (+-1), position
normalised to [0, 1] (x / W, y / H), in a model with an image the time since the image and, with
``geometry``, the shape of the node's causal neighbourhood (:func:`neighbourhood_geometry`: where
its earlier neighbours lie in space and time, the local motion a GCN's isotropic sum cannot see). A stage of GCN blocks runs on the full event
graph, then the graph is max-pooled into ``stride``-pixel cells for each output stride in turn,
with more GCN blocks after each pooling; each pooled level is written out as a dense map
``(B, C, H / stride, W / stride)`` for the detection head. With ``dense`` the pooled stages are
convolutions instead: the first stage's nodes are max-pooled into ``dense``-pixel cells written
out as a dense map, and residual convolution stages (a 3x3 one at that stride, then one of
stride 2 per doubling) give the maps, as a CNN reads a picture.

A hook lets image features join the nodes: ``image_sampler(pos_xy, batch, level)`` returns
``(N, C_level)`` features sampled at the nodes' pixels (level 0 is the input, level ``s`` the
``s``-th pooled graph); they are concatenated to the node features before that level's blocks.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn

from dagr_lite.graph.compiled import neighbourhood_moments
from dagr_lite.graph.pool import PooledGraph, max_pool_to_dense, to_dense, voxel_max_pool
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.blocks import Residual, conv_bn_act
from dagr_lite.nn.gcn import GCNConv, GraphOperator
from dagr_lite.nn.kernels import NodeGraph, compiled_inference, gcn_block

ImageSampler = Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]


GEOMETRY_FEATURES = 10


def neighbourhood_geometry(pos: torch.Tensor, edge_index: torch.Tensor, radius: float, max_neighbors: int,
                           first: int = 0) -> torch.Tensor:
    """``(N - first, 10)`` features of each node ``i >= first`` from its incoming edges ``j -> i``:
    with ``d = (pos_j - pos_i) / radius`` (``dx, dy, dt``; ``dt <= 0``, earlier neighbours), the means
    of ``d`` (3), of ``d * d`` (3) and of ``dx dt, dy dt, dx dy`` (3) over the neighbours, and the
    in-degree over ``max_neighbors`` (0 and zeros for a node without neighbours).

    They depend on the node's edges alone, which the causal graph fixes when the node arrives, so
    they never change afterwards (the streaming detector computes them for new nodes only).
    ``first``: the nodes whose features are wanted are ``first, first + 1, ...`` (every edge's
    destination among them); ``pos`` holds every node an edge names.

    On the CPU one compiled pass over the edges (:func:`~dagr_lite.graph.compiled.neighbourhood_moments`,
    5.6 ms against the tensor expressions' 38.5 ms at a training batch's 580k edges); on another device,
    or where ``pos`` needs a gradient, :func:`neighbourhood_geometry_reference`. Both sum each node's
    edges in their order: in float64 they agree to the bit."""
    if pos.device.type != "cpu" or pos.requires_grad or pos.dtype not in (torch.float32, torch.float64):
        return neighbourhood_geometry_reference(pos, edge_index, radius, max_neighbors, first)
    pos_np = pos.detach().contiguous().numpy()
    edges = edge_index.detach().to(torch.int64).contiguous().numpy()
    out = np.zeros((len(pos_np) - first, GEOMETRY_FEATURES), dtype=pos_np.dtype)
    neighbourhood_moments(pos_np, edges[0], edges[1], first, pos_np.dtype.type(radius),
                          pos_np.dtype.type(max_neighbors), out)
    return torch.from_numpy(out)


def neighbourhood_geometry_reference(pos: torch.Tensor, edge_index: torch.Tensor, radius: float,
                                     max_neighbors: int, first: int = 0) -> torch.Tensor:
    """:func:`neighbourhood_geometry` by tensor expressions (any device; differentiable in ``pos``)."""
    n = len(pos) - first
    src, dst = edge_index[0], edge_index[1] - first
    d = (pos[src] - pos[edge_index[1]]) / radius  # (E, 3)
    dx, dy, dt = d.unbind(dim=1)
    terms = torch.cat([d, d * d, torch.stack([dx * dt, dy * dt, dx * dy], dim=1)], dim=1)  # (E, 9)
    sums = terms.new_zeros(n, 9).index_add_(0, dst, terms)
    degree = torch.bincount(dst, minlength=n).to(pos.dtype)  # (n,)
    return torch.cat([sums / degree.clamp(min=1).unsqueeze(1), (degree / max_neighbors).unsqueeze(1)], dim=1)


def keep_nodes(keep: torch.Tensor, x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor,
               edge_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The nodes where ``keep (N,)`` is true, and the edges between two of them, renumbered."""
    new_id = torch.cumsum(keep, 0) - 1
    edges = edge_index[:, keep[edge_index[0]] & keep[edge_index[1]]]
    return x[keep], pos[keep], batch[keep], new_id[edges]


class GCNBlock(nn.Module):
    """GCN, per-node LayerNorm (no statistics shared across nodes or time), ReLU, residual.

    Shapes:
        x ``(N, F_in)`` and a :class:`GraphOperator` over the N nodes -> ``(N, F_out)``; with a
        :class:`~dagr_lite.nn.kernels.NodeGraph` (inference, :meth:`EventBranch.stage_graph`), one
        compiled pass giving rows ``first ..`` only.
    """

    def __init__(self, in_channels: int, out_channels: int, offsets: bool = False):
        super().__init__()
        self.conv = GCNConv(in_channels, out_channels, offsets=offsets)
        self.norm = nn.LayerNorm(out_channels)
        self.skip = nn.Identity() if in_channels == out_channels else nn.Linear(in_channels, out_channels, bias=False)

    def forward(self, x: torch.Tensor, op: GraphOperator | NodeGraph) -> torch.Tensor:
        """With ``op.rows`` set, the output holds those rows only (``x`` still holds every node)."""
        if isinstance(op, NodeGraph):
            return gcn_block(self, x, op)
        return torch.relu(self.norm(self.conv(x, op))) + self.skip(x if op.rows is None else x[op.rows])


class EventBranch(nn.Module):
    """Causal GCN stack over events with pooling to dense maps at ``strides``.

    Args:
        height, width: sensor size in pixels.
        channels: feature size of the input stage and of each pooled stage (``len(strides) + 1``).
        strides: pooling cell sizes in pixels, increasing; one dense map each.
        graph: the event graph's settings (node positions and edges).
        time_scale_us: with it, nodes carry their time since the image, ``t / time_scale_us``
            (events' ``t`` counts from the image); None: no time feature (a model without an image).
        blocks: GCN blocks per stage.
        image_channels: image feature channels joined at each level (input, then each stride).
        geometry: nodes also carry :func:`neighbourhood_geometry` (10 features).
        directional: the first stage's messages are also weighted by the neighbour's offset from
            the node in units of the graph's radius (``GCNConv(offsets=True)``), so its blocks sense
            the direction of motion.
        dense: > 0: the pooled stages are convolutions over dense maps instead of GCN blocks over
            the pooled graphs. The first stage's nodes are max-pooled into cells of ``dense``
            pixels (the first stride, or that halved one or more times), written out as a map, and
            read by one stage per stride from ``dense`` to the last (a :func:`conv_bn_act`, of
            stride 2 after the first, and a :class:`Residual`); a stride below the first gets half
            the width of the stride above it. Image features then join at the input level alone
            (``image_channels`` is 0 after it). 0: GCN blocks over the pooled graphs.

    Shapes:
        events ``(N, 4)`` x, y, t (us since the image), p; batch ``(N,)`` sorted ->
        list of ``(B, channels[s + 1], ceil(H / strides[s]), ceil(W / strides[s]))``.
    """

    def __init__(self, *, height: int, width: int, channels: Sequence[int], strides: Sequence[int],
                 graph: EventGraphSpec, time_scale_us: float | None, blocks: int, image_channels: Sequence[int] | None = None,
                 geometry: bool = False, directional: bool = False, dense: int = 0):
        super().__init__()
        if len(channels) != len(strides) + 1:
            raise ValueError(f"channels needs one entry for the input stage and one per stride: "
                             f"{len(strides) + 1}, got {len(channels)}")
        if list(strides) != sorted(strides) or len(set(strides)) != len(strides):
            raise ValueError(f"strides must increase, got {list(strides)}")
        self.height, self.width, self.strides = height, width, tuple(strides)
        self.spec, self.time_scale_us = graph, time_scale_us
        self.image_channels = tuple(image_channels) if image_channels is not None else (0,) * len(channels)
        if len(self.image_channels) != len(channels):
            raise ValueError(f"image_channels needs {len(channels)} entries, got {len(self.image_channels)}")
        self.out_channels = tuple(channels[1:])
        self.geometry, self.directional, self.dense = bool(geometry), bool(directional), int(dense)
        halvings = self.strides[0] // self.dense if self.dense > 0 else 0
        if self.dense and (self.dense * halvings != self.strides[0] or halvings & (halvings - 1)):
            raise ValueError(f"event_dense must be 0 or the first stride {self.strides[0]} halved zero or more "
                             f"times, got {dense}")
        if self.dense and any(self.image_channels[1:]):
            raise ValueError(f"dense pooled stages read image features at the input level alone, got image_channels "
                             f"{list(self.image_channels)}")
        in_features = (3 if time_scale_us is None else 4) + (GEOMETRY_FEATURES if self.geometry else 0)
        self.stages = nn.ModuleList()
        self.dense_stages = None
        if self.dense:  # widths: below the first stride, half the width of the stride above
            extra = int(math.log2(self.strides[0] // self.dense))
            widths = [channels[0], *(max(channels[1] // 2 ** k, 1) for k in range(extra, 0, -1)), *channels[1:]]
            self.dense_stages = nn.ModuleList(
                nn.Sequential(conv_bn_act(c_in, c_out, stride=1 if i == 0 else 2), Residual(c_out))
                for i, (c_in, c_out) in enumerate(zip(widths[:-1], widths[1:])))
        for level, out in enumerate(channels[:1] if self.dense else channels):
            width_in = (in_features if level == 0 else channels[level - 1]) + self.image_channels[level]
            self.stages.append(nn.ModuleList(GCNBlock(width_in if b == 0 else out, out,
                                                      offsets=self.directional and level == 0)
                                             for b in range(blocks)))

    @property
    def pool_stride(self) -> int:
        """The cell size, in pixels, of the first pooling of the event nodes."""
        return self.dense or self.strides[0]

    @property
    def first_stage(self) -> nn.ModuleList:
        """The first stage's GCN blocks, over the event nodes (before any pooling)."""
        return self.stages[0]

    @property
    def first_stage_widths(self) -> list[int]:
        """The width of the first stage's input, then of each of its blocks' outputs."""
        return [self.first_stage[0].conv.in_channels, *(block.conv.out_channels for block in self.first_stage)]

    def first_stage_offsets(self, pos: torch.Tensor) -> dict:
        """The :class:`GraphOperator` arguments that give the first stage its offsets, from every
        node's position ``pos (N, 3)`` (none unless ``directional``)."""
        return {"offset_pos": pos, "offset_unit": self.spec.radius} if self.directional else {}

    def maps_from_first_pool(self, first: PooledGraph, image_sampler: ImageSampler | None = None
                             ) -> list[torch.Tensor]:
        """The dense maps of one sample whose first pooled graph is known (the streaming detector
        keeps it up to date as nodes arrive): :meth:`pooled_maps` from there."""
        return self.pooled_maps(None, None, None, None, 1, image_sampler, first=first)

    def node_features(self, events: torch.Tensor, pos: torch.Tensor | None = None,
                      edge_index: torch.Tensor | None = None, first: int = 0) -> torch.Tensor:
        """``(N, 3)`` polarity in {-1, 1}, x / W, y / H; with ``geometry`` then the ten columns of
        :func:`neighbourhood_geometry` (which need the nodes' positions ``pos`` and graph
        ``edge_index``; ``events`` are then the nodes from ``first`` on, ``pos`` every node); with a
        time scale last the time since the image, ``t / time_scale_us``. The geometry is computed in
        ``pos``'s dtype and cast to the events': float64 positions of whole microseconds
        (:attr:`~dagr_lite.graph.spec.EventGraphSpec.time_scale`) give exact offsets, so features
        that do not depend on where time counts from (the batch model and the streaming detector
        pass them).

        Each depends on the event alone, its causal neighbourhood and the image's time, never on a
        window's start or on the time of a query, so a node's features are fixed once its event has
        arrived.
        """
        x, y, t, p = events.unbind(dim=1)
        columns = [2 * p - 1, x / self.width, y / self.height]
        if self.geometry:
            if pos is None or edge_index is None:
                raise ValueError("an event branch with geometry needs the nodes' positions and graph for its features")
            shape = neighbourhood_geometry(pos, edge_index, self.spec.radius, self.spec.max_neighbors, first)
            columns.extend(shape.to(events.dtype).unbind(dim=1))
        # the time comes last: an events-only branch's inputs are then a hybrid's first columns, so a
        # warm start widens its first layer by appending (nn/warm_start.py)
        if self.time_scale_us is not None:
            columns.append(t / self.time_scale_us)
        return torch.stack(columns, dim=1)

    def forward(self, events: torch.Tensor, batch: torch.Tensor, batch_size: int,
                image_sampler: ImageSampler | None = None, edge_index: torch.Tensor | None = None,
                pooled: torch.Tensor | None = None) -> list[torch.Tensor]:
        """``edge_index``: the event graph if already built (e.g. by the data loader's workers);
        ``pooled``: ``(N,)`` bool, the nodes that are pooled into the maps (the others are a graph
        context the first stage reads, :meth:`~dagr_lite.data.collate.Batch.pooled`); None: all."""
        x, pos, edge_index = self.event_nodes(events, batch, image_sampler, edge_index)
        if pooled is not None:
            x, pos, batch, edge_index = keep_nodes(pooled, x, pos, batch, edge_index)
        return self.pooled_maps(x, pos, batch, edge_index, batch_size, image_sampler)

    def pooled_maps(self, x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor, edge_index: torch.Tensor | None,
                    batch_size: int, image_sampler: ImageSampler | None = None, *,
                    first: PooledGraph | None = None) -> list[torch.Tensor]:
        """The dense maps from the first stage's node features ``x (N, channels[0])``.

        ``first``: the first pooled graph when it is already known (the streaming detector keeps it
        up to date as nodes arrive); ``x``, ``pos``, ``batch`` and ``edge_index`` are then unused.
        Dense pooled stages never read ``edge_index`` (None serves).
        """
        if self.dense:  # the cells' edges are not read
            size = {"batch_size": batch_size, "height": math.ceil(self.height / self.dense),
                    "width": math.ceil(self.width / self.dense)}
            m = (to_dense(first.x, first.batch, first.cell, **size) if first is not None
                 else max_pool_to_dense(x, pos, batch, self.dense, **size))
            maps = []
            for stage in self.dense_stages:
                m = stage(m)
                maps.append(m)
            return maps[-len(self.strides):]  # a stage below the first stride gives no map
        maps = []
        for level, stride in enumerate(self.strides, start=1):
            if level == 1 and first is not None:
                pooled = first
            else:
                pooled = voxel_max_pool(x, pos, batch, edge_index, stride)
            x, pos, batch, edge_index = pooled.x, pooled.pos, pooled.batch, pooled.edge_index
            x = self._stage(level, x, pos, batch, edge_index, image_sampler)
            maps.append(to_dense(x, batch, pooled.cell, batch_size=batch_size,
                                 height=math.ceil(self.height / stride), width=math.ceil(self.width / stride)))
        return maps

    def event_nodes(self, events: torch.Tensor, batch: torch.Tensor, image_sampler: ImageSampler | None = None,
                    edge_index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The features ``(N, channels[0])`` of the event nodes after the first stage, their
        positions ``(N, 3)`` and the graph ``(2, E)``.

        A node's features here depend on its event, its causal past and the image only (the
        causal graph and per-node normalisation): adding later events or asking at a later
        time leaves them unchanged.
        """
        if edge_index is None:
            edge_index = self.spec.edges(events, batch)
        edge_index = edge_index.to(events.device)  # (2, E)
        pos = self.spec.positions(events)  # (N, 3)
        # the geometry and the directional offsets read exact float64 positions: the same whatever time
        # the events count from
        exact = self.spec.positions(events.detach().double()) if self.geometry or self.directional else pos
        features = self.node_features(events, exact, edge_index)
        return self._stage(0, features, pos, batch, edge_index, image_sampler, offset_pos=exact), pos, edge_index

    def level_input(self, level: int, x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor,
                    image_sampler: ImageSampler | None) -> torch.Tensor:
        """The input of level ``level``'s blocks: ``x`` with the image features at the nodes joined."""
        if not self.image_channels[level]:
            return x
        if image_sampler is None:
            raise ValueError(f"the branch expects {self.image_channels[level]} image channels at level "
                             f"{level}, but no image_sampler was given")
        return torch.cat([x, image_sampler(pos[:, :2], batch, level)], dim=1)

    def _stage(self, level: int, x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor, edge_index: torch.Tensor,
               image_sampler: ImageSampler | None, offset_pos: torch.Tensor | None = None) -> torch.Tensor:
        """``offset_pos``: the positions the first stage's directional offsets read (default ``pos``)."""
        x = self.level_input(level, x, pos, batch, image_sampler)
        op = self.stage_graph(level, x, edge_index, pos if offset_pos is None else offset_pos)
        for block in self.stages[level]:
            x = block(x, op)
        return x

    def stage_graph(self, level: int, x: torch.Tensor, edge_index: torch.Tensor, offset_pos: torch.Tensor, *,
                    in_degree: torch.Tensor | None = None, first: int = 0) -> GraphOperator | NodeGraph:
        """The graph level ``level``'s blocks read over the nodes of ``x (N, F)``, giving rows ``first ..``:
        in inference on a CPU without offsets a :class:`~dagr_lite.nn.kernels.NodeGraph` (each block one
        compiled pass), else a :class:`GraphOperator` (``rows`` from ``first`` where ``first`` or
        ``in_degree``, the streaming form, is given). ``offset_pos``: the positions the first stage's
        directional offsets read; ``in_degree``: every node's, where ``edge_index`` holds only the edges
        into rows ``first ..``."""
        offsets = self.first_stage_offsets(offset_pos) if level == 0 else {}
        if not offsets and compiled_inference(x):
            return NodeGraph(edge_index, len(x), in_degree=in_degree, first=first)
        rows = None if first == 0 and in_degree is None else torch.arange(first, len(x), device=x.device)
        return GraphOperator(edge_index, len(x), in_degree=in_degree, rows=rows, **offsets)
