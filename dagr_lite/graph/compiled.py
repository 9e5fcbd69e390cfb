"""The causal radius graph from cell chains, compiled with numba (docs/design.md, "The event graph").

Events are binned into square cells of side ``s`` in (x, y): one pixel wherever the grid fits
(:data:`GRID_BUDGET`). Each event links to the previous event of its cell (``prev``) and each
cell to its latest event (``last``), so a cell's events form a chain back in time. Node ``i``
(events taken in index order, sorted by time) walks, for every cell offset that can hold a
point within ``r`` (nearest offsets first), its chain from the latest event before ``i`` back
until the time gap alone exceeds ``r``, tests the exact distance and keeps the ``k`` nearest by
(distance, index); then ``i`` joins its own cell's chain. Two bounds stop the walk early without
changing the answer once ``k`` are held: a chain ends where its time gap alone is beyond the
``k``-th distance, and the offsets end where their nearest possible point is.

The distance is computed as the KD-tree builder computes it (float64, ``sqrt(dx^2 + dy^2 +
dz^2)`` summed in that order) and every bound errs towards looking further, so the edge set is
the KD-tree's, ties included. Work per event is the cells around it plus the events in its
reach, independent of history: streaming insertion (:class:`CellChains`) costs what arrives.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

CELL_SIZE = 1.0
GRID_BUDGET = 1 << 24  # most cells in the grid; wider clouds get cells of more than a pixel
PARALLEL_MIN = 1 << 15  # fewer events than this build on one thread
REACH_MARGIN = 1e-9  # relative: the time gap beyond which no event can be within r, with room for rounding
OFFSET_MARGIN = 1e-9  # relative: the nearest possible distance of a cell offset, rounded down by this
NODE = np.dtype([("x", np.float64), ("y", np.float64), ("z", np.float64), ("prev", np.int64)])  # one cache line half


def cell_offsets(r: float, s: float, integer: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell offsets ``(a, b)`` that can hold a point within ``r``, nearest first.

    With ``integer`` (every x, y an integer and ``s == 1``) points sit on their cell's corner, so
    an offset's nearest point is ``sqrt(a^2 + b^2)`` away, computed as the distance is. Otherwise
    it is ``s * sqrt(max(|a| - 1, 0)^2 + max(|b| - 1, 0)^2)``, lowered by :data:`OFFSET_MARGIN`.
    Returns ``a``, ``b`` (int64) and those nearest distances (float64), sorted by distance.
    """
    reach = int(math.floor(r / s)) + (0 if integer else 1)
    a, b = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="xy")
    a, b = a.ravel(), b.ravel()
    if integer:
        nearest = np.sqrt((a * a + b * b).astype(np.float64))
        keep = nearest <= r * (1 + OFFSET_MARGIN)
    else:
        ga, gb = np.maximum(np.abs(a) - 1, 0), np.maximum(np.abs(b) - 1, 0)
        nearest = s * np.sqrt((ga * ga + gb * gb).astype(np.float64)) * (1 - OFFSET_MARGIN)
        keep = nearest <= r
    order = np.lexsort((a[keep], b[keep], nearest[keep]))
    return a[keep][order].astype(np.int64), b[keep][order].astype(np.int64), nearest[keep][order]


