"""The causal GCN layer as one sparse matrix product per layer (docs/design.md, "The event graph").

``h_i' = W * sum_{j in N(i) + {i}} h_j / sqrt(d_i * d_j)`` with ``d = 1 + in-degree``. A node's
in-degree is fixed when it arrives (its edges come from earlier nodes only), so a node's output
never changes afterwards, and computing the new nodes alone gives exactly what the whole
window gives.
"""
from __future__ import annotations

import math
import warnings

import torch
from torch import nn

from dagr_lite.graph.sparse import (causal_triplets, compiled_for, distinct_in_degree, norm_triplets,
                                    transpose_triplets)


def gcn_norm(edge_index: torch.Tensor, num_nodes: int, *, in_degree: torch.Tensor | None = None,
             rows: torch.Tensor | None = None):
    """Triplets ``(row, col, value)`` of ``D^-1/2 (A + I) D^-1/2`` (rows = destinations).

    Self-loops in ``edge_index`` are dropped (the identity adds the one self-loop of each node)
    and a repeated edge counts once.

    Args:
        edge_index: ``(2, E)`` int64, sources in row 0, destinations in row 1.
        num_nodes: number of nodes ``N``.
        in_degree: ``(N,)`` in-degree of every node; counted from ``edge_index`` when omitted.
            Give it when ``edge_index`` holds only the edges into some nodes (streaming).
        rows: destination nodes to keep (default: all); output rows are numbered by their
            position in ``rows``.

    Returns:
        ``row (E',)``, ``col (E',)``, ``value (E',)`` float64, sorted by (row, col).
    """
    src, dst = edge_index[0], edge_index[1]
    if rows is None and _sorted_causal(src, dst, num_nodes):
        return _norm_sorted_causal(src, dst, num_nodes, in_degree)
    if compiled_for(src) and _within(num_nodes, src, dst, rows):  # one compiled pass each, the same triplets
        src_np, dst_np = src.contiguous().numpy(), dst.contiguous().numpy()
        if in_degree is None:
            in_degree = torch.from_numpy(distinct_in_degree(src_np, dst_np, num_nodes))
        deg_inv_sqrt = (1.0 + in_degree.to(torch.float64)).rsqrt()
        kept = torch.arange(num_nodes) if rows is None else rows
        return tuple(torch.from_numpy(a) for a in norm_triplets(src_np, dst_np, kept.contiguous().numpy(),
                                                                deg_inv_sqrt.contiguous().numpy()))
    keep = src != dst
    src, dst = src[keep], dst[keep]
    if in_degree is None:
        unique = torch.unique(dst * num_nodes + src)
        in_degree = torch.bincount(torch.div(unique, num_nodes, rounding_mode="floor"), minlength=num_nodes)
    deg_inv_sqrt = (1.0 + in_degree.to(torch.float64)).rsqrt()  # (N,)
    if rows is None:
        rows = torch.arange(num_nodes, device=edge_index.device)
    position = torch.full((num_nodes,), -1, dtype=torch.int64, device=edge_index.device)
    position[rows] = torch.arange(len(rows), device=edge_index.device)
    in_rows = position[dst] >= 0
    src, dst = src[in_rows], dst[in_rows]
    row = torch.cat([position[dst], torch.arange(len(rows), device=edge_index.device)])
    col = torch.cat([src, rows])
    value = deg_inv_sqrt[torch.cat([dst, rows])] * deg_inv_sqrt[col]  # float64
    key = row * num_nodes + col
    order = torch.argsort(key)
    first = torch.ones(len(order), dtype=torch.bool, device=key.device)
    first[1:] = key[order][1:] != key[order][:-1]  # a repeated edge counts once: N(i) is a set
    order = order[first]
    return row[order], col[order], value[order]


