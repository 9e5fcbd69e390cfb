import math

import pytest
import torch

from dagr_lite.graph import to_dense, voxel_max_pool


def loop_pool(x, pos, batch, edge_index, size):
    """Reference: a plain loop over nodes and edges."""
    cells = {}
    for i in range(len(x)):
        key = (int(batch[i]), math.floor(pos[i, 1] / size), math.floor(pos[i, 0] / size))
        cells.setdefault(key, []).append(i)
    keys = sorted(cells)
    index = {key: c for c, key in enumerate(keys)}
    cluster = [None] * len(x)
    for key, members in cells.items():
        for i in members:
            cluster[i] = index[key]
    feats = torch.stack([torch.stack([x[i] for i in cells[key]]).max(0).values for key in keys])
    mean_pos = torch.stack([torch.stack([pos[i] for i in cells[key]]).mean(0) for key in keys])
    edges = sorted({(cluster[s], cluster[d]) for s, d in edge_index.T.tolist()}, key=lambda e: (e[1], e[0]))
    return keys, feats, mean_pos, cluster, edges


@pytest.mark.parametrize("grad", [False, True])  # the compiled pass (no gradients) and the tensor operations
def test_pooling_and_dense_maps_equal_a_loop(grad):
    g = torch.Generator().manual_seed(0)
    n = 120
    pos = torch.rand(n, 3, generator=g) * torch.tensor([40.0, 30.0, 1.0])
    batch = torch.sort(torch.randint(0, 3, (n,), generator=g)).values
    x = torch.randn(n, 5, generator=g)
    src = torch.randint(0, n, (300,), generator=g)
    dst = torch.randint(0, n, (300,), generator=g)
    same = batch[src] == batch[dst]
    edge_index = torch.stack([src[same], dst[same]])
    with torch.set_grad_enabled(grad):
        pooled = voxel_max_pool(x.requires_grad_(grad), pos, batch, edge_index, 8)
        cells_only = voxel_max_pool(x, pos, batch, None, 8)  # no edges asked for: the same cells, none
    x = x.detach()
    pooled.x, cells_only.x = pooled.x.detach(), cells_only.x.detach()
    keys, feats, mean_pos, cluster, edges = loop_pool(x, pos, batch, edge_index, 8)
    assert pooled.cluster.tolist() == cluster
    assert [tuple(k) for k in torch.cat([pooled.batch[:, None], pooled.cell], 1).tolist()] == keys
    assert torch.equal(pooled.x, feats)
    assert torch.allclose(pooled.pos, mean_pos)
    assert [tuple(e) for e in pooled.edge_index.T.tolist()] == edges
    assert any(s == d for s, d in edges)  # edges inside a cell become kept self-loops
    for name in ("x", "pos", "batch", "cell", "cluster"):
        assert torch.equal(getattr(cells_only, name), getattr(pooled, name)), name
    assert cells_only.edge_index.shape == (2, 0) and cells_only.edge_index.dtype == torch.int64
    dense = to_dense(pooled.x, pooled.batch, pooled.cell, batch_size=3, height=4, width=5)
    expected = torch.zeros(3, 5, 4, 5)
    for c, (b, row, col) in enumerate(keys):
        expected[b, :, row, col] = feats[c]
    assert torch.equal(dense, expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_pooling_equals_the_tensor_operations(dtype):
    """On a CPU without gradients voxel_max_pool is one compiled pass: the same cells, maxima and edges to
    the bit, the same means to rounding, for nodes of several samples at fractional positions."""
    g = torch.Generator().manual_seed(3)
    n = 2000
    pos = (torch.rand(n, 3, generator=g) * torch.tensor([320.0, 180.0, 50.0])).to(dtype)
    batch = torch.sort(torch.randint(0, 4, (n,), generator=g)).values
    x = torch.randn(n, 12, generator=g).to(dtype)
    edges = torch.randint(0, n, (2, 9000), generator=g)
    with torch.no_grad():
        compiled = voxel_max_pool(x, pos, batch, edges, 4)
    with torch.enable_grad():
        tensors = voxel_max_pool(x.clone().requires_grad_(True), pos, batch, edges, 4)
    for name in ("batch", "cell", "cluster", "edge_index"):
        assert torch.equal(getattr(compiled, name), getattr(tensors, name)), name
    assert torch.equal(compiled.x, tensors.x.detach())
    torch.testing.assert_close(compiled.pos, tensors.pos, rtol=1e-12 if dtype == torch.float64 else 1e-6, atol=0)
    with pytest.raises(ValueError, match="non-negative"), torch.no_grad():
        voxel_max_pool(x[:3], -pos[:3], batch[:3], None, 4)


def test_max_pool_gradient_reaches_the_maximum_only():
    x = torch.tensor([[1.0], [3.0], [2.0]], requires_grad=True)
    pos = torch.tensor([[0.0, 0, 0], [1, 1, 0], [9, 0, 0]])
    pooled = voxel_max_pool(x, pos, torch.zeros(3, dtype=torch.int64), torch.zeros((2, 0), dtype=torch.int64), 8)
    pooled.x.sum().backward()
    assert x.grad.flatten().tolist() == [0.0, 1.0, 1.0]


def test_recency_maps_by_hand():
    from dagr_lite.graph.pool import recency_maps
    # sample 0: ON at (3, 2) t=10 and t=40, OFF at (9, 1) t=25; sample 1: ON at (0, 7) t=5
    events = torch.tensor([[3, 2, 10, 1], [9, 1, 25, 0], [3, 2, 40, 1], [0, 7, 5, 1]], dtype=torch.float64)
    batch = torch.tensor([0, 0, 0, 1])
    maps = recency_maps(events, batch, torch.tensor([50.0, 20.0]), batch_size=2, stride=4, height=2, width=3,
                        taus_us=(10.0, 100.0))
    assert maps.shape == (2, 4, 2, 3)  # channels: (tau 10: OFF, ON), (tau 100: OFF, ON)
    expected = torch.zeros(2, 4, 2, 3, dtype=torch.float64)
    for c, tau in ((0, 10.0), (2, 100.0)):
        expected[0, c + 1, 0, 0] = math.exp(-(50 - 40) / tau)  # the latest ON event of cell (0, 0)
        expected[0, c + 0, 0, 2] = math.exp(-(50 - 25) / tau)  # OFF at x 9 -> column 2
        expected[1, c + 1, 1, 0] = math.exp(-(20 - 5) / tau)
    assert torch.allclose(maps, expected)
    empty = recency_maps(events[:0], batch[:0], torch.tensor([1.0]), batch_size=1, stride=4, height=2, width=3,
                         taus_us=(10.0,))
    assert empty.shape == (1, 2, 2, 3) and not empty.any()


def test_add_members_equals_the_tensor_updates():
    """The streaming cells' compiled update against scatter_reduce / index_add / bincount / unique."""
    from dagr_lite.graph.pool import add_members

    g = torch.Generator().manual_seed(0)
    size, channels = 30, 5
    x = torch.full((size, channels), float("-inf"), dtype=torch.float64)
    pos_sum = torch.zeros((size, 3), dtype=torch.float64)
    count = torch.zeros(size, dtype=torch.int64)
    seen = torch.zeros(size * size, dtype=torch.bool)
    want_x, want_pos, want_count, want_keys = x.clone(), pos_sum.clone(), count.clone(), set()
    for _ in range(3):  # batches of members, some cells met again
        m = 40
        features = torch.randn(m, channels, generator=g, dtype=torch.float64)
        pos = torch.rand(m, 3, generator=g, dtype=torch.float64) * 100
        cell = torch.randint(0, size, (m,), generator=g)
        edge_cells = torch.randint(0, size, (2, 90), generator=g)
        new = add_members(x.numpy(), pos_sum.numpy(), count.numpy(), seen.numpy(), features.numpy(), pos.numpy(),
                          cell.numpy(), edge_cells[0].numpy(), edge_cells[1].numpy())
        want_x.scatter_reduce_(0, cell[:, None].expand(-1, channels), features, reduce="amax")
        want_pos.index_add_(0, cell, pos)
        want_count += torch.bincount(cell, minlength=size)
        keys = set((edge_cells[1] * size + edge_cells[0]).tolist())
        assert sorted(new.tolist()) == sorted(keys - want_keys) and len(set(new.tolist())) == len(new)
        want_keys |= keys
    torch.testing.assert_close(x, want_x, rtol=0, atol=0)
    torch.testing.assert_close(pos_sum, want_pos, rtol=1e-12, atol=1e-12)
    assert torch.equal(count, want_count)
    assert set(torch.nonzero(seen).flatten().tolist()) == want_keys


def test_latest_times_equals_recency_cells_and_a_running_max():
    from dagr_lite.graph.pool import latest_times, recency_cells

    g = torch.Generator().manual_seed(1)
    n, h, w, stride = 500, 6, 10, 8
    events = torch.stack([torch.randint(-3, 85, (n,), generator=g).double(),  # some beyond the edges: clamped
                          torch.randint(0, 50, (n,), generator=g).double(),
                          torch.rand(n, generator=g, dtype=torch.float64) * 1e4,
                          torch.randint(0, 2, (n,), generator=g).double()], dim=1)
    latest = torch.full((2 * h * w,), float("-inf"), dtype=torch.float64)
    latest_times(latest.numpy(), events.numpy(), stride, h, w)
    key = recency_cells(events, torch.zeros(n, dtype=torch.int64), stride=stride, height=h, width=w)
    want = torch.full((2 * h * w,), float("-inf"), dtype=torch.float64).scatter_reduce(0, key, events[:, 2], reduce="amax")
    assert torch.equal(latest, want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_recency_since_equals_the_tensor_operations(dtype, monkeypatch):
    """The compiled recency pass against recency_from_latest: cells with no event, one older than the
    start (empty), one at the query time and later (1), the rest decaying."""
    from dagr_lite.graph import sparse
    from dagr_lite.graph.pool import recency_since
    g = torch.Generator().manual_seed(4)
    h, w = 6, 9
    latest = (torch.rand(2 * h * w, generator=g, dtype=torch.float64) * 60_000 - 10_000).to(dtype)
    latest[::7] = -math.inf
    latest[3] = 50_000.0  # the query time
    latest[5] = 50_300.0  # after it: clamped to recency 1
    start, t_query, taus = 1_234.5, 50_000.0, (10_000.0, 50_000.0)
    compiled = recency_since(latest, h, w, start, t_query, taus)
    monkeypatch.setattr(sparse, "USE_COMPILED", False)
    tensors = recency_since(latest, h, w, start, t_query, taus)
    assert compiled.shape == tensors.shape == (1, 4, h, w) and compiled.dtype == dtype
    tolerance = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(compiled, tensors, rtol=tolerance, atol=tolerance)
    empty = (latest < start) | ~torch.isfinite(latest)
    assert torch.all(compiled.view(2, -1)[:, empty] == 0) and torch.all(compiled.view(2, -1)[:, ~empty] > 0)
    assert compiled.view(2, -1)[:, 3].tolist() == [1.0, 1.0] and compiled.view(2, -1)[:, 5].tolist() == [1.0, 1.0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_dense_maps_equal_the_tensor_operations(monkeypatch, dtype):
    """to_dense on a CPU without gradients is one compiled pass: the same maps to the bit, cells
    outside the map or of a sample past the batch dropped; with gradients the tensor operations,
    which pass them back."""
    from dagr_lite.graph import sparse

    g = torch.Generator().manual_seed(5)
    cells = torch.randperm(6 * 7 * 3, generator=g)[:60]
    batch, cell = cells // 42, torch.stack([(cells % 42) // 7, cells % 7], dim=1)  # some rows 5, columns 6: outside
    x = torch.randn(60, 4, generator=g, dtype=dtype)
    got = to_dense(x, batch, cell, batch_size=2, height=5, width=6)
    monkeypatch.setattr(sparse, "USE_COMPILED", False)
    want = to_dense(x, batch, cell, batch_size=2, height=5, width=6)
    assert got.shape == (2, 4, 5, 6) and torch.equal(got, want)
    assert 0 < int((want != 0).any(dim=1).sum()) < 60  # some cells written, some dropped
    monkeypatch.setattr(sparse, "USE_COMPILED", True)
    leaf = x.clone().requires_grad_(True)
    to_dense(leaf, batch, cell, batch_size=2, height=5, width=6).sum().backward()
    inside = (cell[:, 0] < 5) & (cell[:, 1] < 6) & (batch < 2)
    assert torch.equal(leaf.grad, inside[:, None].to(dtype).expand(-1, 4))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nodes_max_pooled_straight_into_the_map_equal_pooling_then_writing(monkeypatch, dtype):
    """max_pool_to_dense's one compiled pass: the maps of voxel_max_pool then to_dense (compiled, and
    by tensor operations) to the bit, with several nodes a cell, cells outside the map and a sample
    past the batch dropped; with gradients the two steps, whose maximum alone takes the gradient."""
    from dagr_lite.graph import sparse
    from dagr_lite.graph.pool import max_pool_to_dense

    g = torch.Generator().manual_seed(7)
    n = 400
    pos = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([30.0, 26.0, 1.0], dtype=dtype)
    batch = torch.sort(torch.randint(0, 3, (n,), generator=g)).values  # sample 2 lies past a batch of 2
    x = torch.randn(n, 5, generator=g, dtype=dtype)
    x[::7] = x[1::7].max() + 1  # ties between members of a cell
    size = {"batch_size": 2, "height": 5, "width": 6}  # 4-pixel cells: rows 5 and 6, columns 6 and 7 outside
    got = max_pool_to_dense(x, pos, batch, 4, **size)
    pooled = voxel_max_pool(x, pos, batch, None, 4)
    want = to_dense(pooled.x, pooled.batch, pooled.cell, **size)
    assert got.shape == (2, 5, 5, 6) and torch.equal(got, want)
    assert 0 < int((want != 0).any(dim=1).sum()) < len(pooled.x)  # some cells written, some dropped
    monkeypatch.setattr(sparse, "USE_COMPILED", False)
    assert torch.equal(max_pool_to_dense(x, pos, batch, 4, **size), want)
    monkeypatch.setattr(sparse, "USE_COMPILED", True)
    leaf = x.clone().requires_grad_(True)
    max_pool_to_dense(leaf, pos, batch, 4, **size).sum().backward()
    assert 0 < int((leaf.grad != 0).sum()) < leaf.numel()
    with pytest.raises(ValueError, match="non-negative"):
        max_pool_to_dense(x, pos - 40.0, batch, 4, **size)