class Grid:
    """Cells of side ``s`` over ``[lo_xy, hi_xy]`` (plus ``slack`` cells), with a border of ``pad``
    cells so that every offset of :func:`cell_offsets` from a point's own cell stays inside.

    ``frame`` is what the kernels take: ``[s, x0, y0, width, inner x0, inner y0, inner x1, inner
    y1]``, the inner box being the cells a point may occupy.
    """

    def __init__(self, lo_xy, hi_xy, r: float, integer: bool, slack: int = 0):
        s = CELL_SIZE
        span = np.floor(np.asarray(hi_xy, dtype=np.float64)) - np.floor(np.asarray(lo_xy, dtype=np.float64)) + 1
        while float((span[0] / s + 2 * (slack + r / s + 2)) * (span[1] / s + 2 * (slack + r / s + 2))) > GRID_BUDGET:
            s *= 2.0
        self.s, self.integer = s, bool(integer and s == 1.0)
        a, b, self.nearest = cell_offsets(r, s, self.integer)
        self.pad = int(max(np.abs(a).max(), np.abs(b).max()))
        inner_lo = [int(math.floor(v / s)) - slack for v in lo_xy]
        inner_hi = [int(math.floor(v / s)) + slack for v in hi_xy]
        self.x0, self.y0 = inner_lo[0] - self.pad, inner_lo[1] - self.pad
        self.width = inner_hi[0] + self.pad - self.x0 + 1
        self.height = inner_hi[1] + self.pad - self.y0 + 1
        self.offsets = b * self.width + a
        self.frame = np.array([s, self.x0, self.y0, self.width, *inner_lo, *inner_hi], dtype=np.float64)

    @property
    def size(self) -> int:
        return self.width * self.height


@numba.njit(cache=True, nogil=True)
def _cell(x, y, frame):
    s = frame[0]
    return (int(math.floor(y / s)) - int(frame[2])) * int(frame[3]) + int(math.floor(x / s)) - int(frame[1])


@numba.njit(cache=True, nogil=True, inline="always")
def _nearest_earlier(i, mask, lo, nodes, last, home, offsets, nearest, r, reach, k, best_d, best_j):
    """The ``k`` nearest nodes ``lo <= j < i`` within ``r`` into ``best_d`` / ``best_j`` (by
    distance, then index); returns how many. ``nodes`` is indexed by ``id & mask``."""
    node = nodes[i & mask]
    xi, yi, zi = node.x, node.y, node.z
    count = 0
    for o in range(len(offsets)):
        if count == k and nearest[o] > best_d[k - 1]:
            break  # this offset and every later one lie beyond the k-th distance
        j = last[np.uint64(home + offsets[o])]  # unsigned: no negative-index wrap-around in the loop
        while j >= lo:
            other = nodes[np.uint64(j & mask)]
            dz = zi - other.z
            if dz > reach:
                break  # the chain runs back in time: the rest are further still
            dz2 = dz * dz
            if count == k and math.sqrt(dz2) > best_d[k - 1]:
                break  # the time gap alone is beyond the k-th distance
            dx = xi - other.x
            dy = yi - other.y
            d = math.sqrt(dx * dx + dy * dy + dz2)
            if d <= r and (count < k or d < best_d[k - 1] or (d == best_d[k - 1] and j < best_j[k - 1])):
                m = count if count < k else k - 1
                while m > 0 and (best_d[m - 1] > d or (best_d[m - 1] == d and best_j[m - 1] > j)):
                    best_d[m] = best_d[m - 1]
                    best_j[m] = best_j[m - 1]
                    m -= 1
                best_d[m] = d
                best_j[m] = j
                if count < k:
                    count += 1
            j = other.prev
    return count


@numba.njit(cache=True, nogil=True)
def _sort_ids(best_j, count):
    for m in range(1, count):
        value = best_j[m]
        n = m
        while n > 0 and best_j[n - 1] > value:
            best_j[n] = best_j[n - 1]
            n -= 1
        best_j[n] = value


@numba.njit(cache=True, nogil=True)
def link(start, stop, lo, mask, nodes, last, frame, offsets, nearest, r, reach, k, edges, e):
    """Nodes ``start <= i < stop`` in order: their edges written to ``edges[:, e:]``, then each joins
    its cell's chain. Returns the new ``e``."""
    best_d = np.empty(k, dtype=np.float64)
    best_j = np.empty(k, dtype=np.int64)
    for i in range(start, stop):
        p = i & mask
        while lo < i and nodes[lo & mask].z < nodes[p].z - reach:
            lo += 1  # out of reach from here on: a chain stops there without loading it
        home = _cell(nodes[p].x, nodes[p].y, frame)
        count = _nearest_earlier(i, mask, lo, nodes, last, home, offsets, nearest, r, reach, k, best_d, best_j)
        _sort_ids(best_j, count)
        for m in range(count):
            edges[0, e] = best_j[m]
            edges[1, e] = i
            e += 1
        nodes[p].prev = last[home]
        last[home] = i
    return e


