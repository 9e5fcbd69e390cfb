"""The event branch's GCN blocks and image sampling in one compiled pass each, for inference on a CPU.

An answer of the streaming detector runs a GCN block on a few hundred rows at a time: the first
stage's new nodes, then each pooled level's cells. By tensor operations a block is some thirty
small operations (the normalised matrix built, a sparse product, a matrix product, the layer
norm, the ReLU, the skip), each costing its dispatch on tensors this small. Here a block is one
pass: each output row's messages summed, its linear layer, norm, ReLU and skip, the same maths
as :class:`~dagr_lite.nn.event_branch.GCNBlock` over a :class:`~dagr_lite.nn.gcn.GraphOperator`
(``tests/nn/test_kernels.py`` holds the two together: to 1e-9 in float64, 1e-5 in float32). Only
the order of the sums differs. No gradient flows; training takes the tensor operations.
"""
from __future__ import annotations

import weakref

import numba
import numpy as np
import torch

from dagr_lite.graph import sparse
from dagr_lite.graph.sparse import KERNEL, counting_order, distinct_in_degree


# False: every caller takes the tensor operations (a benchmark's baseline, measured in the same process).
USE_KERNELS = True

# Called as ``observer(block, x, graph)`` before each compiled block (a benchmark's count of its
# multiply-adds, as a forward hook counts the tensor operations').
OBSERVERS: list = []


def compiled_inference(x: torch.Tensor) -> bool:
    """Whether layers over ``x`` may take these passes: a float32 or float64 CPU tensor, with gradients
    off (``torch.no_grad`` or inference mode: the weights' gradients are not wanted either); the graph
    passes' switch, :data:`~dagr_lite.graph.sparse.USE_COMPILED`, also turns these off."""
    return (USE_KERNELS and sparse.USE_COMPILED and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
            and not torch.is_grad_enabled())


class NodeGraph:
    """A GCN layer's graph for :func:`gcn_block`: distinct edges ``j -> i`` (self-loops are left out,
    the identity adds each node's own), the first output row (rows ``first .. N - 1`` are computed;
    every edge ends at one of them) and each node's in-degree (the pass takes ``d^-1/2``, ``d = 1 +``
    in-degree, of the nodes it reads), and whether the edges are sorted by (destination, source).

    ``in_degree (N,)``: every node's, where ``edge_index`` holds only the edges into some (streaming);
    counted from ``edge_index`` otherwise (distinct sources, self-loops left out, as ``gcn_norm``)."""

    def __init__(self, edge_index: torch.Tensor, num_nodes: int, *, in_degree: torch.Tensor | None = None,
                 first: int = 0):
        self.src = edge_index[0].to(torch.int64).contiguous().numpy()
        self.dst = edge_index[1].to(torch.int64).contiguous().numpy()
        if len(self.dst) and (int(self.dst.min()) < first or int(self.dst.max()) >= num_nodes
                              or int(self.src.min()) < 0 or int(self.src.max()) >= num_nodes):
            raise ValueError(f"every edge must run between nodes 0..{num_nodes - 1} and end at a row from {first}")
        self.degree = distinct_in_degree(self.src, self.dst, num_nodes) if in_degree is None else \
            in_degree.to(torch.int64).contiguous().numpy()  # each node's d^-1/2 is taken in the pass, where read
        self.num_nodes, self.first = num_nodes, first
        self.grouped = bool(_grouped(self.src, self.dst))


@numba.njit(**KERNEL)
def _matmul(a, b):
    """``a @ b`` by loops (no BLAS call: its threads would contend with torch's), the inner one over
    ``b``'s contiguous rows, four rows of ``a`` at a time: each output row is a chain of additions over
    ``k`` whose every step waits for the last, so four independent chains keep the vector units busy
    (1.7-2.4x one row at a time on the GCN blocks' shapes). Each element is still summed over ``k``
    in order, the same value to the bit as one row at a time."""
    n, depth = a.shape
    width = b.shape[1]
    out = np.zeros((n, width), dtype=a.dtype)
    r = 0
    while r + 4 <= n:
        o0, o1, o2, o3 = out[r], out[r + 1], out[r + 2], out[r + 3]
        for k in range(depth):
            v0, v1, v2, v3 = a[r, k], a[r + 1, k], a[r + 2, k], a[r + 3, k]
            row = b[k]
            for c in range(width):
                w = row[c]
                o0[c] += v0 * w
                o1[c] += v1 * w
                o2[c] += v2 * w
                o3[c] += v3 * w
        r += 4
    for r in range(r, n):
        o = out[r]
        for k in range(depth):
            value = a[r, k]
            row = b[k]
            for c in range(width):
                o[c] += value * row[c]
    return out


