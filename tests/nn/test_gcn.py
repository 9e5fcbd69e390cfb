import torch

from dagr_lite.graph import radius_graph
from dagr_lite.nn import GCNConv, GraphOperator


def dense_gcn(x, edge_index, weight, bias):
    """Reference: D^-1/2 (A + I) D^-1/2 X W + b with a dense matrix (A[i, j] = 1 for j -> i)."""
    n = x.shape[0]
    a = torch.zeros(n, n, dtype=x.dtype)
    src, dst = edge_index
    keep = src != dst
    a[dst[keep], src[keep]] = 1.0
    a_hat = a + torch.eye(n, dtype=x.dtype)
    d = a_hat.sum(1)  # 1 + in-degree
    norm = d.rsqrt()[:, None] * a_hat * d.rsqrt()[None, :]
    return norm @ x @ weight + bias


def test_four_node_graph_by_hand():
    # 0 -> 2, 1 -> 2, 2 -> 3: degrees d = [1, 1, 3, 2].
    edge_index = torch.tensor([[0, 1, 2], [2, 2, 3]])
    x = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    conv = GCNConv(1, 1, bias=False)
    with torch.no_grad():
        conv.weight.fill_(1.0)
    out = conv(x, edge_index).flatten()
    expected = [1.0, 2.0, 1 / 3 ** 0.5 + 2 / 3 ** 0.5 + 3 / 3, 3 / 6 ** 0.5 + 4 / 2]
    assert torch.allclose(out, torch.tensor(expected))


def test_output_and_gradients_equal_the_dense_reference():
    g = torch.Generator().manual_seed(0)
    for in_c, out_c in ((3, 5), (6, 2)):  # propagation before and after the weight
        n = 40
        edge_index = torch.randint(0, n, (2, 150), generator=g)  # repeated edges and self-loops included
        x = torch.randn(n, in_c, generator=g, dtype=torch.float64, requires_grad=True)
        conv = GCNConv(in_c, out_c).double()
        with torch.no_grad():
            conv.bias.normal_(generator=g)
        out = conv(x, GraphOperator(edge_index, n))  # float64 input: propagates in float64
        x_ref = x.detach().clone().requires_grad_(True)
        w_ref = conv.weight.detach().clone().requires_grad_(True)
        b_ref = conv.bias.detach().clone().requires_grad_(True)
        ref = dense_gcn(x_ref, edge_index, w_ref, b_ref)
        assert torch.allclose(out, ref)
        upstream = torch.randn(n, out_c, generator=g, dtype=torch.float64)
        (out * upstream).sum().backward()
        (ref * upstream).sum().backward()
        assert torch.allclose(x.grad, x_ref.grad)
        assert torch.allclose(conv.weight.grad, w_ref.grad)
        assert torch.allclose(conv.bias.grad, b_ref.grad)


def test_float32_layer_matches_the_reference_closely():
    g = torch.Generator().manual_seed(1)
    pos = torch.rand(300, 3, generator=g) * 10
    pos = pos[torch.argsort(pos[:, 2])]
    edge_index = radius_graph(pos, 2.0, 8)
    x = torch.randn(300, 8, generator=g)
    conv = GCNConv(8, 16)
    assert torch.allclose(conv(x, edge_index), dense_gcn(x, edge_index, conv.weight, conv.bias), atol=1e-5)


def test_new_nodes_from_cached_features_equal_the_whole_window():
    g = torch.Generator().manual_seed(2)
    n, new = 200, 30
    pos = torch.rand(n, 3, generator=g) * 8
    pos = pos[torch.argsort(pos[:, 2])]
    edge_index = radius_graph(pos, 2.0, 6)
    conv1, conv2 = GCNConv(4, 8), GCNConv(8, 8, residual=True)
    x = torch.randn(n, 4, generator=g)
    full_op = GraphOperator(edge_index, n)
    h1 = torch.relu(conv1(x, full_op))
    h2 = conv2(h1, full_op)
    # Streaming: the old nodes' features are cached; only the edges into the new nodes and the
    # cached in-degrees are needed.
    rows = torch.arange(n - new, n)
    into_new = edge_index[:, edge_index[1] >= n - new]
    in_degree = torch.bincount(edge_index[1], minlength=n)
    op_new = GraphOperator(into_new, n, in_degree=in_degree, rows=rows)
    h1_new = torch.relu(conv1(x, op_new))
    h1_stream = torch.cat([h1[: n - new], h1_new])  # cached old rows + new rows
    h2_new = conv2(h1_stream, op_new)
    assert torch.allclose(h1_new, h1[n - new:], atol=1e-6)
    assert torch.allclose(h2_new, h2[n - new:], atol=1e-6)


def test_any_float_dtype_propagates():
    edge_index = torch.tensor([[0, 1, 2], [2, 2, 3]])
    op = GraphOperator(edge_index, 4)
    x = torch.randn(4, 3, dtype=torch.float64)
    reference = op.propagate(x)
    assert reference.dtype == torch.float64
    for dtype in (torch.float32, torch.bfloat16):
        out = op.propagate(x.to(dtype))
        assert out.dtype == dtype and torch.allclose(out.double(), reference, atol=0.05)