@numba.njit(cache=True, nogil=True)
def link_samples(bounds, nodes, last, frame, offsets, nearest, r, reach, k):
    """:func:`link` over every sample ``[bounds[s], bounds[s + 1])`` on one thread: chains never
    reach back past a sample's first node. Returns the edges ``(2, E)``."""
    edges = np.empty((2, len(nodes) * k), dtype=np.int64)
    e = 0
    for s in range(len(bounds) - 1):
        e = link(bounds[s], bounds[s + 1], bounds[s], -1, nodes, last, frame, offsets, nearest, r, reach, k,
                 edges, e)
    return edges[:, :e].copy()


@numba.njit(cache=True, nogil=True)
def chain_all(nodes, grid_size, frame):
    """Each node's cell (returned) and ``prev``: the chains of all nodes, in one pass."""
    n = len(nodes)
    home = np.empty(n, dtype=np.int64)
    latest = np.full(grid_size, -1, dtype=np.int64)
    for i in range(n):
        home[i] = _cell(nodes[i].x, nodes[i].y, frame)
        nodes[i].prev = latest[home[i]]
        latest[home[i]] = i
    return home


@numba.njit(cache=True, nogil=True)
def link_chunk(start, stop, replay, lo, nodes, home, grid_size, offsets, nearest, r, reach, k, neighbours, counts):
    """The neighbours of nodes ``start <= i < stop`` (chains set by :func:`chain_all`) into rows
    ``i`` of ``neighbours`` / ``counts``. ``last`` is rebuilt as it stands at ``start`` from the
    nodes within reach before it (``replay``); ``lo``: each node's sample start. Chunks run on
    threads of their own (the GIL released)."""
    last = np.full(grid_size, -1, dtype=np.int64)
    for j in range(replay, start):
        last[home[j]] = j
    best_d = np.empty(k, dtype=np.float64)
    best_j = np.empty(k, dtype=np.int64)
    near = replay
    for i in range(start, stop):
        near = max(near, lo[i])
        while near < i and nodes[near].z < nodes[i].z - reach:
            near += 1  # out of reach from here on: a chain stops there without loading it
        count = _nearest_earlier(i, -1, near, nodes, last, home[i], offsets, nearest, r, reach, k, best_d, best_j)
        _sort_ids(best_j, count)
        neighbours[i, :count] = best_j[:count]
        counts[i] = count
        last[home[i]] = i


@numba.njit(cache=True, nogil=True)
def rows_to_edges(neighbours, counts):
    """Rows of neighbours -> ``(2, E)`` edges (sources, destinations = row)."""
    edges = np.empty((2, counts.sum()), dtype=np.int64)
    e = 0
    for i in range(len(counts)):
        for m in range(counts[i]):
            edges[0, e] = neighbours[i, m]
            edges[1, e] = i
            e += 1
    return edges


def integral(x: np.ndarray, y: np.ndarray) -> bool:
    return bool(np.all(x == np.floor(x)) and np.all(y == np.floor(y)))


def reach_of(r: float) -> float:
    """The time gap (in z) beyond which no event can be within ``r``, with room for rounding."""
    return r * (1 + REACH_MARGIN)


def check_time_order(z: np.ndarray, bounds: np.ndarray) -> None:
    down = np.flatnonzero(z[1:] < z[:-1]) + 1
    if len(down):
        starts = set(bounds[1:-1].tolist())
        inside = [int(i) for i in down if int(i) not in starts]
        if inside:
            raise ValueError(f"pos must be sorted by time (z) within each sample: {len(inside)} event(s) earlier "
                             f"than the event before, the first at index {inside[0]}")


def threads_for(workers: int | None) -> int:
    """Threads for ``workers`` (-1 or None: one per core this process may use)."""
    most = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return most if workers in (None, -1) else max(1, min(int(workers), most))