def _within(num_nodes: int, *ids: torch.Tensor | None) -> bool:
    """Whether every id given is a node, ``0 <= id < num_nodes``: the compiled passes do not check
    (an id outside would write outside their arrays); the tensor expression raises an IndexError."""
    return all(i is None or not len(i) or (int(i.min()) >= 0 and int(i.max()) < num_nodes) for i in ids)


def _sorted_causal(src: torch.Tensor, dst: torch.Tensor, num_nodes: int) -> bool:
    """Whether edges are unique, sorted by (dst, src) and all from earlier nodes (as radius_graph gives)."""
    if len(src) == 0:
        return True
    key = dst * num_nodes + src
    return bool((key[1:] > key[:-1]).all()) and bool((src < dst).all())


def _norm_sorted_causal(src: torch.Tensor, dst: torch.Tensor, num_nodes: int, in_degree: torch.Tensor | None):
    """:func:`gcn_norm` without sorting: each node's self-loop follows its incoming edges, which
    all come from smaller indices. Edge ``e`` moves to ``e + dst[e]`` (one self-loop per earlier row)."""
    device = src.device
    counts = torch.bincount(dst, minlength=num_nodes)  # (N,)
    deg_inv_sqrt = (1.0 + (counts if in_degree is None else in_degree).to(torch.float64)).rsqrt()
    if compiled_for(src):  # one compiled pass, the same triplets (graph/sparse.py)
        return tuple(torch.from_numpy(a) for a in causal_triplets(src.contiguous().numpy(), dst.contiguous().numpy(),
                                                                  deg_inv_sqrt.numpy()))
    total = len(src) + num_nodes
    row = torch.empty(total, dtype=torch.int64, device=device)
    col = torch.empty(total, dtype=torch.int64, device=device)
    nodes = torch.arange(num_nodes, device=device)
    edge_pos = torch.arange(len(src), device=device) + dst
    self_pos = torch.cumsum(counts, 0) + nodes
    row[edge_pos], col[edge_pos] = dst, src
    row[self_pos], col[self_pos] = nodes, nodes
    return row, col, deg_inv_sqrt[row] * deg_inv_sqrt[col]


