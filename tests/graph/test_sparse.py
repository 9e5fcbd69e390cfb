"""The compiled index passes give exactly what the tensor expressions they replace give."""
import numpy as np
import pytest
import torch

from dagr_lite.graph.pool import voxel_max_pool
from dagr_lite.graph.radius import radius_graph
from dagr_lite.graph import sparse
from dagr_lite.graph.sparse import (causal_triplets, counting_order, distinct_in_degree, norm_triplets,
                                    transpose_triplets, unique_inverse, unique_pairs)
import dagr_lite.nn.gcn as gcn_module
from dagr_lite.nn.gcn import GraphOperator, gcn_norm


@pytest.mark.parametrize("n, size", [(0, 5), (1, 1), (50, 3), (2000, 97), (5000, 5000)])
def test_counting_order_is_a_stable_argsort(n, size):
    keys = torch.from_numpy(np.random.default_rng(n).integers(0, size, n))
    assert torch.equal(torch.from_numpy(counting_order(keys.numpy(), size)), torch.argsort(keys, stable=True))


@pytest.mark.parametrize("n, size", [(0, 4), (1, 1), (300, 40), (4000, 30000)])
def test_unique_inverse_is_torch_unique(n, size):
    keys = torch.from_numpy(np.random.default_rng(n).integers(0, size, n))
    unique, inverse = unique_inverse(keys.numpy(), size)
    expected, expected_inverse = torch.unique(keys, sorted=True, return_inverse=True)
    assert torch.equal(torch.from_numpy(unique), expected)
    assert torch.equal(torch.from_numpy(inverse), expected_inverse)


def test_unique_inverse_declines_a_sparse_table():
    assert unique_inverse(np.array([0, 10 ** 9], dtype=np.int64), 10 ** 9 + 1) is None


@pytest.mark.parametrize("e, size", [(0, 3), (1, 1), (500, 20), (20000, 700)])
def test_unique_pairs_is_torch_unique_of_the_keys(e, size):
    rng = np.random.default_rng(e)
    src, dst = (torch.from_numpy(rng.integers(0, size, e)) for _ in range(2))
    key = torch.unique(dst * size + src, sorted=True)
    got_src, got_dst = unique_pairs(src.numpy(), dst.numpy(), size)
    assert torch.equal(torch.from_numpy(got_src), key % size)
    assert torch.equal(torch.from_numpy(got_dst), key // size)


def causal_graph(n: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 20000, n))
    pos = torch.from_numpy(np.stack([rng.integers(0, 30, n), rng.integers(0, 20, n), 5e-4 * t], 1).astype(np.float64))
    return radius_graph(pos, 5.0, 16, None)


@pytest.mark.parametrize("n", [1, 2, 40, 3000])
def test_causal_triplets_equal_the_sorting_normalisation(n):
    edge_index = causal_graph(n, n)
    counts = torch.bincount(edge_index[1], minlength=n)
    scale = (1.0 + counts.to(torch.float64)).rsqrt()
    got = causal_triplets(edge_index[0].numpy(), edge_index[1].numpy(), scale.numpy())
    # rows given: the general path, which sorts the triplets and drops repeats
    expected = gcn_norm(edge_index, n, rows=torch.arange(n))
    for a, b in zip(got, expected):
        assert torch.equal(torch.from_numpy(a), b)
    assert torch.equal(torch.stack(gcn_norm(edge_index, n)[:2]), torch.stack(expected[:2]))


def test_graph_operator_matches_dense_matrices_both_ways():
    n = 500
    edge_index = causal_graph(n, 7)
    dense = torch.zeros(n, n, dtype=torch.float64)
    dense[edge_index[1], edge_index[0]] = 1.0
    dense += torch.eye(n, dtype=torch.float64)
    scale = dense.sum(1).rsqrt()
    dense = scale[:, None] * dense * scale[None, :]
    op = GraphOperator(edge_index, n)
    assert torch.allclose(op.matrix(torch.float64).to_dense(), dense, rtol=0, atol=1e-15)
    assert torch.allclose(op.transposed(torch.float64).to_dense(), dense.T, rtol=0, atol=1e-15)