def build(points: np.ndarray, bounds: np.ndarray, r: float, k: int, workers: int | None = -1) -> np.ndarray:
    """Causal edges ``(2, E)`` of ``points (N, 3)`` (float64, time-sorted within each sample
    ``[bounds[s], bounds[s + 1])``), sorted by (destination, source)."""
    n = len(points)
    if n < 2:
        return np.zeros((2, 0), dtype=np.int64)
    nodes = np.empty(n, dtype=NODE)
    nodes["x"], nodes["y"], nodes["z"] = points[:, 0], points[:, 1], points[:, 2]
    check_time_order(nodes["z"], bounds)
    lo_xy, hi_xy = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    grid = Grid(lo_xy, hi_xy, r, integral(nodes["x"], nodes["y"]))
    reach, threads = reach_of(r), threads_for(workers)
    if threads == 1 or n < PARALLEL_MIN:
        last = np.full(grid.size, -1, dtype=np.int64)
        return link_samples(bounds.astype(np.int64), nodes, last, grid.frame, grid.offsets, grid.nearest, r, reach, k)
    chunks = np.linspace(0, n, 2 * threads + 1).astype(np.int64)
    lo = bounds[np.searchsorted(bounds, np.arange(n), side="right") - 1].astype(np.int64)
    home = chain_all(nodes, grid.size, grid.frame)
    z = nodes["z"]
    neighbours = np.empty((n, k), dtype=np.int64)
    counts = np.empty(n, dtype=np.int64)

    def run(c: int) -> None:
        start, stop = int(chunks[c]), int(chunks[c + 1])
        replay = int(lo[start] + np.searchsorted(z[lo[start]:start], z[start] - reach, side="left"))
        link_chunk(start, stop, replay, lo, nodes, home, grid.size, grid.offsets, grid.nearest, r, reach, k,
                   neighbours, counts)

    with ThreadPoolExecutor(threads) as pool:  # the kernels release the GIL; no threading layer to fork
        list(pool.map(run, range(len(chunks) - 1)))
    return rows_to_edges(neighbours, counts)


# The state of a stream, one int64 array (one argument for the kernel): its fields.
LO, COUNT, MASK, INTEGER, STATE_SIZE = 0, 1, 2, 3, 4
TIME_ORDER, OUTSIDE, FULL = -1, -2, -3  # why an insertion stopped before linking


@numba.njit(cache=True, nogil=True)
def insert_kernel(points, state, last_z, nodes, last, frame, offsets, nearest, r, reach, k):
    """One insertion of ``points (M, 3)``: returns ``(edges (2, E), status)``, status 0 when done,
    else why it did nothing (:data:`TIME_ORDER`, :data:`OUTSIDE` of the grid's inner box or of its
    integer offsets, ring :data:`FULL`). ``state`` and ``last_z[0]`` are updated when done."""
    m = len(points)
    empty = np.empty((2, 0), dtype=np.int64)
    if points[0, 2] < last_z[0]:
        return empty, TIME_ORDER
    s = frame[0]
    for i in range(m):
        if i and points[i, 2] < points[i - 1, 2]:
            return empty, TIME_ORDER
        x, y = points[i, 0], points[i, 1]
        cx, cy = math.floor(x / s), math.floor(y / s)
        if cx < frame[4] or cy < frame[5] or cx > frame[6] or cy > frame[7]:
            return empty, OUTSIDE
        if state[INTEGER] and (x != math.floor(x) or y != math.floor(y)):
            return empty, OUTSIDE
    mask = state[MASK]
    lo, count = state[LO], state[COUNT]
    while lo < count and nodes[lo & mask].z < points[0, 2] - reach:
        lo += 1  # out of reach of every new event (and of every later one)
    if count + m - lo > mask + 1:
        state[LO] = lo
        return empty, FULL
    for i in range(m):
        node = nodes[(count + i) & mask]
        node.x, node.y, node.z = points[i, 0], points[i, 1], points[i, 2]
    edges = np.empty((2, m * k), dtype=np.int64)
    e = link(count, count + m, lo, mask, nodes, last, frame, offsets, nearest, r, reach, k, edges, 0)
    state[LO], state[COUNT] = lo, count + m
    last_z[0] = points[m - 1, 2]
    return edges[:, :e], 0


