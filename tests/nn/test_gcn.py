import pytest
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


def loop_offset_gcn(x, edge_index, pos, unit, conv):
    """Reference for ``GCNConv(offsets=True)``: a loop over each node's set of neighbours (and
    itself), each message ``h_j (W + dx W_x + dy W_y + dt W_t)`` with the offset of ``j`` from ``i``."""
    n = x.shape[0]
    neighbours = [{i} for i in range(n)]
    for j, i in edge_index.T.tolist():
        neighbours[i].add(j)
    degree = [len(s) for s in neighbours]  # 1 + in-degree (a repeated edge or a self-loop counts once)
    rows = []
    for i in range(n):
        total = conv.bias.clone()
        for j in neighbours[i]:
            d = (pos[j] - pos[i]) / unit
            weight = conv.weight + d[0] * conv.weight_offsets[0] + d[1] * conv.weight_offsets[1] + d[2] * conv.weight_offsets[2]
            total = total + x[j] @ weight / (degree[i] * degree[j]) ** 0.5
        rows.append(total)
    return torch.stack(rows)


def test_offset_weighted_messages_equal_a_loop_over_neighbours_with_gradients():
    g = torch.Generator().manual_seed(3)
    n = 30
    pos = torch.rand(n, 3, generator=g, dtype=torch.float64) * 6
    edge_index = torch.randint(0, n, (2, 120), generator=g)  # repeated edges and self-loops included
    conv = GCNConv(5, 4, offsets=True).double()
    with torch.no_grad():
        conv.bias.normal_(generator=g)
    x = torch.randn(n, 5, generator=g, dtype=torch.float64, requires_grad=True)
    out = conv(x, GraphOperator(edge_index, n, offset_pos=pos, offset_unit=2.5))
    ref = loop_offset_gcn(x, edge_index, pos, 2.5, conv)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    upstream = torch.randn(n, 4, generator=g, dtype=torch.float64)
    grads = torch.autograd.grad((out * upstream).sum(), [x, conv.weight, conv.weight_offsets, conv.bias])
    grads_ref = torch.autograd.grad((ref * upstream).sum(), [x, conv.weight, conv.weight_offsets, conv.bias])
    for got, want in zip(grads, grads_ref):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert conv.weight_offsets.abs().sum() > 0 and grads[2].abs().sum() > 0  # the offsets take part
    zero = GCNConv(5, 4, offsets=True).double()  # with no offset weights it is the plain layer
    plain = GCNConv(5, 4).double()
    with torch.no_grad():
        zero.weight.copy_(plain.weight)
        zero.weight_offsets.zero_()
    torch.testing.assert_close(zero(x, GraphOperator(edge_index, n, offset_pos=pos)), plain(x, edge_index))


def test_offset_weighted_messages_of_new_nodes_equal_the_whole_window():
    g = torch.Generator().manual_seed(4)
    n, new = 200, 30
    pos = torch.rand(n, 3, generator=g, dtype=torch.float64) * 8
    pos = pos[torch.argsort(pos[:, 2])]
    edge_index = radius_graph(pos, 2.0, 6)
    conv = GCNConv(4, 8, offsets=True).double()
    x = torch.randn(n, 4, generator=g, dtype=torch.float64)
    whole = conv(x, GraphOperator(edge_index, n, offset_pos=pos, offset_unit=2.0))
    rows = torch.arange(n - new, n)
    op_new = GraphOperator(edge_index[:, edge_index[1] >= n - new], n, in_degree=torch.bincount(edge_index[1], minlength=n),
                           rows=rows, offset_pos=pos, offset_unit=2.0)
    torch.testing.assert_close(conv(x, op_new), whole[n - new:], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="made without offset_pos"):
        conv(x, GraphOperator(edge_index, n))
