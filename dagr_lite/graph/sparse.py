"""Index structures of the GCN and the pooling in one compiled pass each (docs/design.md, "The event graph").

A training step builds, for every batch, the propagation matrix of the event graph, its
transpose, the cells the nodes pool into and the deduplicated edges between those cells. These
depend on the graph alone, never on the weights. By tensor operations each is a sort of the
edges (``torch.argsort``, ``torch.unique``); the keys are small integers, so a counting pass
gives the same order in time linear in the edges. Each function here returns exactly what its
tensor expression returns (``tests/graph/test_sparse.py``); callers use them for CPU tensors.
"""
from __future__ import annotations

import numba
import numpy as np

# Cached on disk, releasing the GIL, no division-by-zero checks (as the graph builder's kernels).
KERNEL = {"cache": True, "nogil": True, "error_model": "numpy"}

# False: every caller takes its tensor expression (a benchmark's baseline, a test's reference).
USE_COMPILED = True

# A dense table of every possible key costs its size: above this many keys per item (and a floor),
# :func:`unique_inverse` declines and the caller sorts instead.
DENSE_KEYS_PER_ITEM, DENSE_KEYS_FLOOR = 8, 1 << 16


def compiled_for(tensor) -> bool:
    """Whether a caller takes these passes for ``tensor``: on the CPU, unless :data:`USE_COMPILED` is off."""
    return USE_COMPILED and tensor.device.type == "cpu"


@numba.njit(**KERNEL)
def counting_order(keys, size):
    """The stable order of ``keys (N,)`` (int64 in ``[0, size)``): ``torch.argsort(keys, stable=True)``."""
    start = np.zeros(size + 1, dtype=np.int64)
    for e in range(len(keys)):
        start[keys[e] + 1] += 1
    for k in range(size):
        start[k + 1] += start[k]
    order = np.empty(len(keys), dtype=np.int64)
    for e in range(len(keys)):
        k = keys[e]
        order[start[k]] = e
        start[k] += 1
    return order


@numba.njit(**KERNEL)
def transpose_triplets(row, col, value, num_cols):
    """The transpose of a matrix given as triplets sorted by (row, col), as CSR: ``(crow (num_cols + 1,),
    rows, values, order)``, where ``order`` is :func:`counting_order` of ``col`` (rows ascend within
    each column) and ``rows = row[order]``, ``values = value[order]``."""
    crow = np.zeros(num_cols + 1, dtype=np.int64)
    for e in range(len(col)):
        crow[col[e] + 1] += 1
    for k in range(num_cols):
        crow[k + 1] += crow[k]
    fill = crow[:-1].copy()
    order = np.empty(len(col), dtype=np.int64)
    rows = np.empty(len(col), dtype=np.int64)
    values = np.empty(len(col), dtype=value.dtype)
    for e in range(len(col)):
        k = col[e]
        at = fill[k]
        order[at] = e
        rows[at] = row[e]
        values[at] = value[e]
        fill[k] = at + 1
    return crow, rows, values, order


@numba.njit(**KERNEL)
def _unique_inverse(keys, size):
    slot = np.full(size, -1, dtype=np.int64)
    for e in range(len(keys)):
        slot[keys[e]] = 0
    count = 0
    for k in range(size):
        if slot[k] == 0:
            slot[k] = count
            count += 1
    unique = np.empty(count, dtype=np.int64)
    inverse = np.empty(len(keys), dtype=np.int64)
    for e in range(len(keys)):
        c = slot[keys[e]]
        unique[c] = keys[e]
        inverse[e] = c
    return unique, inverse