@numba.njit(**KERNEL)
def _grouped(src, dst):
    """Whether the edges are sorted by (destination, source), as the graph builders and the pooling give them."""
    for e in range(1, len(dst)):
        if dst[e] < dst[e - 1] or (dst[e] == dst[e - 1] and src[e] < src[e - 1]):
            return False
    return True


@numba.njit(**KERNEL)
def _scale(degree, i):
    """``d^-1/2`` of node ``i``, ``d = 1 +`` its in-degree (float64)."""
    return 1.0 / np.sqrt(1.0 + np.float64(degree[i]))


@numba.njit(**KERNEL)
def _gcn_block(x, src, dst, first, degree, grouped, weight, bias, gamma, beta, eps, skip, identity):
    """Rows ``first ..`` of ``relu(layer_norm(A x W + b)) + skip(x)``, ``A = D^-1/2 (A + I) D^-1/2``:
    each row's messages (a repeated edge once, a self-loop through the identity only), then the
    linear layer, the norm over the row, the ReLU and the skip (``x`` itself with ``identity``).
    A row's messages are summed by increasing source: edges ``grouped`` by (destination, source) are
    read in their order, any others in a stable order by source, which sums each row the same way."""
    n, f_in = x.shape
    rows = n - first
    scales = np.empty(n)  # each node's d^-1/2: a square root and a division a node, not two an edge
    for i in range(n):
        scales[i] = _scale(degree, i)
    agg = np.zeros((rows, f_in), dtype=x.dtype)
    for r in range(rows):
        i = first + r
        own = scales[i]
        value = own * own
        for c in range(f_in):
            agg[r, c] = value * x[i, c]
    if grouped:
        for e in range(len(src)):
            s, d = src[e], dst[e]
            if s == d or (e > 0 and s == src[e - 1] and d == dst[e - 1]):
                continue
            value = scales[d] * scales[s]
            r = d - first
            for c in range(f_in):
                agg[r, c] += value * x[s, c]
    else:
        stamp = np.full(n, -1, dtype=np.int64)  # the source a destination last took: a repeat is seen in its group
        for e in counting_order(src, n):
            s, d = src[e], dst[e]
            if s == d or stamp[d] == s:
                continue
            stamp[d] = s
            value = scales[d] * scales[s]
            r = d - first
            for c in range(f_in):
                agg[r, c] += value * x[s, c]
    h = _matmul(agg, weight)
    f_out = h.shape[1]
    own = x[first:]
    extra = own if identity else _matmul(own, skip)
    for r in range(rows):
        mean = 0.0
        for c in range(f_out):
            h[r, c] += bias[c]
            mean += h[r, c]
        mean /= f_out
        var = 0.0
        for c in range(f_out):
            var += (h[r, c] - mean) ** 2
        inv = 1.0 / np.sqrt(var / f_out + eps)
        for c in range(f_out):
            y = (h[r, c] - mean) * inv * gamma[c] + beta[c]
            h[r, c] = (y if y > 0 else 0.0) + extra[r, c]
    return h


# Per block: the dtype, parameters and their versions its arrays were made from, and the arrays.
_ARRAYS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _block_arrays(block, dtype: torch.dtype) -> tuple:
    """``block``'s weight ``(F_in, F_out)``, bias, norm scale and shift, skip weight and whether the skip
    is the identity, as numpy arrays of ``dtype``: made once and kept while no parameter of the block
    is replaced or changed in place (each tensor's version counter says so)."""
    conv, norm = block.conv, block.norm
    params = [conv.weight, conv.bias, norm.weight, norm.bias, getattr(block.skip, "weight", None)]
    if any(t is not None and t.is_inference() for t in params):  # no version counter: made afresh each call
        return _arrays(block, dtype)
    versions = [None if t is None else t._version for t in params]
    kept = _ARRAYS.get(block)
    if (kept is not None and kept[0] == dtype and kept[2] == versions
            and all(a is b for a, b in zip(kept[1], params))):  # the same tensors (kept, so never an id reused)
        return kept[3]
    arrays = _arrays(block, dtype)
    _ARRAYS[block] = (dtype, params, versions, arrays)
    return arrays