@numba.njit(cache=True, nogil=True)
def relink(lo, count, mask, nodes, last, frame):
    """The chains of the held nodes ``lo <= id < count`` rebuilt on a new grid."""
    for i in range(lo, count):
        node = nodes[i & mask]
        home = _cell(node.x, node.y, frame)
        node.prev = last[home]
        last[home] = i


class CellChains:
    """The cell chains of a stream of events, kept in a ring while a later event may reach them.

    An insertion costs the new events' neighbourhoods, whatever the history: the ring holds the
    events within ``r`` in z of the newest (and grows when they do not fit); the grid grows (or
    takes larger cells) when events arrive outside it.
    """

    def __init__(self, r: float, k: int, capacity: int = 1 << 12):
        self.r, self.k, self.reach = float(r), int(k), reach_of(r)
        self.nodes = np.zeros(1 << max(4, int(capacity - 1).bit_length()), dtype=NODE)
        self.state = np.array([0, 0, len(self.nodes) - 1, 1], dtype=np.int64)
        self.last_z = np.array([-np.inf])
        self.grid: Grid | None = None
        self.last = np.zeros(0, dtype=np.int64)

    @property
    def held(self) -> int:
        """Events a later event may still link to (and a few beyond)."""
        return int(self.state[COUNT] - self.state[LO])

    @property
    def count(self) -> int:
        return int(self.state[COUNT])

    def _held(self) -> np.ndarray:
        return self.nodes[np.arange(self.state[LO], self.state[COUNT]) & self.state[MASK]]

    def _grow_ring(self, need: int) -> None:
        ids = np.arange(self.state[LO], self.state[COUNT])
        grown = np.zeros(1 << int(need - 1).bit_length(), dtype=NODE)
        grown[ids & (len(grown) - 1)] = self.nodes[ids & self.state[MASK]]
        self.nodes, self.state[MASK] = grown, len(grown) - 1

    def _regrid(self, points: np.ndarray) -> None:
        """A grid holding the held events and ``points``, with room to spare; chains relinked."""
        held = self._held()
        xs, ys = np.concatenate([held["x"], points[:, 0]]), np.concatenate([held["y"], points[:, 1]])
        lo_xy, hi_xy = np.array([xs.min(), ys.min()]), np.array([xs.max(), ys.max()])
        if self.grid is not None:  # keep what was covered, so that a wandering stream settles
            g = self.grid
            lo_xy = np.minimum(lo_xy, [g.frame[4] * g.s, g.frame[5] * g.s])
            hi_xy = np.maximum(hi_xy, [g.frame[6] * g.s, g.frame[7] * g.s])
        self.grid = Grid(lo_xy, hi_xy, self.r, bool(self.state[INTEGER]) and integral(xs, ys), slack=16)
        self.state[INTEGER] = int(self.grid.integer)
        self.last = np.full(self.grid.size, -1, dtype=np.int64)
        relink(self.state[LO], self.state[COUNT], self.state[MASK], self.nodes, self.last, self.grid.frame)

    def insert(self, points: np.ndarray) -> np.ndarray:
        """Edges ``(2, E)`` into new events ``points (M, 3)`` (float64, time-sorted, none earlier
        than an event before), in stream ids, sorted by (destination, source)."""
        if self.grid is None:
            self._regrid(points)
        while True:
            edges, status = insert_kernel(points, self.state, self.last_z, self.nodes, self.last, self.grid.frame,
                                          self.grid.offsets, self.grid.nearest, self.r, self.reach, self.k)
            if status == 0:
                return edges
            if status == TIME_ORDER:
                raise ValueError("events must arrive in time order: pos[:, 2] may not decrease")
            if status == OUTSIDE:
                self._regrid(points)
            else:
                self._grow_ring(self.held + len(points))