def unique_inverse(keys: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``torch.unique(keys, sorted=True, return_inverse=True)`` of int64 ``keys (N,)`` in ``[0, size)``,
    by a table of every key; None where that table would be much larger than ``keys``."""
    if size > max(DENSE_KEYS_PER_ITEM * len(keys), DENSE_KEYS_FLOOR):
        return None
    return _unique_inverse(keys, size)


@numba.njit(**KERNEL)
def unique_pairs(src, dst, size):
    """The distinct pairs ``(src[e], dst[e])`` (int64 in ``[0, size)``), sorted by (dst, src):
    ``torch.unique(dst * size + src, sorted=True)`` split back into ``(src, dst)``."""
    order = counting_order(dst, size)  # grouped by destination
    stamp = np.full(size, -1, dtype=np.int64)  # the destination a source was last kept for
    out_src = np.empty(len(src), dtype=np.int64)
    out_dst = np.empty(len(src), dtype=np.int64)
    n = 0
    e = 0
    while e < len(order):
        d = dst[order[e]]
        first = n
        while e < len(order) and dst[order[e]] == d:
            s = src[order[e]]
            if stamp[s] != d:
                stamp[s] = d
                out_src[n] = s
                n += 1
            e += 1
        out_src[first:n].sort()
        out_dst[first:n] = d
    return out_src[:n].copy(), out_dst[:n].copy()


@numba.njit(**KERNEL)
def causal_triplets(src, dst, scale):
    """``D^-1/2 (A + I) D^-1/2`` as triplets ``(row, col, value)`` sorted by (row, col), for edges
    sorted by (dst, src), each from an earlier node (the causal graph's): each row's edges, then
    its self-loop. ``scale (N,)`` float64 is ``d^-1/2`` of every node; the value is
    ``scale[row] * scale[col]``, as ``nn.gcn.gcn_norm`` computes it."""
    num_nodes = len(scale)
    total = len(src) + num_nodes
    row = np.empty(total, dtype=np.int64)
    col = np.empty(total, dtype=np.int64)
    value = np.empty(total, dtype=np.float64)
    n = 0
    e = 0
    for i in range(num_nodes):
        while e < len(src) and dst[e] == i:
            row[n] = i
            col[n] = src[e]
            value[n] = scale[i] * scale[src[e]]
            n += 1
            e += 1
        row[n] = i
        col[n] = i
        value[n] = scale[i] * scale[i]
        n += 1
    return row, col, value


@numba.njit(**KERNEL)
def distinct_in_degree(src, dst, num_nodes):
    """Each node's count of distinct sources among the edges into it, self-loops left out:
    ``torch.bincount(torch.unique(dst * N + src) // N, minlength=N)`` over the edges with ``src != dst``."""
    stamp = np.full(num_nodes, -1, dtype=np.int64)  # the source a destination's count last took
    order = counting_order(src, num_nodes)  # edges grouped by source: a repeat of (src, dst) is seen in its group
    degree = np.zeros(num_nodes, dtype=np.int64)
    for e in order:
        s, d = src[e], dst[e]
        if s != d and stamp[d] != s:
            stamp[d] = s
            degree[d] += 1
    return degree


@numba.njit(**KERNEL)
def norm_triplets(src, dst, rows, scale):
    """The general form of ``nn.gcn.gcn_norm``'s triplets: for the output rows ``rows (R,)`` (node
    ids, distinct), each row's distinct sources among the edges into its node and the node itself
    (self-loops in the edges left out), sorted by (row, col), with the value ``scale[node] *
    scale[col]``; ``scale (N,)`` float64 is every node's ``d^-1/2``."""
    num_nodes, num_rows = len(scale), len(rows)
    position = np.full(num_nodes, -1, dtype=np.int64)
    for i in range(num_rows):
        position[rows[i]] = i
    start = np.zeros(num_rows + 1, dtype=np.int64)
    for e in range(len(src)):
        if src[e] != dst[e] and position[dst[e]] >= 0:
            start[position[dst[e]] + 1] += 1
    for i in range(num_rows):
        start[i + 1] += start[i] + 1  # and one self-loop a row
    cols = np.empty(start[num_rows], dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(num_rows):
        cols[fill[i]] = rows[i]
        fill[i] += 1
    for e in range(len(src)):
        if src[e] != dst[e] and position[dst[e]] >= 0:
            i = position[dst[e]]
            cols[fill[i]] = src[e]
            fill[i] += 1
    row = np.empty(len(cols), dtype=np.int64)
    col = np.empty(len(cols), dtype=np.int64)
    value = np.empty(len(cols), dtype=np.float64)
    n = 0
    for i in range(num_rows):
        segment = cols[start[i]:start[i + 1]]
        segment.sort()
        node = rows[i]
        for k in range(len(segment)):
            c = segment[k]
            if k == 0 or c != segment[k - 1]:  # a repeated edge counts once
                row[n], col[n] = i, c
                value[n] = scale[node] * scale[c]
                n += 1
    return row[:n].copy(), col[:n].copy(), value[:n].copy()
