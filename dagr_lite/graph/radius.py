"""The causal radius graph of an event cloud (docs/design.md, "The event graph").

Node ``i`` is at ``pos_i = (x, y, beta * t)``. The edge ``j -> i`` exists iff ``j`` is earlier
than ``i`` (smaller index: events are sorted by time, ties by index), ``|pos_i - pos_j| <= r``,
and ``j`` is among the ``k`` nearest such earlier nodes (ties by smaller index). Edges never
cross samples. A node's incoming edges are fixed when it arrives, which is what makes
streaming inference exact.

Neighbours come from a scipy ``cKDTree``. When a cheap bound on the number of pairs within
``r`` is small (:func:`pairs_bound`), the tree lists every pair within ``r`` at once
(``query_pairs``) and each node keeps its ``k`` nearest earlier partners, ranked by one
integer sort (:func:`knn_from_pairs`). Otherwise (dense
clouds: the memory of all pairs is not bounded) it runs ``k``-nearest queries: a query returns
the nearest nodes whatever their time, so for the causal graph it asks for more than ``k`` and keeps the earlier ones; rows where that was not
enough to be sure of the ``k`` nearest earlier ones are asked again with a larger count
(:func:`knn_within`). Both give the same edges: distances are float64, summed over the axes
in order as scipy sums them, for the radius test and the ordering.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.graph import compiled

PAIR_BUDGET = 1 << 23  # most pairs within r (bounded by pairs_bound) for the all-pairs path
ROW_CHUNK = 1 << 14  # query rows per pass: bounds the (rows, ask) candidate matrices
CANDIDATE_BUDGET = 1 << 22  # most (row, candidate) pairs per query pass, when ties force large asks


def as_numpy_pos(pos) -> np.ndarray:
    """``pos`` as a C-contiguous float64 ``(N, D)`` array, checked."""
    pos = pos.detach().cpu().numpy() if isinstance(pos, torch.Tensor) else np.asarray(pos)
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise ValueError(f"pos must have shape (N, 3) (or (N, 2)), got {tuple(pos.shape)}")
    if not np.all(np.isfinite(pos)):
        raise ValueError("pos holds non-finite values")
    return pos


def sample_slices(batch: np.ndarray | None, n: int) -> list[slice]:
    """The contiguous index range of each sample (one range without ``batch``)."""
    if batch is None:
        return [slice(0, n)]
    if batch.shape != (n,):
        raise ValueError(f"batch must have shape ({n},), got {batch.shape}")
    if np.any(batch[1:] < batch[:-1]):
        raise ValueError("batch must be sorted (the events of each sample contiguous, in sample order)")
    bounds = np.flatnonzero(np.r_[True, batch[1:] != batch[:-1], True])
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]


def first_k(dist: np.ndarray, idx: np.ndarray, ok: np.ndarray, k: int):
    """Per row, the ``k`` best accepted candidates by (distance, index).

    ``dist`` and ``idx`` are ``(M, A)`` with each row sorted by distance (ties in any order).
    Returns ``(M, k)`` matrices of indices (``-1`` where a row has fewer) and distances (inf).
    """
    m, a = dist.shape
    # Accepted entries first, in their distance order; the rest become (inf, max id).
    order = np.argsort(~ok, axis=1, kind="stable")
    ok = np.take_along_axis(ok, order, axis=1)
    dist = np.where(ok, np.take_along_axis(dist, order, axis=1), np.inf)
    idx = np.where(ok, np.take_along_axis(idx, order, axis=1), np.iinfo(np.int64).max)
    tied = np.any((dist[:, 1:] == dist[:, :-1]) & ok[:, 1:], axis=1)
    if tied.any():  # order equal distances by id (rare outside grid-aligned data)
        rows = np.flatnonzero(tied)
        order = np.lexsort((idx[rows], dist[rows]), axis=-1)
        dist[rows] = np.take_along_axis(dist[rows], order, axis=1)
        idx[rows] = np.take_along_axis(idx[rows], order, axis=1)
    if a < k:
        dist = np.pad(dist, ((0, 0), (0, k - a)), constant_values=np.inf)
        idx = np.pad(idx, ((0, 0), (0, k - a)), constant_values=np.iinfo(np.int64).max)
    dist, idx = dist[:, :k], idx[:, :k]
    idx = np.where(np.isfinite(dist), idx, -1)
    return idx, dist


def knn_within(tree: cKDTree, query: np.ndarray, query_id: np.ndarray | None, k: int, r: float, *,
               tree_id: np.ndarray | None = None, workers: int = -1):
    """For each query row, the ``k`` nearest tree points within ``r`` by (distance, id).

    With ``query_id`` given, only tree points with a smaller id count (the causal case; the
    tree's ids are ``tree_id``, by default the point positions). Exact: a row is kept only once
    every point that could belong to its answer has been seen.

    Returns ``(M, k)`` int64 ids (``-1`` for none) and float64 distances (``inf`` for none).
    """
    n_tree = tree.n
    out_idx = np.full((len(query), k), -1, dtype=np.int64)
    out_dist = np.full((len(query), k), np.inf)
    if n_tree == 0 or len(query) == 0:
        return out_idx, out_dist
    causal = query_id is not None
    pending = [(np.arange(start, min(len(query), start + ROW_CHUNK)), min(n_tree, 2 * k + 2 if causal else k))
               for start in range(0, len(query), ROW_CHUNK)]
    while pending:
        rows, ask = pending.pop()
        if len(rows) * ask > CANDIDATE_BUDGET and len(rows) > 1:  # many exact ties: keep memory bounded
            per_pass = max(1, CANDIDATE_BUDGET // ask)
            pending += [(rows[i:i + per_pass], ask) for i in range(0, len(rows), per_pass)]
            continue
        if len(rows):
            # scipy keeps distances strictly below the bound: search a hair beyond r, keep d <= r.
            dist, nbr = tree.query(query[rows], k=ask, distance_upper_bound=r * (1 + 1e-9), workers=workers)
            dist, nbr = dist.reshape(len(rows), ask), nbr.reshape(len(rows), ask)  # (M, ask)
            found = (nbr < n_tree) & (dist <= r)
            ids = nbr if tree_id is None else tree_id[np.where(found, nbr, 0)]
            ok = found & (ids < query_id[rows][:, None]) if causal else found
            # Complete: the search ran out of points within r, or the farthest point returned is
            # beyond the k-th accepted one (so nothing unseen can enter or tie).
            count = ok.sum(axis=1)
            kth = np.full(len(rows), np.inf)
            enough = count >= k
            if enough.any():
                kth[enough] = np.partition(np.where(ok[enough], dist[enough], np.inf), k - 1, axis=1)[:, k - 1]
            complete = (nbr[:, -1] == n_tree) | (ask == n_tree) | (enough & (dist[:, -1] > kth))
            done = rows[complete]
            out_idx[done], out_dist[done] = first_k(dist[complete], ids[complete], ok[complete], k)
            if not complete.all():
                pending.append((rows[~complete], min(n_tree, 2 * ask)))
    return out_idx, out_dist


def neighbours_to_edges(idx: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(M, k)`` neighbour ids of destinations ``dst`` -> ``(2, E)`` edges sorted by (dst, src)."""
    src = np.sort(np.where(idx >= 0, idx, np.iinfo(np.int64).max), axis=1)  # (M, k)
    valid = src != np.iinfo(np.int64).max
    return np.stack([src[valid], np.repeat(dst, valid.sum(axis=1))])


def pairs_bound(points: np.ndarray, r: float) -> float:
    """An upper bound on the ordered pairs (self-pairs included) of ``points`` within ``r``.

    In cells of side ``r`` a point's partners lie in the ``3^D`` cells around its own (27 in 3-D),
    so the pairs number at most ``sum_c n_c * sum_{c' near c} n_c' <= 3^D * sum_c n_c^2``.
    """
    if len(points) == 0:
        return 0.0
    cells = np.floor((points - points.min(axis=0)) / r).astype(np.int64)  # (N, D)
    span = cells.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0 ** 62:  # cell ids would overflow: count the rows
        _, counts = np.unique(cells, axis=0, return_counts=True)
    else:
        key = cells[:, 0]
        for axis in range(1, cells.shape[1]):
            key = key * span[axis] + cells[:, axis]
        _, counts = np.unique(key, return_counts=True)
    return 3.0 ** cells.shape[1] * float(np.dot(counts.astype(np.float64), counts))


def knn_from_pairs(tree: cKDTree, points: np.ndarray, k: int, r: float) -> np.ndarray:
    """Causal edges ``(2, E)`` sorted by (dst, src): per node its ``k`` nearest earlier nodes
    within ``r`` by (distance, index), from every pair within ``r`` of the tree of ``points``.

    The pairs are ranked by one integer sort (torch's radix sort) of the keys
    ``dst | q | src``, where ``q`` is the distance quantised to the bits left over. Quantising is
    monotone, so it can merge two distances but never swap them; the rare runs of one
    (dst, q) holding distinct distances are reordered exactly by (distance, index). The kept
    edges are then ordered by one sort of ``dst * n + src``. Exact for any ``n < 2^31``.
    """
    n = len(points)
    # scipy keeps pairs at most its bound: search a hair beyond r, keep d <= r.
    pairs = tree.query_pairs(r * (1 + 1e-9), output_type="ndarray")  # (P, 2), first < second
    src, dst = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    columns = [np.ascontiguousarray(points[:, axis]) for axis in range(points.shape[1])]
    diff = columns[0][src] - columns[0][dst]
    squared = diff * diff
    for column in columns[1:]:  # summed over the axes in order, as scipy sums them
        diff = column[src] - column[dst]
        squared += diff * diff
    dist = np.sqrt(squared)
    within = dist <= r
    if not within.all():
        src, dst, dist = src[within], dst[within], dist[within]
    id_bits = max(1, (n - 1).bit_length())
    q_bits = min(52, max(0, 62 - 2 * id_bits))  # at most float64's mantissa: 2^q_bits - 1 is exact
    top = (1 << q_bits) - 1
    dst_shift, src_mask = q_bits + id_bits, (1 << id_bits) - 1  # key = dst << dst_shift | q << id_bits | src
    quantised = np.minimum(np.floor(dist * (top / r)), top).astype(np.int64)  # in [0, 2^q_bits)
    key, order = torch.sort(torch.from_numpy((dst << dst_shift) | (quantised << id_bits) | src))
    key, dist = key.numpy(), dist[order.numpy()]
    group = key >> id_bits  # (dst, q)
    merged = (group[1:] == group[:-1]) & (dist[1:] != dist[:-1])
    if merged.any():  # distinct distances in one quantum: order those runs by (distance, index)
        run = np.cumsum(np.r_[True, group[1:] != group[:-1]]) - 1
        rows = np.flatnonzero(np.isin(run, run[1:][merged]))
        key[rows] = key[rows][np.lexsort((key[rows] & src_mask, dist[rows], run[rows]))]
    dst = key >> dst_shift
    rank = np.arange(len(key)) - np.searchsorted(dst, dst, side="left")
    kept = key[rank < k]
    edge_key = torch.sort(torch.from_numpy((kept >> dst_shift) * n + (kept & src_mask)))
    edge_key = edge_key.values.numpy()
    return np.stack([edge_key % n, edge_key // n])


BACKENDS = ("auto", "compiled", "kdtree", "torch")


def radius_graph(pos, r: float, k: int, batch=None, *, workers: int = -1, backend: str = "auto",
                 query=None) -> torch.Tensor:
    """Causal radius graph with at most ``k`` nearest earlier neighbours per node.

    Args:
        pos: ``(N, 3)`` positions ``(x, y, beta * t)``, sorted by time within each sample.
        r: radius, in the units of ``pos``.
        k: most incoming edges per node (the nearest earlier ones; ties by smaller index).
        batch: ``(N,)`` sample of each node, sorted; no edge crosses samples.
        workers: threads for the KD-tree queries (-1: all cores).
        backend: ``compiled`` (cell chains compiled with numba, on the CPU; see
            :mod:`dagr_lite.graph.compiled`), ``kdtree`` (scipy, on the CPU), ``torch`` (pure torch,
            on ``pos``'s device; see :func:`radius_graph_torch`) or ``auto`` (torch for a CUDA
            tensor, else compiled). All give the identical edge set.
        query: ``(N,)`` bool, or None: only the edges into the nodes it marks (every node still a
            candidate source); the compiled backend searches only for those.

    Returns:
        ``edge_index`` ``(2, E)`` int64, sources in row 0 and destinations in row 1, sorted by
        destination and then source; no self-loops. On ``pos``'s device.

    Shapes:
        pos ``(N, 3)``, batch ``(N,)`` -> edge_index ``(2, E)`` with ``E <= N * k``.
    """
    if r <= 0 or k <= 0:
        raise ValueError(f"r and k must be positive, got r={r}, k={k}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    on_cuda = isinstance(pos, torch.Tensor) and pos.is_cuda
    if query is not None:
        query = query.detach().cpu().numpy() if isinstance(query, torch.Tensor) else np.asarray(query)
        if query.shape != (len(pos),) or query.dtype != np.bool_:
            raise ValueError(f"query must be ({len(pos)},) bool (one mark per node), got {query.shape} {query.dtype}")
        if backend == "kdtree" or backend == "torch" or (backend == "auto" and on_cuda) or pos.shape[1] != 3:
            edges = radius_graph(pos, r, k, batch, workers=workers, backend=backend)
            return edges[:, torch.from_numpy(query).to(edges.device)[edges[1]]]
    if backend == "torch" or (backend == "auto" and on_cuda):
        return radius_graph_torch(pos, r, k, batch)
    device = pos.device if isinstance(pos, torch.Tensor) else torch.device("cpu")
    points = as_numpy_pos(pos)
    batch_np = None
    if batch is not None:
        batch_np = batch.detach().cpu().numpy() if isinstance(batch, torch.Tensor) else np.asarray(batch)
    slices = sample_slices(batch_np, len(points))
    if backend != "kdtree" and points.shape[1] == 3:
        bounds = np.array([0] + [part.stop for part in slices], dtype=np.int64)
        return torch.from_numpy(compiled.build(points, bounds, r, k, workers=workers, query=query)).to(device)
    parts = []
    for part in slices:  # one tree per sample: no edge can cross samples
        sample = points[part]
        if len(sample) < 2:
            continue
        tree = cKDTree(sample, balanced_tree=False, compact_nodes=False)
        if pairs_bound(sample, r) <= PAIR_BUDGET:
            parts.append(knn_from_pairs(tree, sample, k, r) + part.start)
        else:
            ids = np.arange(len(sample))
            idx, _ = knn_within(tree, sample, ids, k, r, workers=workers)
            parts.append(neighbours_to_edges(idx, ids) + part.start)
    edges = np.concatenate(parts, axis=1) if parts else np.zeros((2, 0), dtype=np.int64)
    return torch.from_numpy(edges).to(device)


# Candidate (node, neighbour) pairs the torch backend holds at once: bounds its memory.
TORCH_PAIR_BUDGET = 1 << 23
# Margins that keep every possible neighbour among the candidates whatever the rounding; the
# distance test itself is exact.
CELL_MARGIN, TIME_MARGIN = 1e-9, 1e-9


def radius_graph_torch(pos, r: float, k: int, batch=None) -> torch.Tensor:
    """:func:`radius_graph` in pure torch, on ``pos``'s device (CPU or CUDA), with the same edges.

    Nodes are bucketed into ``r``-sized (x, y) cells. For node ``i``, the candidates in each of the
    nine cells around its own are one contiguous run of that cell's nodes (kept in index order):
    those with index in ``[first index at z >= z_i - r, i)``, found with ``searchsorted``.
    Distances are ``sqrt(dx^2 + dy^2 + dz^2)`` in float64, as scipy computes them; the ``k``
    nearest within ``r`` are kept, ties by index. Candidates are processed in chunks of nodes
    holding at most :data:`TORCH_PAIR_BUDGET` pairs.
    """
    points = torch.as_tensor(pos).detach().to(torch.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"pos must have shape (N, 3), got {tuple(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError("pos holds non-finite values")
    device, n = points.device, len(points)
    if batch is None:
        bounds = [0, n]
    else:
        batch = torch.as_tensor(batch, device=device)
        if batch.shape != (n,):
            raise ValueError(f"batch must have shape ({n},), got {tuple(batch.shape)}")
        if n and bool((batch[1:] < batch[:-1]).any()):
            raise ValueError("batch must be sorted (the events of each sample contiguous, in sample order)")
        change = torch.nonzero(batch[1:] != batch[:-1]).flatten() + 1 if n else batch.new_zeros(0)
        bounds = [0, *change.tolist(), n]
    parts = [_sample_graph_torch(points[a:b], r, k) + a for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= 2]
    return torch.cat(parts, dim=1) if parts else torch.zeros((2, 0), dtype=torch.int64, device=device)


def _sample_graph_torch(points: torch.Tensor, r: float, k: int) -> torch.Tensor:
    """The causal graph of one sample's time-sorted ``points (n, 3)``: ``(2, E)`` local ids."""
    device, n = points.device, len(points)
    if bool((points[1:, 2] < points[:-1, 2]).any()):
        raise ValueError("pos must be sorted by time (z) within each sample")
    size = r * (1 + CELL_MARGIN)
    cell_xy = torch.floor(points[:, :2] / size).to(torch.int64)  # (n, 2)
    cell_xy -= cell_xy.min(dim=0).values - 1  # >= 1: neighbours at -1 stay >= 0
    width = int(cell_xy[:, 0].max()) + 2
    cell = cell_xy[:, 1] * width + cell_xy[:, 0]  # (n,)
    ids = torch.arange(n, device=device)
    key = cell * n + ids  # cell, then index: strictly increasing once sorted
    sorted_key, order = torch.sort(key)
    first = torch.searchsorted(points[:, 2].contiguous(), points[:, 2] - r * (1 + TIME_MARGIN) - TIME_MARGIN)
    offsets = torch.tensor([dy * width + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)], device=device)
    neighbour_cell = cell[:, None] + offsets[None, :]  # (n, 9)
    lo = torch.searchsorted(sorted_key, neighbour_cell * n + first[:, None])  # (n, 9)
    hi = torch.searchsorted(sorted_key, neighbour_cell * n + ids[:, None])  # index < i
    count = (hi - lo).clamp(min=0)
    per_node = count.sum(dim=1)  # (n,)
    edges, start = [], 0
    while start < n:  # chunks of nodes with at most TORCH_PAIR_BUDGET candidate pairs
        cum = torch.cumsum(per_node[start:], 0)
        stop = start + max(1, int(torch.searchsorted(cum, torch.tensor(TORCH_PAIR_BUDGET, device=device))))
        edges.append(_nearest_in_chunk(points, order, lo[start:stop], count[start:stop], start, r, k))
        start = stop
    return torch.cat(edges, dim=1)


def _nearest_in_chunk(points, order, lo, count, first_node: int, r: float, k: int) -> torch.Tensor:
    """Edges into nodes ``first_node ...`` from their candidate runs ``[lo, lo + count)`` of ``order``."""
    device = points.device
    flat_count = count.flatten()
    total = int(flat_count.sum())
    if total == 0:
        return torch.zeros((2, 0), dtype=torch.int64, device=device)
    run = torch.repeat_interleave(torch.arange(len(flat_count), device=device), flat_count)
    run_start = torch.cumsum(flat_count, 0) - flat_count
    within = torch.arange(total, device=device) - run_start[run]
    src = order[lo.flatten()[run] + within]  # (T,)
    dst = first_node + torch.div(run, count.shape[1], rounding_mode="floor")  # (T,)
    diff = points[dst] - points[src]
    squared = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]
    # torch's vectorised float64 square root on a CPU may be an ulp off, which breaks ties unlike the
    # other builders: numpy's there is correctly rounded, as a CUDA GPU's is
    dist = torch.from_numpy(np.sqrt(squared.numpy())) if squared.device.type == "cpu" else torch.sqrt(squared)
    keep = dist <= r
    src, dst, dist = src[keep], dst[keep], dist[keep]
    # Sort by (dst, dist, src): stable sorts from the last key to the first.
    step = torch.sort(src, stable=True).indices
    src, dst, dist = src[step], dst[step], dist[step]
    step = torch.sort(dist, stable=True).indices
    src, dst, dist = src[step], dst[step], dist[step]
    step = torch.sort(dst, stable=True).indices
    src, dst = src[step], dst[step]
    rank = torch.arange(len(dst), device=device)
    if len(dst):
        new_row = torch.ones(len(dst), dtype=torch.bool, device=device)
        new_row[1:] = dst[1:] != dst[:-1]
        row_start = torch.cummax(torch.where(new_row, rank, torch.zeros_like(rank)), 0).values
        rank = rank - row_start
    src, dst = src[rank < k], dst[rank < k]
    final = torch.sort(dst * len(points) + src).indices  # by (dst, src)
    return torch.stack([src[final], dst[final]])
