"""Streaming construction of the causal radius graph over a sliding time window.

Events arrive in batches of any size. Each batch gets its incoming edges from the events
already held (KD-trees built once per chunk of earlier events) and from the earlier events of
the batch itself; the edge set over any sequence of insertions equals :func:`radius_graph` on
all events. Chunks are merged like a binary counter (a chunk at most as large as the one
before it is merged into it), so a window holds O(log n) trees and each event is re-indexed
O(log n) times; chunks that lie wholly more than ``r`` in the past are not queried, and chunks
older than the window are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.graph.radius import as_numpy_pos, first_k, knn_within, neighbours_to_edges


@dataclass
class _Chunk:
    pos: np.ndarray  # (n, 3)
    ids: np.ndarray  # (n,) global node ids, ascending
    tree: cKDTree

    @property
    def z_max(self) -> float:
        return float(self.pos[-1, 2])

    @property
    def z_min(self) -> float:
        return float(self.pos[0, 2])


def _tree(pos: np.ndarray) -> cKDTree:
    return cKDTree(pos, balanced_tree=False, compact_nodes=False)


class StreamingGraph:
    """The causal radius graph of the last ``window`` (in the units of ``pos[:, 2]``) of events.

    Args:
        r: radius; k: most incoming edges per node (see :func:`radius_graph`).
        window: how far back in ``z = beta * t`` events are kept; must be >= ``r`` so that
            no dropped event could still be a neighbour.
        workers: threads for KD-tree queries (-1: all cores).

    Node ids are global and increase with each inserted event (the first event is 0).
    """

    def __init__(self, r: float, k: int, window: float, *, workers: int = -1):
        if r <= 0 or k <= 0:
            raise ValueError(f"r and k must be positive, got r={r}, k={k}")
        if window < r:
            raise ValueError(f"window ({window}) must be >= r ({r}): events still within r would be dropped")
        self.r, self.k, self.window, self.workers = float(r), int(k), float(window), workers
        self._chunks: list[_Chunk] = []
        self.num_inserted = 0
        self._last_z = -np.inf

    @property
    def num_nodes(self) -> int:
        """Events currently held (including some older than the window, until their chunk expires)."""
        return sum(len(c.ids) for c in self._chunks)

    def insert(self, pos) -> torch.Tensor:
        """Add events ``(M, 3)`` (sorted by ``z``, not earlier than any before) and return their
        incoming edges ``(2, E)`` in global ids, sorted by destination and then source."""
        points = as_numpy_pos(pos) if len(pos) else np.zeros((0, 3))
        if points.shape[1] != 3:
            raise ValueError(f"pos must have shape (M, 3), got {tuple(points.shape)}")
        m = len(points)
        if m == 0:
            return torch.zeros((2, 0), dtype=torch.int64)
        if np.any(points[1:, 2] < points[:-1, 2]) or points[0, 2] < self._last_z:
            raise ValueError("events must arrive in time order: pos[:, 2] may not decrease")
        ids = self.num_inserted + np.arange(m)
        # Earlier events of the batch itself (the causal query), then each recent chunk.
        own = _tree(points)
        idx, dist = knn_within(own, points, ids - self.num_inserted, self.k, self.r, workers=self.workers)
        idx = np.where(idx >= 0, idx + self.num_inserted, -1)
        candidates_idx, candidates_dist = [idx], [dist]
        for chunk in self._chunks:
            if points[0, 2] - chunk.z_max > self.r:
                continue  # wholly more than r in the past (differences, as distances are computed)
            c_idx, c_dist = knn_within(chunk.tree, points, None, self.k, self.r, tree_id=chunk.ids,
                                       workers=self.workers)
            candidates_idx.append(c_idx)
            candidates_dist.append(c_dist)
        if len(candidates_idx) > 1:
            all_idx, all_dist = np.concatenate(candidates_idx, axis=1), np.concatenate(candidates_dist, axis=1)
            order = np.argsort(all_dist, axis=1, kind="stable")
            all_idx, all_dist = np.take_along_axis(all_idx, order, axis=1), np.take_along_axis(all_dist, order, axis=1)
            idx, _ = first_k(all_dist, all_idx, all_idx >= 0, self.k)
        edges = neighbours_to_edges(idx, ids)
        self._add_chunk(_Chunk(points, ids, own))
        self.num_inserted += m
        self._last_z = float(points[-1, 2])
        self._chunks = [c for c in self._chunks if self._last_z - c.z_max <= self.window]
        return torch.from_numpy(edges)

    def _add_chunk(self, chunk: _Chunk) -> None:
        self._chunks.append(chunk)
        while len(self._chunks) >= 2 and len(self._chunks[-1].ids) >= len(self._chunks[-2].ids):
            last, before = self._chunks.pop(), self._chunks.pop()
            pos = np.concatenate([before.pos, last.pos])
            self._chunks.append(_Chunk(pos, np.concatenate([before.ids, last.ids]), _tree(pos)))
