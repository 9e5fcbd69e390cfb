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

import numba
import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.graph.compiled import KERNEL, CellChains
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


@numba.njit(**KERNEL)
def _split_arrival(arrival, start, count, k):
    """:func:`edges_after`'s pass over the arrival rows: the edges kept (``(2, E)``, from ``start``)
    and which nodes are searched again."""
    again = np.zeros(count, dtype=np.bool_)
    kept = np.empty((2, len(arrival)), dtype=np.int64)
    e, i = 0, 0
    while i < len(arrival):
        j, early = i, False
        while j < len(arrival) and arrival[j, 1] == arrival[i, 1]:
            early |= arrival[j, 0] < start
            j += 1
        node = arrival[i, 1] - start
        if early and j - i == k:
            again[node] = True
        else:
            for m in range(i, j):
                if arrival[m, 0] >= start:
                    kept[0, e], kept[1, e] = arrival[m, 0] - start, node
                    e += 1
        i = j
    return kept[:, :e], again


@numba.njit(**KERNEL)
def _merge_destinations(a, b):
    """Two edge sets ``(2, E)`` sorted by destination, no destination in both, as one sorted likewise."""
    out = np.empty((2, a.shape[1] + b.shape[1]), dtype=np.int64)
    i = j = e = 0
    while i < a.shape[1] or j < b.shape[1]:
        if j == b.shape[1] or (i < a.shape[1] and a[1, i] < b[1, j]):
            out[0, e], out[1, e] = a[0, i], a[1, i]
            i += 1
        else:
            out[0, e], out[1, e] = b[0, j], b[1, j]
            j += 1
        e += 1
    return out


def edges_after(arrival: torch.Tensor, start: int, count: int, k: int, search) -> torch.Tensor:
    """The causal edges ``(2, E)`` into nodes ``[start, start + count)`` once every node before
    ``start`` is gone, indices counted from ``start``, sorted by (destination, source) as every
    builder gives them, from the edges those nodes got on arrival (``arrival (E, 2)``: rows of
    (source, destination), sorted by (destination, source), every earlier node a candidate then).

    A node's arrival edges come from its ``k`` nearest earlier nodes within the radius, or from all
    of them when there are fewer. With fewer than ``k``, its edges from ``start`` on are those of
    them from ``start`` on; with ``k``, none from before ``start``, they are still its ``k`` nearest.
    Only a node with ``k`` edges, some from before ``start``, may now reach a candidate that was
    further than its ``k``: ``search(query)`` (``query (count,)`` bool marks those) finds their edges
    again among the nodes from ``start`` (``(2, E')`` counted from ``start``, sorted likewise)."""
    kept, again = _split_arrival(arrival.cpu().numpy(), int(start), int(count), int(k))
    if again.any():
        kept = _merge_destinations(kept, search(torch.from_numpy(again)).cpu().numpy())
    return torch.from_numpy(kept)
