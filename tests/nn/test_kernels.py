"""The compiled GCN block and image sampling against the tensor operations they replace in inference."""
import numpy as np
import pytest
import torch

from dagr_lite.nn.detector import sample_at
from dagr_lite.nn.event_branch import GCNBlock
from dagr_lite.nn.gcn import GraphOperator
from dagr_lite.nn.kernels import NodeGraph, _matmul, bilinear_at, channels_last, compiled_inference, gcn_block

TOLERANCE = {torch.float64: 1e-9, torch.float32: 1e-5}


def random_graph(n: int, e: int, seed: int) -> torch.Tensor:
    """Edges with repeats and self-loops, in no order (what gcn_norm accepts)."""
    g = torch.Generator().manual_seed(seed)
    src = torch.randint(0, n, (e,), generator=g)
    dst = torch.randint(0, n, (e,), generator=g)
    edges = torch.stack([src, dst])
    return torch.cat([edges, edges[:, :e // 5], torch.stack([src[:7], src[:7]])], dim=1)  # repeats, self-loops


def trained_looking(block: GCNBlock, seed: int) -> GCNBlock:
    """Non-trivial norm and bias parameters (a fresh block has ones and zeros)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in (block.conv.bias, block.norm.weight, block.norm.bias):
            p.copy_(torch.randn(p.shape, generator=g))
    return block.eval()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("f_in,f_out", [(24, 32), (32, 32), (22, 16)])
def test_gcn_block_equals_the_tensor_block(dtype, f_in, f_out):
    torch.manual_seed(0)
    block = trained_looking(GCNBlock(f_in, f_out), 1).to(dtype)
    n = 300
    x = torch.randn(n, f_in, dtype=dtype)
    edges = random_graph(n, 2000, 2)
    with torch.no_grad():
        want = block(x, GraphOperator(edges, n))
        got = gcn_block(block, x, NodeGraph(edges, n))
    assert got.dtype == dtype and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gcn_block_of_the_newest_rows_with_given_in_degrees(dtype):
    """The streaming form: the edges into the last rows only, every node's in-degree given."""
    torch.manual_seed(0)
    block = trained_looking(GCNBlock(22, 16), 3).to(dtype)
    n, first = 400, 330
    x = torch.randn(n, 22, dtype=dtype)
    src = torch.randint(0, n - 1, (3000,))
    dst = src + 1 + torch.randint(0, 40, (3000,))
    keep = dst < n
    key = torch.unique(dst[keep] * n + src[keep])  # distinct causal edges, as the graph builder gives
    edges = torch.stack([key % n, key // n])
    in_degree = torch.bincount(edges[1], minlength=n)
    tail = edges[:, edges[1] >= first]
    rows = torch.arange(first, n)
    with torch.no_grad():
        want = block(x, GraphOperator(tail, n, in_degree=in_degree, rows=rows))
        got = gcn_block(block, x, NodeGraph(tail, n, in_degree=in_degree, first=first))
    torch.testing.assert_close(got, want, rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype])
    # and the same rows of a pass over the whole graph
    with torch.no_grad():
        whole = block(x, GraphOperator(edges, n))[first:]
    torch.testing.assert_close(got, whole, rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype])


def test_gcn_block_projecting_skip_and_a_node_without_edges():
    block = trained_looking(GCNBlock(5, 7), 4).double()
    x = torch.randn(3, 5, dtype=torch.float64)
    edges = torch.tensor([[0], [1]])  # node 2 has none: its own message alone
    with torch.no_grad():
        got = gcn_block(block, x, NodeGraph(edges, 3))
        conv = block.conv
        # by hand: d = (1, 2, 1); row 2 is relu(norm(x2 W + b)) + x2 S
        h2 = x[2] @ conv.weight + conv.bias
        want2 = torch.relu(block.norm(h2)) + x[2] @ block.skip.weight.T
    torch.testing.assert_close(got[2], want2, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gcn_block_reads_grouped_edges_in_order_to_the_bit(dtype):
    """Edges sorted by (destination, source), as the builders give them, are read in their order; any other
    order by source: each row is summed by increasing source either way, so the outputs are equal to the bit."""
    torch.manual_seed(0)
    block = trained_looking(GCNBlock(10, 12), 8).to(dtype)
    n = 200
    x = torch.randn(n, 10, dtype=dtype)
    edges = random_graph(n, 1500, 9)  # repeats and self-loops
    key = torch.sort(edges[1] * n + edges[0]).values
    grouped = torch.stack([key % n, key // n])
    shuffled = grouped[:, torch.randperm(grouped.shape[1])]
    a, b = NodeGraph(grouped, n), NodeGraph(shuffled, n)
    assert a.grouped and not b.grouped
    with torch.no_grad():
        assert torch.equal(gcn_block(block, x, a), gcn_block(block, x, b))


def test_gcn_block_reads_changed_and_replaced_parameters():
    """The numpy weights kept between calls follow an in-place change, a replaced parameter and the dtype."""
    torch.manual_seed(0)
    block = trained_looking(GCNBlock(12, 12), 5).double()
    n = 60
    x = torch.randn(n, 12, dtype=torch.float64)
    edges = random_graph(n, 300, 6)

    def check(inputs):
        with torch.no_grad():
            want = block(inputs.double(), GraphOperator(edges, n))
            got = gcn_block(block, inputs, NodeGraph(edges, n))
        assert got.dtype == inputs.dtype
        torch.testing.assert_close(got.double(), want, rtol=TOLERANCE[inputs.dtype], atol=TOLERANCE[inputs.dtype])

    check(x)
    with torch.no_grad():
        block.conv.weight.mul_(-2.0)  # in place: a new version of the same tensor
        block.norm.bias.add_(0.5)
    check(x)
    block.conv.weight = torch.nn.Parameter(torch.randn_like(block.conv.weight))  # another tensor
    check(x)
    check(x.float())  # the same block's arrays in another dtype
    with torch.inference_mode():  # inference tensors have no version counter: read afresh
        frozen = trained_looking(GCNBlock(12, 12), 7).double()
    with torch.inference_mode():
        want = frozen(x, GraphOperator(edges, n))
        got = gcn_block(frozen, x, NodeGraph(edges, n))
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows", [1, 4, 7, 13])
def test_the_loop_matrix_product_sums_each_element_in_order_to_the_bit(dtype, rows):
    """Four rows at a time (and the rows left over): each element the sum over k in order of its
    products, rounded at every step as one scalar at a time would round it."""
    rng = np.random.default_rng(rows)
    a, b = rng.standard_normal((rows, 11)).astype(dtype), rng.standard_normal((11, 6)).astype(dtype)
    want = np.zeros((rows, 6), dtype=dtype)
    for r in range(rows):
        for c in range(6):
            total = dtype(0)
            for k in range(11):
                total = dtype(total + dtype(a[r, k] * b[k, c]))
            want[r, c] = total
    got = _matmul(a, b)
    assert got.dtype == dtype and np.array_equal(got, want)


def test_node_graph_refuses_an_edge_outside():
    with pytest.raises(ValueError, match="between nodes 0..2"):
        NodeGraph(torch.tensor([[0], [3]]), 3)
    with pytest.raises(ValueError, match="row from 2"):
        NodeGraph(torch.tensor([[0], [1]]), 3, first=2)


def test_compiled_inference_only_without_gradients():
    x = torch.zeros(2, 2)  # an input wants no gradient, but the weights reading it may
    assert not compiled_inference(x)
    with torch.no_grad():
        assert compiled_inference(x)
        assert not compiled_inference(torch.zeros(2, 2, dtype=torch.bfloat16))
    with torch.inference_mode():
        assert compiled_inference(x)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_bilinear_at_equals_sample_at(dtype):
    torch.manual_seed(0)
    feature = torch.randn(3, 6, 12, 20, dtype=dtype)
    xy = torch.rand(500, 2, dtype=dtype) * torch.tensor([170.0, 110.0], dtype=dtype) - 5  # beyond the edges too
    batch = torch.randint(0, 3, (500,))
    want = sample_at(feature, xy, batch, 8)
    got = bilinear_at(channels_last(feature), 12, 20, xy, batch, 8)
    torch.testing.assert_close(got, want, rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype])
    assert np.isfinite(got.numpy()).all()


def test_bilinear_at_refuses_a_sample_outside():
    with pytest.raises(ValueError, match="0..0"):
        bilinear_at(np.zeros((4, 2), np.float32), 2, 2, torch.zeros(1, 2), torch.tensor([1]), 8)
