"""The causal radius graph from cell chains, compiled with numba (docs/design.md, "The event graph").

Events are binned into square cells of side ``s`` in (x, y): one pixel for integer positions,
two for fractional ones, larger where the grid would not fit (:data:`GRID_BUDGET`). Each event
links to the previous event of its cell (``prev``) and each cell to its latest event (``last``),
so a cell's events form a chain back in time. Node ``i`` (events taken in index order, sorted by
time) walks, for every cell offset that can hold a point within ``r`` (nearest offsets first),
its chain from the latest event before ``i`` back until the time gap puts the cell beyond the
bound, tests the exact distance and keeps the ``k`` nearest by (distance, index); then ``i``
joins its own cell's chain. The bound is ``r``, then the ``k``-th distance once ``k`` are held.

The distance is computed as the KD-tree builder computes it (float64, ``sqrt(dx^2 + dy^2 +
dz^2)`` summed in that order). Every skip compares a lower bound of that computed sum of squares
against ``bound^2 * SQUARE_MARGIN``, above which its rounded root is certainly beyond the bound,
so the edge set is the KD-tree's, ties included. Work per event is the cells around it plus the
events in its reach, independent of history: streaming insertion (:class:`CellChains`) costs what
arrives.
"""
from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

# Cell side: one pixel for integer positions (a cell's least distance is then exact and no point
# needs its own), two for fractional ones (a point then reaches 3 cells each way instead of 6:
# 37 cells instead of 129, the fewer reads outweighing the longer chains; measured in
# benchmarks/graph.py on the loader's zoomed samples).
CELL_SIZE, FRACTIONAL_CELL_SIZE = 1.0, 2.0
GRID_BUDGET = 1 << 24  # most cells in the grid; wider clouds get cells of more than a pixel
PARALLEL_MIN = 1 << 15  # fewer events than this build on one thread
REACH_MARGIN = 1e-9  # relative: the time gap beyond which no event can be within r, with room for rounding
SQUARE_MARGIN = 1.0 + 1e-12  # a squared distance above bound^2 x this has a (rounded) root above the bound
# Every kernel: cached on disk, releasing the GIL (threads), no division-by-zero checks.
KERNEL = {"cache": True, "nogil": True, "error_model": "numpy"}
NODE = np.dtype([("x", np.float64), ("y", np.float64), ("z", np.float64), ("prev", np.int64)])  # one cache line half


