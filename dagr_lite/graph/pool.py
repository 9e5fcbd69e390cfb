"""Voxel-grid max pooling over (x, y) and dense maps for the detection head.

Nodes are grouped into cells of ``size x size`` pixels per sample; a cell's features are the
maximum over its nodes and its position the mean of theirs. Edges map to edges between cells,
deduplicated; an edge inside one cell becomes that cell's self-loop and is kept (the GCN adds
the identity itself and ignores self-loops in ``edge_index``). Cells are ordered by (sample,
row, column), so pooling the same nodes always gives the same cells.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from dagr_lite.graph.sparse import KERNEL, compiled_for, unique_inverse, unique_pairs


@dataclass
class PooledGraph:
    """The coarser graph of :func:`voxel_max_pool`.

    Attributes:
        x: ``(C, F)`` cell features; pos: ``(C, 3)`` mean member positions; batch: ``(C,)``.
        cell: ``(C, 2)`` int64 cell row and column (``floor(y / size)``, ``floor(x / size)``).
        edge_index: ``(2, E_c)`` cell edges, deduplicated, sorted by (destination, source).
        cluster: ``(N,)`` the cell of each input node.
    """

    x: torch.Tensor
    pos: torch.Tensor
    batch: torch.Tensor
    cell: torch.Tensor
    edge_index: torch.Tensor
    cluster: torch.Tensor


def voxel_max_pool(x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor, edge_index: torch.Tensor | None,
                   size: float) -> PooledGraph:
    """Max-pool nodes into ``size``-pixel cells over (x, y).

    ``edge_index`` None: the cells alone, without edges (``edge_index`` of the result is empty),
    for a caller that reads no pooled graph (dense stages): the edges are most of the work.

    Shapes:
        x ``(N, F)``, pos ``(N, 3)`` with columns x, y, z, batch ``(N,)``, edge_index ``(2, E)``
        -> :class:`PooledGraph` with ``C`` cells.
    """
    if size <= 0:
        raise ValueError(f"size must be positive, got {size}")
    if compiled_for(x) and len(x) and not (torch.is_grad_enabled() and (x.requires_grad or pos.requires_grad)):
        compiled = _compiled_pool(x, pos, batch, edge_index, size)
        if compiled is not None:
            return compiled
    device = x.device
    col = torch.div(pos[:, 0], size, rounding_mode="floor").to(torch.int64)  # (N,)
    row = torch.div(pos[:, 1], size, rounding_mode="floor").to(torch.int64)  # (N,)
    if len(x) and (col.min() < 0 or row.min() < 0):
        raise ValueError("pooling needs non-negative x and y positions")
    width = int(col.max()) + 1 if len(x) else 1
    height = int(row.max()) + 1 if len(x) else 1
    key = (batch.to(torch.int64) * height + row) * width + col  # (N,)
    batch_size = int(batch.max()) + 1 if len(x) else 1
    on_cpu = compiled_for(key)
    found = unique_inverse(key.contiguous().numpy(), batch_size * height * width) if on_cpu else None
    if found is not None:  # a table of every cell instead of a sort: the same cells (graph/sparse.py)
        unique, cluster = (torch.from_numpy(a) for a in found)
    else:
        unique, cluster = torch.unique(key, sorted=True, return_inverse=True)  # (C,), (N,)
    num_cells = len(unique)
    index = cluster[:, None].expand(-1, x.shape[1])
    pooled = torch.zeros((num_cells, x.shape[1]), dtype=x.dtype, device=device)
    pooled = pooled.scatter_reduce(0, index, x, reduce="amax", include_self=False)  # (C, F)
    counts = torch.bincount(cluster, minlength=num_cells).clamp(min=1).to(pos.dtype)
    pos_c = torch.zeros((num_cells, pos.shape[1]), dtype=pos.dtype, device=device)
    pos_c = pos_c.index_add(0, cluster, pos) / counts[:, None]  # (C, 3)
    batch_c = torch.div(unique, height * width, rounding_mode="floor")
    cell = torch.stack([torch.div(unique, width, rounding_mode="floor") % height, unique % width], dim=1)
    if edge_index is None:
        return PooledGraph(x=pooled, pos=pos_c, batch=batch_c, cell=cell,
                           edge_index=torch.zeros((2, 0), dtype=torch.int64, device=device), cluster=cluster)
    edges = cluster[edge_index]  # (2, E)
    if on_cpu:  # grouped by destination cell in one pass instead of a sort: the same edges (graph/sparse.py)
        src, dst = unique_pairs(edges[0].contiguous().numpy(), edges[1].contiguous().numpy(), max(num_cells, 1))
        return PooledGraph(x=pooled, pos=pos_c, batch=batch_c, cell=cell,
                           edge_index=torch.from_numpy(np.stack([src, dst])), cluster=cluster)
    edge_key = edges[1] * max(num_cells, 1) + edges[0]  # (E,)
    if len(edge_key) > 1:  # neighbouring edges often map to the same cell pair: drop those repeats first
        edge_key = edge_key[torch.cat([edge_key.new_ones(1, dtype=torch.bool), edge_key[1:] != edge_key[:-1]])]
    edge_key = torch.unique(edge_key, sorted=True)  # deduplicated, by (dst, src)
    edge_index_c = torch.stack([edge_key % max(num_cells, 1), torch.div(edge_key, max(num_cells, 1),
                                                                         rounding_mode="floor")])
    return PooledGraph(x=pooled, pos=pos_c, batch=batch_c, cell=cell, edge_index=edge_index_c, cluster=cluster)


@numba.njit(**KERNEL)
def _cell_keys(pos, batch, size):
    """Each node's cell key ``(sample row + row) width + column`` and the grid's ``(width, height,
    samples)``, as :func:`voxel_max_pool` computes them; None where a position is negative."""
    n = len(pos)
    col = np.empty(n, dtype=np.int64)
    row = np.empty(n, dtype=np.int64)
    width, height, samples = 1, 1, 1
    for i in range(n):
        col[i] = np.int64(np.floor(pos[i, 0] / size))
        row[i] = np.int64(np.floor(pos[i, 1] / size))
        if col[i] < 0 or row[i] < 0:
            return None
        width, height, samples = max(width, col[i] + 1), max(height, row[i] + 1), max(samples, batch[i] + 1)
    key = (batch * height + row) * width + col
    return key, width, height, samples


def _compiled_pool(x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor, edge_index: torch.Tensor | None,
                   size: float) -> PooledGraph | None:
    """:func:`voxel_max_pool` on a CPU without gradients in compiled passes: the cells by the table of
    :func:`~dagr_lite.graph.sparse.unique_inverse`, the members' maxima and position sums by
    :func:`add_members` (in node order, as ``index_add`` sums them), the cell edges by ``unique_pairs``
    (``tests/graph/test_pool.py`` holds it to the tensor operations). None where the table would be
    too large (the caller sorts instead)."""
    found = _cell_keys(pos.detach().contiguous().numpy(), batch.to(torch.int64).contiguous().numpy(), float(size))
    if found is None:
        raise ValueError("pooling needs non-negative x and y positions")
    key, width, height, samples = found
    cells = unique_inverse(key, samples * height * width)
    if cells is None:
        return None
    unique, cluster = cells
    features = x.detach().contiguous().numpy()
    points = pos.detach().contiguous().numpy()
    pooled = np.full((len(unique), features.shape[1]), -np.inf, dtype=features.dtype)
    pos_sum = np.zeros((len(unique), points.shape[1]), dtype=points.dtype)
    counts = np.zeros(len(unique), dtype=np.int64)
    none = np.zeros(0, dtype=np.int64)
    add_members(pooled, pos_sum, counts, np.zeros(0, dtype=np.bool_), features, points, cluster, none, none)
    pos_c = pos_sum / counts[:, None].astype(points.dtype)
    cell = np.stack([(unique // width) % height, unique % width], axis=1)
    if edge_index is None:
        edges = np.zeros((2, 0), dtype=np.int64)
    else:
        index = edge_index.to(torch.int64).contiguous().numpy()
        edges = np.stack(unique_pairs(cluster[index[0]], cluster[index[1]], max(len(unique), 1)))
    return PooledGraph(x=torch.from_numpy(pooled), pos=torch.from_numpy(pos_c),
                       batch=torch.from_numpy(unique // (height * width)), cell=torch.from_numpy(cell),
                       edge_index=torch.from_numpy(edges), cluster=torch.from_numpy(cluster))


def to_dense(x: torch.Tensor, batch: torch.Tensor, cell: torch.Tensor, *, batch_size: int, height: int,
             width: int) -> torch.Tensor:
    """Write cell features into dense maps; empty cells are zero, cells outside are dropped.

    Shapes:
        x ``(C, F)``, batch ``(C,)``, cell ``(C, 2)`` rows and columns -> ``(B, F, H, W)``.
    """
    dense = x.new_zeros((batch_size, height, width, x.shape[1]))  # (B, H, W, F)
    if (compiled_for(x) and x.dtype in (torch.float32, torch.float64) and len(x)
            and not (torch.is_grad_enabled() and x.requires_grad)):  # one compiled pass: the same copies
        _write_cells(x.detach().contiguous().numpy(), batch.to(torch.int64).contiguous().numpy(),
                     cell.to(torch.int64).contiguous().numpy(), dense.numpy())
        return dense.permute(0, 3, 1, 2)
    inside = (cell[:, 0] < height) & (cell[:, 1] < width) & (batch < batch_size)
    dense[batch[inside], cell[inside, 0], cell[inside, 1]] = x[inside]
    return dense.permute(0, 3, 1, 2)  # (B, F, H, W)


def max_pool_to_dense(x: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor, size: float, *, batch_size: int,
                      height: int, width: int) -> torch.Tensor:
    """``to_dense`` of ``voxel_max_pool(x, pos, batch, None, size)``: the nodes max-pooled into
    ``size``-pixel cells, written out as maps (empty cells zero, cells outside dropped). On a CPU
    without gradients one compiled pass over the nodes writes each cell's running maxima straight
    into the map, in the comparisons the pooling makes (the same maps to the bit); otherwise the
    two steps.

    Shapes:
        x ``(N, F)``, pos ``(N, 3)``, batch ``(N,)`` -> ``(B, F, H, W)``.
    """
    if size <= 0:
        raise ValueError(f"size must be positive, got {size}")
    if not (compiled_for(x) and x.dtype in (torch.float32, torch.float64) and len(x)
            and not (torch.is_grad_enabled() and (x.requires_grad or pos.requires_grad))):
        pooled = voxel_max_pool(x, pos, batch, None, size)
        return to_dense(pooled.x, pooled.batch, pooled.cell, batch_size=batch_size, height=height, width=width)
    dense = x.new_zeros((batch_size, height, width, x.shape[1]))  # (B, H, W, F)
    if not _pool_cells(x.detach().contiguous().numpy(), pos.detach().contiguous().numpy(),
                       batch.to(torch.int64).contiguous().numpy(), float(size), dense.numpy()):
        raise ValueError("pooling needs non-negative x and y positions")
    return dense.permute(0, 3, 1, 2)


@numba.njit(**KERNEL)
def _pool_cells(x, pos, batch, size, dense):
    """:func:`max_pool_to_dense`'s pass: each node's features into its cell of ``dense (B, H, W, F)``
    by the running maxima of :func:`add_members` (a cell's first member meets ``-inf``); cells outside
    dropped. False (nothing written) where a position is negative."""
    n = len(x)
    col = np.empty(n, dtype=np.int64)
    row = np.empty(n, dtype=np.int64)
    for i in range(n):
        col[i] = np.int64(np.floor(pos[i, 0] / size))
        row[i] = np.int64(np.floor(pos[i, 1] / size))
        if col[i] < 0 or row[i] < 0:
            return False
    samples, height, width, channels = dense.shape
    flat = dense.reshape(samples * height * width, channels)
    seen = np.zeros(samples * height * width, dtype=np.bool_)
    for i in range(n):
        b, r, c = batch[i], row[i], col[i]
        if r >= height or c >= width or b >= samples:
            continue
        key = (b * height + r) * width + c
        if not seen[key]:
            seen[key] = True
            for k in range(channels):
                flat[key, k] = -np.inf
        for k in range(channels):  # a select, not a branch: the loop runs in vector lanes
            value, kept = x[i, k], flat[key, k]
            flat[key, k] = value if value > kept else kept
    return True


@numba.njit(**KERNEL)
def _write_cells(x, batch, cell, dense):
    """:func:`to_dense`'s writes: row ``c`` of ``x`` into ``dense[batch[c], row, column]``, cells outside dropped."""
    for c in range(len(x)):
        b, r, col = batch[c], cell[c, 0], cell[c, 1]
        if r < dense.shape[1] and col < dense.shape[2] and b < dense.shape[0]:
            dense[b, r, col, :] = x[c]


def recency_maps(events: torch.Tensor, batch: torch.Tensor, t_query: torch.Tensor, *, batch_size: int, stride: int,
                 height: int, width: int, taus_us: tuple[float, ...]) -> torch.Tensor:
    """How recently each ``stride``-pixel cell saw an event of each polarity, at the query time.

    For the latest event of polarity ``p`` in a cell, at ``t_last``: ``exp(-(t_query - t_last) / tau)``
    for each ``tau`` of ``taus_us``; 0 for a cell without such events. This depends on the
    query time, so it lives on the dense maps, never on the nodes; it can only grow as events
    arrive.

    Shapes:
        events ``(N, 4)`` x, y, t, p; batch ``(N,)``; t_query ``(B,)`` in the events' time origin ->
        ``(B, 2 len(taus_us), height, width)``, channels by (tau, polarity).
    """
    if len(events) == 0 or not taus_us:
        return events.new_zeros((batch_size, 2 * len(taus_us), height, width))
    latest = events.new_full((batch_size * 2 * height * width,), -math.inf)
    key = recency_cells(events, batch, stride=stride, height=height, width=width)
    latest = latest.scatter_reduce(0, key, events[:, 2].detach(), reduce="amax")
    return recency_from_latest(latest.view(batch_size, 2, height, width), t_query, taus_us)


def recency_cells(events: torch.Tensor, batch: torch.Tensor, *, stride: int, height: int, width: int) -> torch.Tensor:
    """``(N,)`` the flat index of each event's (sample, polarity, row, column) in the recency grid."""
    col = torch.div(events[:, 0], stride, rounding_mode="floor").long().clamp(0, width - 1)
    row = torch.div(events[:, 1], stride, rounding_mode="floor").long().clamp(0, height - 1)
    return ((batch * 2 + events[:, 3].long()) * height + row) * width + col


def recency_from_latest(latest: torch.Tensor, t_query: torch.Tensor, taus_us: tuple[float, ...]) -> torch.Tensor:
    """The recency maps of :func:`recency_maps` from the latest event time of each (sample,
    polarity, cell), ``latest (B, 2, h, w)`` (-inf where none), at ``t_query (B,)``."""
    since = t_query.to(latest.dtype)[:, None, None, None] - latest  # (B, 2, h, w)
    maps = [torch.where(torch.isfinite(since), torch.exp(-since.clamp(min=0) / tau), torch.zeros_like(since))
            for tau in taus_us]
    return torch.cat(maps, dim=1)


def recency_since(latest: torch.Tensor, height: int, width: int, start: float, t_query: float,
                  taus_us: tuple[float, ...]) -> torch.Tensor:
    """:func:`recency_from_latest` of one sample's latest times ``latest (2 height width,)`` at ``t_query``,
    a cell whose latest event is earlier than ``start`` counted as empty: ``(1, 2 len(taus_us), height,
    width)``. On a CPU one compiled pass; the times compared and subtracted in ``latest``'s dtype, as
    the tensor operations do."""
    if not (compiled_for(latest) and taus_us and latest.dtype in (torch.float32, torch.float64)):
        kept = torch.where(latest >= start, latest, torch.full_like(latest, -math.inf))
        query = torch.tensor([t_query], dtype=torch.float64, device=latest.device)
        return recency_from_latest(kept.view(1, 2, height, width), query, taus_us)
    array = latest.contiguous().numpy()
    kind = array.dtype.type
    out = np.empty(len(taus_us) * len(array), dtype=array.dtype)
    _recency(array, kind(start), kind(t_query), np.asarray(taus_us, dtype=array.dtype), out)
    return torch.from_numpy(out).view(1, 2 * len(taus_us), height, width)


@numba.njit(**KERNEL)
def _recency(latest, start, t_query, taus, out):
    """``out[a, p, cell] = exp(-max(t_query - latest[p, cell], 0) / taus[a])`` (flat), 0 where the latest
    time is before ``start`` or none (-inf)."""
    n = len(latest)
    for j in range(n):
        t = latest[j]
        if t >= start and np.isfinite(t):
            since = t_query - t
            if since < 0:
                since = since - since  # 0 in the times' dtype
            for a in range(len(taus)):
                out[a * n + j] = np.exp(-since / taus[a])
        else:
            for a in range(len(taus)):
                out[a * n + j] = 0


@numba.njit(**KERNEL)
def add_members(x, pos_sum, count, seen, features, pos, cell, src_cell, dst_cell):
    """Cells ``(S, C)`` of running member maxima ``x``, position sums and counts take new members
    ``features (M, C)`` at ``pos (M, 3)`` in cells ``cell (M,)``, in order (the sums as ``index_add_``
    adds them); returns the keys ``dst * S + src`` of the members' edge cells not in ``seen`` (``(S S,)``,
    then marked), each once, in the order first met."""
    for i in range(len(cell)):
        c = cell[i]
        for k in range(features.shape[1]):
            if features[i, k] > x[c, k]:
                x[c, k] = features[i, k]
        for k in range(pos.shape[1]):
            pos_sum[c, k] += pos[i, k]
        count[c] += 1
    size = len(count)
    new = np.empty(len(src_cell), dtype=np.int64)
    n = 0
    for e in range(len(src_cell)):
        key = dst_cell[e] * size + src_cell[e]
        if not seen[key]:
            seen[key] = True
            new[n] = key
            n += 1
    return new[:n]


@numba.njit(**KERNEL)
def latest_times(latest, events, stride, height, width):
    """:func:`recency_cells` and the running max of ``latest (2 height width,)`` over one sample's
    ``events (N, 4)`` (x, y, t, p) in one pass: each (polarity, cell) keeps its latest event time."""
    for i in range(len(events)):
        col = min(max(int(np.floor(events[i, 0] / stride)), 0), width - 1)
        row = min(max(int(np.floor(events[i, 1] / stride)), 0), height - 1)
        key = (int(events[i, 3]) * height + row) * width + col
        if events[i, 2] > latest[key]:
            latest[key] = events[i, 2]
