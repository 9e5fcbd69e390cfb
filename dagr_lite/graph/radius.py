"""The causal radius graph of an event cloud (docs/design.md, "The event graph").

Node ``i`` is at ``pos_i = (x, y, beta * t)``. The edge ``j -> i`` exists iff ``j`` is earlier
than ``i`` (smaller index: events are sorted by time, ties by index), ``|pos_i - pos_j| <= r``,
and ``j`` is among the ``k`` nearest such earlier nodes (ties by smaller index). Edges never
cross samples. A node's incoming edges are fixed when it arrives, which is what makes
streaming inference exact.

Neighbours come from scipy ``cKDTree`` queries. A query returns the nearest nodes whatever
their time, so for the causal graph it asks for more than ``k`` and keeps the earlier ones;
rows where that was not enough to be sure of the ``k`` nearest earlier ones are asked again
with a larger count. Distances are scipy's (float64), for the radius test and the ordering.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

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


def radius_graph(pos, r: float, k: int, batch=None, *, workers: int = -1) -> torch.Tensor:
    """Causal radius graph with at most ``k`` nearest earlier neighbours per node.

    Args:
        pos: ``(N, 3)`` positions ``(x, y, beta * t)``, sorted by time within each sample.
        r: radius, in the units of ``pos``.
        k: most incoming edges per node (the nearest earlier ones; ties by smaller index).
        batch: ``(N,)`` sample of each node, sorted; no edge crosses samples.
        workers: threads for the KD-tree queries (-1: all cores).

    Returns:
        ``edge_index`` ``(2, E)`` int64, sources in row 0 and destinations in row 1, sorted by
        destination and then source; no self-loops.

    Shapes:
        pos ``(N, 3)``, batch ``(N,)`` -> edge_index ``(2, E)`` with ``E <= N * k``.
    """
    if r <= 0 or k <= 0:
        raise ValueError(f"r and k must be positive, got r={r}, k={k}")
    device = pos.device if isinstance(pos, torch.Tensor) else torch.device("cpu")
    points = as_numpy_pos(pos)
    batch_np = None
    if batch is not None:
        batch_np = batch.detach().cpu().numpy() if isinstance(batch, torch.Tensor) else np.asarray(batch)
    parts = []
    for part in sample_slices(batch_np, len(points)):  # one tree per sample: no edge can cross samples
        sample = points[part]
        if len(sample) < 2:
            continue
        ids = np.arange(len(sample))
        tree = cKDTree(sample, balanced_tree=False, compact_nodes=False)
        idx, _ = knn_within(tree, sample, ids, k, r, workers=workers)
        parts.append(neighbours_to_edges(idx, ids) + part.start)
    edges = np.concatenate(parts, axis=1) if parts else np.zeros((2, 0), dtype=np.int64)
    return torch.from_numpy(edges).to(device)