def pool_by_sorting(x, pos, batch, edge_index, size):
    """voxel_max_pool's cells and cell edges by torch.unique (its expression on other devices)."""
    col = torch.div(pos[:, 0], size, rounding_mode="floor").long()
    row = torch.div(pos[:, 1], size, rounding_mode="floor").long()
    width, height = int(col.max()) + 1, int(row.max()) + 1
    unique, cluster = torch.unique((batch * height + row) * width + col, sorted=True, return_inverse=True)
    edges = cluster[edge_index]
    key = torch.unique(edges[1] * len(unique) + edges[0], sorted=True)
    return cluster, torch.stack([key % len(unique), key // len(unique)])


@pytest.mark.parametrize("size", [4.0, 8.0, 16.0])
def test_voxel_pool_cells_and_edges_equal_sorting(size):
    rng = np.random.default_rng(int(size))
    n = 4000
    batch = torch.from_numpy(np.sort(rng.integers(0, 3, n)))
    t = torch.from_numpy(rng.uniform(0, 30000, n))
    order = torch.argsort(batch * 1e6 + t)
    batch, t = batch[order], t[order]
    pos = torch.stack([torch.from_numpy(rng.uniform(0, 160, n)), torch.from_numpy(rng.uniform(0, 96, n)), 5e-4 * t], 1)
    edge_index = radius_graph(pos, 5.0, 16, batch)
    x = torch.randn(n, 6, dtype=torch.float64)
    pooled = voxel_max_pool(x, pos, batch, edge_index, size)
    cluster, cell_edges = pool_by_sorting(x, pos, batch, edge_index, size)
    assert torch.equal(pooled.cluster, cluster)
    assert torch.equal(pooled.edge_index, cell_edges)


def test_transpose_triplets_are_the_sorted_transpose():
    edge_index = causal_graph(800, 3)
    row, col, value = gcn_norm(edge_index, 800)
    crow, rows, values, order = transpose_triplets(row.numpy(), col.numpy(), value.numpy(), 800)
    expected_order = torch.argsort(col, stable=True)
    assert torch.equal(torch.from_numpy(order), expected_order)
    assert torch.equal(torch.from_numpy(rows), row[expected_order])
    assert torch.equal(torch.from_numpy(values), value[expected_order])
    assert torch.equal(torch.from_numpy(crow[1:]), torch.cumsum(torch.bincount(col, minlength=800), 0))
    assert crow[0] == 0


def test_graph_operator_transposes_agree_with_and_without_the_compiled_passes(monkeypatch):
    edge_index = causal_graph(600, 5)
    pos = torch.randn(600, 3, dtype=torch.float64)
    built = {}
    for arm in (True, False):
        monkeypatch.setattr(sparse, "USE_COMPILED", arm)
        op = GraphOperator(edge_index, 600, offset_pos=pos, offset_unit=5.0)
        built[arm] = [op.transposed(torch.float64, k) for k in range(4)] + [op.matrix(torch.float64, k) for k in range(4)]
    for a, b in zip(built[True], built[False]):
        assert torch.equal(a.crow_indices(), b.crow_indices())
        assert torch.equal(a.col_indices(), b.col_indices())
        assert torch.equal(a.values(), b.values())


@pytest.mark.parametrize("e, n", [(0, 4), (1, 1), (300, 40), (5000, 700)])
@pytest.mark.parametrize("rows_kind", ["all", "some", "shuffled"])
@pytest.mark.parametrize("degree_given", [False, True])
def test_general_gcn_norm_is_the_tensor_expression(monkeypatch, e, n, rows_kind, degree_given):
    """Edges in any order, from later nodes too, repeated and with self-loops: the compiled
    triplets (and in-degrees) are the tensor expression's to the bit."""
    rng = np.random.default_rng(e + n)
    src, dst = (torch.from_numpy(rng.integers(0, n, e)) for _ in range(2))
    if e > 10:  # some repeats and self-loops
        src[:5], dst[:5] = src[5:10], dst[5:10]
        src[10] = dst[10]
    edge_index = torch.stack([src, dst])
    rows = {"all": None, "some": torch.arange(n // 3, n - n // 4),
            "shuffled": torch.from_numpy(rng.permutation(n)[: max(1, n // 2)])}[rows_kind]
    in_degree = torch.from_numpy(rng.integers(0, 9, n)) if degree_given else None
    got, calls = {}, []
    monkeypatch.setattr(gcn_module, "norm_triplets", lambda *args: calls.append(1) or norm_triplets(*args))
    for arm in (True, False):
        monkeypatch.setattr(sparse, "USE_COMPILED", arm)
        got[arm] = gcn_norm(edge_index, n, in_degree=in_degree, rows=rows)
    for a, b in zip(got[True], got[False]):
        assert a.dtype == b.dtype
        assert torch.equal(a, b)
    if e > 10 or rows is not None:  # not a sorted causal graph: the compiled arm took the general pass, once
        assert calls == [1]


def test_an_edge_to_no_node_is_an_index_error_not_a_write_outside_the_arrays():
    edge_index = torch.tensor([[3, 0, 1000], [1, 2, 0]])
    with pytest.raises(IndexError):
        gcn_norm(edge_index, 4)
    with pytest.raises(IndexError):
        gcn_norm(torch.tensor([[0], [1]]), 4, rows=torch.tensor([7]), in_degree=torch.zeros(4, dtype=torch.int64))


def test_distinct_in_degree_counts_each_source_once():
    src = np.array([0, 0, 1, 2, 2, 3, 1], dtype=np.int64)
    dst = np.array([1, 1, 1, 2, 0, 0, 3], dtype=np.int64)  # (0 -> 1) twice, a self-loop at 1 and at 2
    assert distinct_in_degree(src, dst, 4).tolist() == [2, 1, 0, 1]
