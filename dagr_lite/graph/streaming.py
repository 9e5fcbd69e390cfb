"""Streaming construction of the causal radius graph, one batch of events at a time.

Events arrive in batches of any size, in time order. A later event can only link to events
within ``r`` of it, so within ``r`` in ``z = beta * t`` of the latest one: the builder keeps
just those (the "recent" events), and the edge set over any sequence of insertions equals
:func:`~dagr_lite.graph.radius.radius_graph` on all events.

Two backends give the same edges. ``compiled`` (the default) keeps the recent events in the
cell chains of :class:`~dagr_lite.graph.compiled.CellChains`: an insertion costs the new events'
neighbourhoods, whatever the history. ``kdtree`` indexes each batch together with the recent
events in one KD-tree and asks the causal query of the batch builder: ``O((R + M) log(R + M))``
for ``R`` recent and ``M`` new events; it stays as the reference the tests compare with.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.graph.compiled import CellChains
from dagr_lite.graph.radius import as_numpy_pos, knn_within, neighbours_to_edges

# Events are kept this much beyond r in z, so that rounding can never drop a possible neighbour.
KEEP_MARGIN = 1e-6


class StreamingGraph:
    """The causal radius graph of a stream of events, built as they arrive.

    Args:
        r: radius; k: most incoming edges per node (see :func:`radius_graph`).
        workers: threads for the ``kdtree`` backend's queries (-1: all cores).
        backend: ``compiled`` (cell chains, the default) or ``kdtree`` (the reference).

    Node ids are global and increase with each inserted event (the first event is 0).
    """

    BACKENDS = ("compiled", "kdtree")

    def __init__(self, r: float, k: int, *, workers: int = -1, backend: str = "compiled"):
        if r <= 0 or k <= 0:
            raise ValueError(f"r and k must be positive, got r={r}, k={k}")
        if backend not in self.BACKENDS:
            raise ValueError(f"backend must be one of {self.BACKENDS}, got {backend!r}")
        self.r, self.k, self.workers, self.backend = float(r), int(k), workers, backend
        self._chains = CellChains(self.r, self.k) if backend == "compiled" else None
        self._pos = np.zeros((0, 3))  # the recent events: those a later event may link to
        self._ids = np.zeros(0, dtype=np.int64)
        self.num_inserted = 0
        self._last_z = -np.inf

    @property
    def num_nodes(self) -> int:
        """Events currently held: those within ``r`` (in z) of the latest (the compiled backend
        lets them go when the next batch arrives)."""
        return self._chains.held if self._chains is not None else len(self._ids)

    def insert(self, pos) -> torch.Tensor:
        """Add events ``(M, 3)`` (sorted by ``z``, not earlier than any before) and return their
        incoming edges ``(2, E)`` in global ids, sorted by destination and then source."""
        points = as_numpy_pos(pos) if len(pos) else np.zeros((0, 3))
        if points.shape[1] != 3:
            raise ValueError(f"pos must have shape (M, 3), got {tuple(points.shape)}")
        m = len(points)
        if m == 0:
            return torch.zeros((2, 0), dtype=torch.int64)
        if self._chains is not None:
            edges = self._chains.insert(points)
            self.num_inserted += m
            return torch.from_numpy(edges)
        if np.any(points[1:, 2] < points[:-1, 2]) or points[0, 2] < self._last_z:
            raise ValueError("events must arrive in time order: pos[:, 2] may not decrease")
        ids = self.num_inserted + np.arange(m)
        held = np.concatenate([self._pos, points])
        held_ids = np.concatenate([self._ids, ids])
        tree = cKDTree(held, balanced_tree=False, compact_nodes=False)
        idx, _ = knn_within(tree, points, ids, self.k, self.r, tree_id=held_ids, workers=self.workers)
        edges = neighbours_to_edges(idx, ids)
        self.num_inserted += m
        self._last_z = float(points[-1, 2])
        first = int(np.searchsorted(held[:, 2], self._last_z - self.r * (1 + KEEP_MARGIN) - KEEP_MARGIN, side="left"))
        self._pos, self._ids = held[first:], held_ids[first:]
        return torch.from_numpy(edges)