def _arrays(block, dtype: torch.dtype) -> tuple:
    conv, norm = block.conv, block.norm
    weight = conv.weight.detach().to(dtype).contiguous().numpy().copy()
    f_out = weight.shape[1]
    bias = (conv.bias.detach().to(dtype) if conv.bias is not None else torch.zeros(f_out, dtype=dtype)).numpy().copy()
    gamma = (norm.weight.detach().to(dtype) if norm.weight is not None else torch.ones(f_out, dtype=dtype)).numpy().copy()
    beta = (norm.bias.detach().to(dtype) if norm.bias is not None else torch.zeros(f_out, dtype=dtype)).numpy().copy()
    identity = isinstance(block.skip, torch.nn.Identity)
    skip = weight[:0] if identity else block.skip.weight.detach().to(dtype).T.contiguous().numpy().copy()
    return weight, bias, gamma, beta, skip, identity


def gcn_block(block, x: torch.Tensor, graph: NodeGraph) -> torch.Tensor:
    """:class:`~dagr_lite.nn.event_branch.GCNBlock` ``block`` (without offsets) on ``x (N, F_in)`` over
    ``graph``, in one compiled pass: rows ``graph.first ..`` of its output, ``(N - first, F_out)``."""
    for observer in OBSERVERS:
        observer(block, x, graph)
    conv, norm = block.conv, block.norm
    if conv.weight_offsets is not None:
        raise ValueError("the compiled GCN block has no offset-weighted messages (a directional first stage)")
    weight, bias, gamma, beta, skip, identity = _block_arrays(block, x.dtype)
    out = _gcn_block(x.detach().contiguous().numpy(), graph.src, graph.dst, graph.first, graph.degree, graph.grouped, weight,
                     bias, gamma, beta, float(norm.eps), skip, identity)
    return torch.from_numpy(out)


@numba.njit(**KERNEL)
def _bilinear(flat, h, w, xy, batch, stride, out):
    """``out[n] =`` the bilinear sample of sample ``batch[n]``'s map in the ``(B h w, C)`` channels-last
    maps at pixel ``xy[n]``, as
    :func:`~dagr_lite.nn.detector.sample_at` computes it (cell ``i`` covers pixels ``[i s, (i + 1) s)``;
    beyond the outer centres, the edge value)."""
    for n in range(len(xy)):
        u = min(max((xy[n, 0] + 0.5) / stride - 0.5, 0.0), w - 1.0)
        v = min(max((xy[n, 1] + 0.5) / stride - 0.5, 0.0), h - 1.0)
        u0, v0 = min(int(np.floor(u)), w - 1), min(int(np.floor(v)), h - 1)
        u1, v1 = min(u0 + 1, w - 1), min(v0 + 1, h - 1)
        fu, fv = u - u0, v - v0
        base = batch[n] * h * w
        a, b, c, d = base + v0 * w + u0, base + v0 * w + u1, base + v1 * w + u0, base + v1 * w + u1
        for k in range(flat.shape[1]):
            top = flat[a, k] * (1 - fu) + flat[b, k] * fu
            bottom = flat[c, k] * (1 - fu) + flat[d, k] * fu
            out[n, k] = top * (1 - fv) + bottom * fv


def channels_last(feature: torch.Tensor) -> np.ndarray:
    """A ``(B, C, h, w)`` map as the ``(B h w, C)`` array :func:`bilinear_at` reads."""
    return feature.detach().permute(0, 2, 3, 1).reshape(-1, feature.shape[1]).contiguous().numpy()


def bilinear_at(flat: np.ndarray, height: int, width: int, xy: torch.Tensor, batch: torch.Tensor,
                stride: int) -> torch.Tensor:
    """:func:`~dagr_lite.nn.detector.sample_at` of maps laid out channels last, ``flat (B h w, C)``
    (:func:`channels_last`), at ``xy (N, 2)`` pixels of samples ``batch (N,)``, in one compiled pass:
    ``(N, C)`` of the maps' dtype."""
    out = np.empty((len(xy), flat.shape[1]), dtype=flat.dtype)
    if len(batch) and (int(batch.min()) < 0 or (int(batch.max()) + 1) * height * width > len(flat)):
        raise ValueError(f"node samples must lie in 0..{len(flat) // (height * width) - 1}")
    _bilinear(flat, height, width, xy.detach().to(torch.float64).contiguous().numpy(),
              batch.to(torch.int64).contiguous().numpy(), float(stride), out)
    return torch.from_numpy(out)