def cell_offsets(r: float, s: float, integer: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell offsets ``(a, b)`` that can hold a point within ``r``, nearest first (made once for
    each ``(r, s, integer)``; each call gets copies).

    Returns ``a``, ``b`` (int64) and ``flat2`` (float64): the least ``dx^2 + dy^2`` between a
    point and one in the offset cell, as the distance computes it. With ``integer`` (every x, y an
    integer and ``s == 1``) points sit on their cell's corner, so it is exactly ``a^2 + b^2``;
    otherwise ``s^2 ((|a| - 1)^2 + (|b| - 1)^2)`` (positive parts), which the computed squares
    cannot undercut: ``|dx|`` is at least ``(|a| - 1) s``, a number held exactly, and rounding is
    monotone.
    """
    return tuple(array.copy() for array in _cell_offsets(float(r), float(s), bool(integer)))


@functools.lru_cache(maxsize=64)
def _cell_offsets(r: float, s: float, integer: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    reach = int(math.floor(r / s)) + (0 if integer else 1)
    a, b = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="xy")
    a, b = a.ravel(), b.ravel()
    ga, gb = (a, b) if integer else (np.maximum(np.abs(a) - 1, 0), np.maximum(np.abs(b) - 1, 0))
    flat2 = (s * s) * (ga * ga + gb * gb).astype(np.float64)
    keep = np.sqrt(flat2) <= r
    order = np.lexsort((a[keep], b[keep], flat2[keep]))
    return a[keep][order].astype(np.int64), b[keep][order].astype(np.int64), flat2[keep][order]


class Grid:
    """Cells of side ``s`` over ``[lo_xy, hi_xy]`` (plus ``slack`` cells), with a border of ``pad``
    cells so that every offset of :func:`cell_offsets` from a point's own cell stays inside.

    ``frame`` is what the kernels take: ``[s, x0, y0, width, inner x0, inner y0, inner x1, inner
    y1]``, the inner box being the cells a point may occupy.
    """

    def __init__(self, lo_xy, hi_xy, r: float, integer: bool, slack: int = 0):
        s = CELL_SIZE if integer else FRACTIONAL_CELL_SIZE
        span = np.floor(np.asarray(hi_xy, dtype=np.float64)) - np.floor(np.asarray(lo_xy, dtype=np.float64)) + 1
        while float((span[0] / s + 2 * (slack + r / s + 2)) * (span[1] / s + 2 * (slack + r / s + 2))) > GRID_BUDGET:
            s *= 2.0
        self.s, self.integer = s, bool(integer and s == 1.0)
        a, b, self.flat2 = cell_offsets(r, s, self.integer)
        self.pad = int(max(np.abs(a).max(), np.abs(b).max()))
        inner_lo = [int(math.floor(v / s)) - slack for v in lo_xy]
        inner_hi = [int(math.floor(v / s)) + slack for v in hi_xy]
        self.x0, self.y0 = inner_lo[0] - self.pad, inner_lo[1] - self.pad
        self.width = inner_hi[0] + self.pad - self.x0 + 1
        self.height = inner_hi[1] + self.pad - self.y0 + 1
        self.offsets = np.stack([b * self.width + a, a + self.pad, b + self.pad])  # (3, n): cell step, a, b
        self.frame = np.array([s, self.x0, self.y0, self.width, *inner_lo, *inner_hi], dtype=np.float64)

    @property
    def size(self) -> int:
        return self.width * self.height


@numba.njit(**KERNEL)
def _cell(x, y, frame):
    s = frame[0]
    return (int(math.floor(y / s)) - int(frame[2])) * int(frame[3]) + int(math.floor(x / s)) - int(frame[1])


@numba.njit(**KERNEL, inline="always")
def _nearest_earlier(i, mask, lo, nodes, last, home, offsets, flat2, integer, frame, r, k, best_d, best_j, gap2):
    """The ``k`` nearest nodes ``lo <= j < i`` within ``r`` into ``best_d`` / ``best_j`` (by
    distance, then index); returns how many. ``nodes`` is indexed by ``id & mask``; ``gap2`` is
    scratch, ``(2, 2 * pad + 1)``."""
    node = nodes[i & mask]
    xi, yi, zi = node.x, node.y, node.z
    if not integer:  # the least dx^2 (dy^2) from this point to a cell a (b) columns (rows) away
        s = frame[0]
        pad = (gap2.shape[1] - 1) // 2
        cx, cy = math.floor(xi / s), math.floor(yi / s)
        for a in range(-pad, pad + 1):
            gx = (cx + a) * s - xi if a > 0 else (xi - (cx + a + 1) * s if a < 0 else 0.0)
            gy = (cy + a) * s - yi if a > 0 else (yi - (cy + a + 1) * s if a < 0 else 0.0)
            gap2[0, a + pad] = gx * gx
            gap2[1, a + pad] = gy * gy
    count = 0
    bound = r  # r, then the k-th distance once k are held
    bound2 = r * r * SQUARE_MARGIN  # a squared distance above this has its root above the bound
    for o in range(offsets.shape[1]):
        f2 = flat2[o]
        if f2 > bound2:
            break  # this offset and every later one lie beyond the bound
        if not integer:
            f2 = gap2[0, offsets[1, o]] + gap2[1, offsets[2, o]]  # this point's own least, at least flat2[o]
            if f2 > bound2:
                continue
        j = last[np.uint64(home + offsets[0, o])]  # unsigned: no negative-index wrap-around in the loop
        while j >= lo:
            other = nodes[np.uint64(j & mask)]
            dz = zi - other.z
            dz2 = dz * dz
            least2 = f2 + dz2  # no event of this cell is nearer; the chain only gets further
            if least2 > bound2:
                break
            if integer:
                d2 = least2  # on integer pixels the least distance of the cell is the distance
            else:
                dx = xi - other.x
                dy = yi - other.y
                d2 = dx * dx + dy * dy + dz2
            if d2 <= bound2:
                d = math.sqrt(d2)
                if d <= bound and (count < k or d < bound or j < best_j[k - 1]):
                    m = count if count < k else k - 1
                    while m > 0 and (best_d[m - 1] > d or (best_d[m - 1] == d and best_j[m - 1] > j)):
                        best_d[m] = best_d[m - 1]
                        best_j[m] = best_j[m - 1]
                        m -= 1
                    best_d[m] = d
                    best_j[m] = j
                    if count < k:
                        count += 1
                    if count == k:
                        bound = best_d[k - 1]
                        bound2 = bound * bound * SQUARE_MARGIN
            j = other.prev
    return count


@numba.njit(**KERNEL)
def _sort_ids(best_j, count):
    for m in range(1, count):
        value = best_j[m]
        n = m
        while n > 0 and best_j[n - 1] > value:
            best_j[n] = best_j[n - 1]
            n -= 1
        best_j[n] = value


@numba.njit(**KERNEL)
def link(start, stop, lo, mask, nodes, last, frame, offsets, flat2, integer, r, reach, k, edges, e, query):
    """Nodes ``start <= i < stop`` in order: their edges written to ``edges[:, e:]`` (only those of
    nodes whose ``query[i]`` holds, unless ``query`` is empty), then each joins its cell's chain.
    Returns the new ``e``."""
    best_d = np.empty(k, dtype=np.float64)
    best_j = np.empty(k, dtype=np.int64)
    gap2 = np.empty((2, int(offsets[1].max()) + 1), dtype=np.float64)  # offsets run -pad..pad
    every = len(query) == 0
    for i in range(start, stop):
        p = i & mask
        home = _cell(nodes[p].x, nodes[p].y, frame)
        if every or query[i]:
            while lo < i and nodes[lo & mask].z < nodes[p].z - reach:
                lo += 1  # out of reach from here on: a chain stops there without loading it
            count = _nearest_earlier(i, mask, lo, nodes, last, home, offsets, flat2, integer, frame, r, k, best_d,
                                     best_j, gap2)
            _sort_ids(best_j, count)
            for m in range(count):
                edges[0, e] = best_j[m]
                edges[1, e] = i
                e += 1
        nodes[p].prev = last[home]
        last[home] = i
    return e


NO_QUERY = np.zeros(0, dtype=np.bool_)  # link's ``query``: every node's edges


@numba.njit(**KERNEL)
def link_samples(bounds, nodes, last, frame, offsets, flat2, integer, r, reach, k, query):
    """:func:`link` over every sample ``[bounds[s], bounds[s + 1])`` on one thread: chains never
    reach back past a sample's first node. Returns the edges ``(2, E)``."""
    edges = np.empty((2, (len(nodes) if len(query) == 0 else int(query.sum())) * k), dtype=np.int64)
    e = 0
    for s in range(len(bounds) - 1):
        e = link(bounds[s], bounds[s + 1], bounds[s], -1, nodes, last, frame, offsets, flat2, integer, r, reach, k,
                 edges, e, query)
    return edges[:, :e].copy()


@numba.njit(**KERNEL)
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


@numba.njit(**KERNEL)
def link_chunk(start, stop, replay, lo, nodes, home, grid_size, frame, offsets, flat2, integer, r, reach, k, neighbours, counts):
    """The neighbours of nodes ``start <= i < stop`` (chains set by :func:`chain_all`) into rows
    ``i`` of ``neighbours`` / ``counts``. ``last`` is rebuilt as it stands at ``start`` from the
    nodes within reach before it (``replay``); ``lo``: each node's sample start. Chunks run on
    threads of their own (the GIL released)."""
    last = np.full(grid_size, -1, dtype=np.int64)
    for j in range(replay, start):
        last[home[j]] = j
    best_d = np.empty(k, dtype=np.float64)
    best_j = np.empty(k, dtype=np.int64)
    gap2 = np.empty((2, int(offsets[1].max()) + 1), dtype=np.float64)  # offsets run -pad..pad
    near = replay
    for i in range(start, stop):
        near = max(near, lo[i])
        while near < i and nodes[near].z < nodes[i].z - reach:
            near += 1  # out of reach from here on: a chain stops there without loading it
        count = _nearest_earlier(i, -1, near, nodes, last, home[i], offsets, flat2, integer, frame, r, k, best_d, best_j,
                                 gap2)
        _sort_ids(best_j, count)
        neighbours[i, :count] = best_j[:count]
        counts[i] = count
        last[home[i]] = i


@numba.njit(**KERNEL)
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


def build(points: np.ndarray, bounds: np.ndarray, r: float, k: int, workers: int | None = -1,
          query: np.ndarray | None = None) -> np.ndarray:
    """Causal edges ``(2, E)`` of ``points (N, 3)`` (float64, time-sorted within each sample
    ``[bounds[s], bounds[s + 1])``), sorted by (destination, source); with ``query`` (``(N,)``
    bool) only the edges into the nodes it marks (every node still a source), on one thread."""
    n = len(points)
    if query is not None:
        query = np.ascontiguousarray(query, dtype=np.bool_)
        if query.shape != (n,):
            raise ValueError(f"query must mark each of the {n} points, got shape {query.shape}")
        if not query.any():
            return np.zeros((2, 0), dtype=np.int64)
    if n < 2:
        return np.zeros((2, 0), dtype=np.int64)
    nodes = np.empty(n, dtype=NODE)
    nodes["x"], nodes["y"], nodes["z"] = points[:, 0], points[:, 1], points[:, 2]
    check_time_order(nodes["z"], bounds)
    # per column: numpy's reduction over axis 0 of an (N, 2) view runs 15-35x slower
    lo_xy = np.array([points[:, 0].min(), points[:, 1].min()])
    hi_xy = np.array([points[:, 0].max(), points[:, 1].max()])
    grid = Grid(lo_xy, hi_xy, r, integral(nodes["x"], nodes["y"]))
    reach, threads = reach_of(r), threads_for(workers)
    if threads == 1 or n < PARALLEL_MIN or query is not None:
        last = np.full(grid.size, -1, dtype=np.int64)
        return link_samples(bounds.astype(np.int64), nodes, last, grid.frame, grid.offsets, grid.flat2, grid.integer, r,
                            reach, k, NO_QUERY if query is None else query)
    chunks = np.linspace(0, n, 2 * threads + 1).astype(np.int64)
    lo = bounds[np.searchsorted(bounds, np.arange(n), side="right") - 1].astype(np.int64)
    home = chain_all(nodes, grid.size, grid.frame)
    z = nodes["z"]
    neighbours = np.empty((n, k), dtype=np.int64)
    counts = np.empty(n, dtype=np.int64)

    def run(c: int) -> None:
        start, stop = int(chunks[c]), int(chunks[c + 1])
        replay = int(lo[start] + np.searchsorted(z[lo[start]:start], z[start] - reach, side="left"))
        link_chunk(start, stop, replay, lo, nodes, home, grid.size, grid.frame, grid.offsets, grid.flat2, grid.integer, r, reach, k,
                   neighbours, counts)

    with ThreadPoolExecutor(threads) as pool:  # the kernels release the GIL; no threading layer to fork
        list(pool.map(run, range(len(chunks) - 1)))
    return rows_to_edges(neighbours, counts)


# The state of a stream, one int64 array (one argument for the kernel): its fields.
LO, COUNT, MASK, INTEGER, STATE_SIZE = 0, 1, 2, 3, 4
TIME_ORDER, OUTSIDE, FULL = -1, -2, -3  # why an insertion stopped before linking


@numba.njit(**KERNEL)
def insert_kernel(points, state, last_z, nodes, last, frame, offsets, flat2, integer, r, reach, k):
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
    e = link(count, count + m, lo, mask, nodes, last, frame, offsets, flat2, integer, r, reach, k, edges, 0, NO_QUERY)
    state[LO], state[COUNT] = lo, count + m
    last_z[0] = points[m - 1, 2]
    return edges[:, :e], 0


@numba.njit(**KERNEL)
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
                                          self.grid.offsets, self.grid.flat2, self.grid.integer, self.r, self.reach, self.k)
            if status == 0:
                return edges
            if status == TIME_ORDER:
                raise ValueError("events must arrive in time order: pos[:, 2] may not decrease")
            if status == OUTSIDE:
                self._regrid(points)
            else:
                self._grow_ring(self.held + len(points))


@numba.njit(**KERNEL)
def neighbourhood_moments(pos, src, dst, first, radius, max_neighbors, out):
    """``out (n, 10)`` zeros -> per node ``first + i`` the means over its incoming edges of the offsets
    ``d = (pos[src] - pos[dst]) / radius``, of their squares and of ``dx dt, dy dt, dx dy``, then the
    in-degree over ``max_neighbors`` (``nn.event_branch.neighbourhood_geometry``). One pass over the
    edges in their order, each product in ``out``'s precision."""
    for e in range(len(src)):
        s, d = src[e], dst[e]
        i = d - first
        dx = (pos[s, 0] - pos[d, 0]) / radius
        dy = (pos[s, 1] - pos[d, 1]) / radius
        dt = (pos[s, 2] - pos[d, 2]) / radius
        row = out[i]
        row[0] += dx
        row[1] += dy
        row[2] += dt
        row[3] += dx * dx
        row[4] += dy * dy
        row[5] += dt * dt
        row[6] += dx * dt
        row[7] += dy * dt
        row[8] += dx * dy
        row[9] += 1
    for i in range(len(out)):
        degree = out[i, 9]
        if degree > 0:
            for c in range(9):
                out[i, c] /= degree
        out[i, 9] = degree / max_neighbors