def _csr(row: torch.Tensor, col: torch.Tensor, value: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """CSR matrix from triplets sorted by (row, col)."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=row.device)
    crow[1:] = torch.cumsum(torch.bincount(row, minlength=shape[0]), 0)
    return _csr_tensor(crow, col, value, shape)


def _csr_tensor(crow: torch.Tensor, col: torch.Tensor, value: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, value, shape, check_invariants=False)


class GraphOperator:
    """The normalised propagation matrix of one graph, prepared once and shared by all layers.

    Holds ``adj`` = ``D^-1/2 (A + I) D^-1/2`` restricted to the output rows, as CSR, and its
    transpose (also CSR) for the backward pass, so both directions are one sparse product.

    With ``offset_pos`` ``(N, 3)`` (node positions), it also holds the offset of each entry's
    source from its destination, ``(offset_pos[j] - offset_pos[i]) / offset_unit``, for
    :meth:`propagate_offsets`.

    Shapes:
        adj ``(N_out, N)``, adj_t ``(N, N_out)``; ``N_out = N`` unless ``rows`` was given.
    """

    def __init__(self, edge_index: torch.Tensor, num_nodes: int, *, in_degree: torch.Tensor | None = None,
                 rows: torch.Tensor | None = None, offset_pos: torch.Tensor | None = None, offset_unit: float = 1.0):
        row, col, value = gcn_norm(edge_index, num_nodes, in_degree=in_degree, rows=rows)
        n_out = num_nodes if rows is None else len(rows)
        self.num_nodes, self.num_out, self.rows = num_nodes, n_out, rows
        self._triplets = (row, col, value)
        self._offsets = None
        if offset_pos is not None:  # each entry's source minus its destination (a self-loop's is 0)
            dst = row if rows is None else rows[row]
            self._offsets = (offset_pos[col] - offset_pos[dst]).to(torch.float64) / offset_unit  # (E', 3)
        self._order: torch.Tensor | None = None  # (col, row) order of the triplets, for the transpose
        self._adj: dict[tuple[torch.dtype, int], torch.Tensor] = {}
        self._adj_t: dict[tuple[torch.dtype, int], torch.Tensor] = {}

    def _values(self, k: int) -> torch.Tensor:
        """The entries of ``adj`` (``k = 0``) or of ``adj`` weighted by the offset along x, y or t
        (``k = 1, 2, 3``), in the order of the triplets."""
        value = self._triplets[2]
        if k == 0:
            return value
        if self._offsets is None:
            raise ValueError("this graph operator was made without offset_pos, so it has no offset-weighted matrices")
        return value * self._offsets[:, k - 1]

    def matrix(self, dtype: torch.dtype, k: int = 0) -> torch.Tensor:
        """``adj`` (or its offset-weighted ``k``-th form, see :meth:`_values`) as CSR of ``dtype``,
        made once per dtype; all four share one index structure."""
        if (dtype, k) not in self._adj:
            if k:
                self._adj[dtype, k] = _with_values(self.matrix(dtype), self._values(k).to(dtype))
            else:
                row, col, value = self._triplets
                self._adj[dtype, 0] = _csr(row, col, value.to(dtype), (self.num_out, self.num_nodes))
        return self._adj[dtype, k]

    def transposed(self, dtype: torch.dtype, k: int = 0) -> torch.Tensor:
        """The transpose of :meth:`matrix` as CSR, made on first use (only the backward pass needs it)."""
        if (dtype, k) not in self._adj_t:
            if k:
                base = self.transposed(dtype)  # sets the order
                self._adj_t[dtype, k] = _with_values(base, self._values(k)[self._order].to(dtype))
            else:
                row, col, value = self._triplets
                shape = (self.num_nodes, self.num_out)
                if compiled_for(col):  # one counting pass, the same matrix (graph/sparse.py)
                    crow, rows, values, order = (torch.from_numpy(a) for a in transpose_triplets(
                        row.contiguous().numpy(), col.contiguous().numpy(), value.contiguous().numpy(), self.num_nodes))
                    self._order = order
                    self._adj_t[dtype, 0] = _csr_tensor(crow, rows, values.to(dtype), shape)
                else:
                    if self._order is None:
                        self._order = torch.argsort(col, stable=True)  # rows ascend within each column
                    order = self._order
                    self._adj_t[dtype, 0] = _csr(col[order], row[order], value[order].to(dtype), shape)
        return self._adj_t[dtype, k]

    def propagate(self, x: torch.Tensor) -> torch.Tensor:
        """``adj @ x`` with a sparse backward (``adj_t @ grad``).  ``(N, F) -> (N_out, F)``.

        float64 inputs propagate in float64; all others (float16, bfloat16 under autocast) in
        float32, and the result comes back in the input's dtype.
        """
        return _Propagate.apply(x, self, (0,))

    def propagate_offsets(self, x: torch.Tensor) -> torch.Tensor:
        """``adj @ x`` and the same sums with each neighbour's term weighted by its offset from the
        destination along x, y and t (``offset_pos[j] - offset_pos[i]``): ``(N, F) -> (4, N_out, F)``."""
        return _Propagate.apply(x, self, (0, 1, 2, 3))


def _with_values(base: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """A CSR matrix with ``base``'s index structure and other ``values``."""
    return _csr_tensor(base.crow_indices(), base.col_indices(), values, tuple(base.shape))


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


class _Propagate(torch.autograd.Function):
    """``adj_k @ x`` for each ``k`` of ``forms`` (:meth:`GraphOperator.matrix`): ``(N_out, F)`` for
    one form, ``(len(forms), N_out, F)`` for several; the backward sums ``adj_k^T @ grad_k``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, op: GraphOperator, forms: tuple[int, ...]) -> torch.Tensor:
        ctx.op, ctx.forms = op, forms
        dtype, given = _compute_dtype(x.dtype), x.dtype
        with torch.autocast(x.device.type, enabled=False):  # sparse products stay in float32/64
            x = x.to(dtype)
            out = [op.matrix(dtype, k) @ x for k in forms]
            return (out[0] if len(forms) == 1 else torch.stack(out)).to(given)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        dtype = _compute_dtype(grad.dtype)
        with torch.autocast(grad.device.type, enabled=False):
            parts = grad.to(dtype).unsqueeze(0) if len(ctx.forms) == 1 else grad.to(dtype)
            total = None
            for k, part in zip(ctx.forms, parts):
                term = ctx.op.transposed(dtype, k) @ part.contiguous()  # (N, F)
                total = term if total is None else total + term
            return total.to(grad.dtype), None, None


class GCNConv(nn.Module):
    """Causal graph convolution ``h' = D^-1/2 (A + I) D^-1/2 h W + b`` (+ ``h`` with ``residual``).

    Propagation runs on the narrower side of ``W`` (before the weight when ``in <= out``, after
    it otherwise): the same result with fewer sparse multiply-adds.

    With ``offsets``, a neighbour's message also depends on where it lies: ``h_i' = sum_j a_ij h_j
    (W + dx_ij W_x + dy_ij W_y + dt_ij W_t) + b``, with ``(dx, dy, dt)_ij`` the offset of ``j`` from
    ``i`` that the :class:`GraphOperator` was given (``offset_pos``), a Cartesian kernel of degree
    one as SplineConv's: the layer can tell from which side and how long before an input arrived,
    so it senses the direction of motion that the isotropic sum cannot. ``a_ij`` and the offsets
    are fixed when node ``i`` arrives, so its output still never changes afterwards.

    Args:
        in_channels, out_channels: feature sizes.
        bias: add a learned bias.
        residual: add the input (projected by a bias-free linear map if the sizes differ).
        offsets: the messages also weighted by the offsets (``weight_offsets``, ``(3, F_in, F_out)``).

    Shapes:
        x ``(|V|, F_in)``, edge_index ``(2, |E|)`` or a :class:`GraphOperator` -> ``(|V_out|, F_out)``.
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True, residual: bool = False,
                 offsets: bool = False):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.weight = nn.Parameter(torch.empty(in_channels, out_channels))
        self.weight_offsets = nn.Parameter(torch.empty(3, in_channels, out_channels)) if offsets else None
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None
        self.residual = None
        if residual:
            self.residual = nn.Identity() if in_channels == out_channels else nn.Linear(in_channels, out_channels,
                                                                                         bias=False)
        nn.init.kaiming_uniform_(self.weight.T, a=math.sqrt(5))
        if self.weight_offsets is not None:
            with torch.no_grad():
                for k in range(3):
                    nn.init.kaiming_uniform_(self.weight_offsets[k].T, a=math.sqrt(5))

    def forward(self, x: torch.Tensor, graph: torch.Tensor | GraphOperator) -> torch.Tensor:
        op = graph if isinstance(graph, GraphOperator) else GraphOperator(graph, x.shape[0])
        if self.weight_offsets is not None:
            sums = op.propagate_offsets(x)  # (4, N_out, F_in)
            out = sums[0] @ self.weight + torch.bmm(sums[1:], self.weight_offsets).sum(dim=0)  # (N_out, F_out)
        elif self.in_channels <= self.out_channels:
            out = op.propagate(x) @ self.weight  # (N_out, F_out)
        else:
            out = op.propagate(x @ self.weight)  # (N_out, F_out)
        if self.bias is not None:
            out = out + self.bias
        if self.residual is not None:
            out = out + self.residual(x if op.rows is None else x[op.rows])
        return out

    def extra_repr(self) -> str:
        return (f"{self.in_channels}, {self.out_channels}, bias={self.bias is not None}, "
                f"residual={self.residual is not None}, offsets={self.weight_offsets is not None}")
