import pytest
import torch

from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn import EventBranch

SPEC = EventGraphSpec(radius=6.0, beta=1e-3, max_neighbors=16)
STRIDES = (8, 16, 32)


def events_of(n, seed, height=48, width=64):
    g = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.rand(n, generator=g) * 33333).values
    xy = torch.rand(n, 2, generator=g) * torch.tensor([width - 1.0, height - 1.0])
    p = torch.randint(0, 2, (n,), generator=g).float()
    return torch.cat([xy.round(), t[:, None], p[:, None]], dim=1)


def test_dense_maps_have_the_strides_shapes_and_carry_gradient():
    torch.manual_seed(0)
    branch = EventBranch(height=48, width=64, channels=(8, 16, 16, 24), strides=STRIDES, graph=SPEC, time_scale_us=1e5,
                         blocks=1)
    a, b = events_of(300, 0), events_of(200, 1)
    events = torch.cat([a, b])
    batch = torch.cat([torch.zeros(300), torch.ones(200)]).long()
    maps = branch(events, batch, batch_size=2)
    assert [tuple(m.shape) for m in maps] == [(2, 16, 6, 8), (2, 16, 3, 4), (2, 24, 2, 2)]
    sum(m.sum() for m in maps).backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in branch.parameters())
    assert any(p.grad.abs().sum() > 0 for p in branch.stages[0].parameters())


def test_samples_do_not_influence_each_other():
    torch.manual_seed(0)
    branch = EventBranch(height=48, width=64, channels=(8, 8, 8, 8), strides=STRIDES, graph=SPEC,
                         time_scale_us=1e5, blocks=1).eval()
    a, b = events_of(250, 2), events_of(150, 3)
    alone = branch(a, torch.zeros(250, dtype=torch.long), batch_size=1)
    together = branch(torch.cat([a, b]), torch.cat([torch.zeros(250), torch.ones(150)]).long(), batch_size=2)
    for m_alone, m_together in zip(alone, together):
        assert torch.allclose(m_alone[0], m_together[0], atol=1e-6)


def test_no_events_give_zero_maps_and_the_image_hook_joins_with_gradient():
    torch.manual_seed(0)
    branch = EventBranch(height=32, width=32, channels=(4, 4, 4, 4), strides=STRIDES,
                         graph=EventGraphSpec(radius=5.0, beta=5e-4, max_neighbors=16), time_scale_us=1e5, blocks=1,
                         image_channels=(3, 2, 0, 0))
    maps = branch(torch.zeros((0, 4)), torch.zeros(0, dtype=torch.long), batch_size=2,
                  image_sampler=lambda pos, batch, level: torch.zeros(len(pos), (3, 2)[level]))
    assert all(m.abs().sum() == 0 for m in maps) and maps[0].shape == (2, 4, 4, 4)
    image_feature = torch.ones(1, requires_grad=True)
    events = events_of(100, 4, 32, 32)
    sampler = lambda pos, batch, level: image_feature * pos[:, :1].new_ones(len(pos), (3, 2)[level])  # noqa: E731
    out = branch(events, torch.zeros(100, dtype=torch.long), batch_size=1, image_sampler=sampler)
    sum(m.sum() for m in out).backward()
    assert image_feature.grad is not None and image_feature.grad.abs() > 0


def test_neighbourhood_geometry_equals_a_loop_over_each_nodes_neighbours():
    from dagr_lite.nn.event_branch import neighbourhood_geometry

    events = events_of(400, 3).double()
    batch = torch.zeros(400, dtype=torch.long)
    edges = SPEC.edges(events, batch)
    pos = SPEC.positions(events)
    got = neighbourhood_geometry(pos, edges, SPEC.radius, SPEC.max_neighbors)
    for i in range(400):
        src = edges[0][edges[1] == i]
        row = [0.0] * 9
        for j in src.tolist():
            dx, dy, dt = ((pos[j] - pos[i]) / SPEC.radius).tolist()
            assert dt <= 0  # an earlier neighbour
            for k, v in enumerate([dx, dy, dt, dx * dx, dy * dy, dt * dt, dx * dt, dy * dt, dx * dy]):
                row[k] += v / len(src)
        torch.testing.assert_close(got[i], torch.tensor(row + [len(src) / SPEC.max_neighbors], dtype=torch.float64),
                                   rtol=0, atol=1e-12)
    assert got[:, 9].max() > 0 and (got[:, 9] == 0).any()  # nodes with neighbours, and the first ones alone
    # The features of the nodes from `first` on, from their edges alone, equal the whole graph's.
    late = edges[:, edges[1] >= 250]
    torch.testing.assert_close(neighbourhood_geometry(pos, late, SPEC.radius, SPEC.max_neighbors, first=250), got[250:])


def test_compiled_neighbourhood_geometry_equals_the_tensor_reference():
    from dagr_lite.nn.event_branch import neighbourhood_geometry, neighbourhood_geometry_reference

    events = torch.cat([events_of(700, 5), events_of(500, 6)]).double()
    batch = torch.cat([torch.zeros(700, dtype=torch.long), torch.ones(500, dtype=torch.long)])
    edges = SPEC.edges(events, batch)
    pos = SPEC.positions(events)
    assert edges.shape[1] > 1000
    # float64: the same sums in the same order, to the bit; from `first` on too
    assert torch.equal(neighbourhood_geometry(pos, edges, SPEC.radius, SPEC.max_neighbors),
                       neighbourhood_geometry_reference(pos, edges, SPEC.radius, SPEC.max_neighbors))
    late = edges[:, edges[1] >= 900]
    assert torch.equal(neighbourhood_geometry(pos, late, SPEC.radius, SPEC.max_neighbors, first=900),
                       neighbourhood_geometry_reference(pos, late, SPEC.radius, SPEC.max_neighbors, first=900))
    # float32: the training precision, to its rounding
    got = neighbourhood_geometry(pos.float(), edges, SPEC.radius, SPEC.max_neighbors)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, neighbourhood_geometry_reference(pos.float(), edges, SPEC.radius, SPEC.max_neighbors))
    # no edges: zeros; a position that needs a gradient takes the differentiable reference
    none = neighbourhood_geometry(pos, edges[:, :0], SPEC.radius, SPEC.max_neighbors)
    assert none.shape == (1200, 10) and not none.any()
    grad_pos = pos.clone().requires_grad_(True)
    neighbourhood_geometry(grad_pos, edges, SPEC.radius, SPEC.max_neighbors).sum().backward()
    assert grad_pos.grad is not None


def test_a_branch_with_geometry_reads_the_neighbourhood_and_refuses_features_without_a_graph():
    import pytest

    torch.manual_seed(0)
    branch = EventBranch(height=48, width=64, channels=(8, 16, 16, 24), strides=STRIDES, graph=SPEC, time_scale_us=None,
                         blocks=1, geometry=True)
    events = events_of(300, 0)
    batch = torch.zeros(300, dtype=torch.long)
    assert branch.stages[0][0].conv.in_channels == 3 + 10
    maps = branch(events, batch, batch_size=1)
    moved = events.clone()
    moved[150:, 0] = (moved[150:, 0] + 1).clamp(max=63)  # other neighbourhoods, the same polarities
    assert not torch.allclose(maps[0], branch(moved, batch, batch_size=1)[0])
    with pytest.raises(ValueError, match="positions and graph"):
        branch.node_features(events)


@pytest.mark.parametrize("cell", [8, 4])
def test_dense_pooled_stages_convolve_the_first_stages_cell_maxima(cell):
    """``dense``: the first stage's node features, max-pooled per ``cell``-pixel cell by a loop over
    the cells (empty cells zero), then the convolution stages; maps at every stride (a stage at
    stride 4 first gives none), samples apart."""
    torch.manual_seed(0)
    branch = EventBranch(height=48, width=64, channels=(8, 12, 16, 24), strides=STRIDES, graph=SPEC,
                         time_scale_us=1e5, blocks=1, dense=cell).double().eval()
    assert branch.pool_stride == cell and len(branch.dense_stages) == 3 + (cell == 4)
    a, b = events_of(300, 5).double(), events_of(200, 6).double()
    events = torch.cat([a, b])
    batch = torch.cat([torch.zeros(300), torch.ones(200)]).long()
    maps = branch(events, batch, batch_size=2)
    assert [tuple(m.shape) for m in maps] == [(2, 12, 6, 8), (2, 16, 3, 4), (2, 24, 2, 2)]
    x, _, _ = branch.event_nodes(events, batch)
    grid = torch.full((2, 8, 48 // cell, 64 // cell), -torch.inf, dtype=torch.float64)
    for node in range(len(events)):
        col, row, s = int(events[node, 0]) // cell, int(events[node, 1]) // cell, int(batch[node])
        grid[s, :, row, col] = torch.maximum(grid[s, :, row, col], x[node])
    expected, out = grid.nan_to_num(neginf=0.0), []  # empty cells are zero
    for stage in branch.dense_stages:
        expected = stage(expected)
        out.append(expected)
    if cell == 4:
        assert out[0].shape == (2, 6, 12, 16)  # half the first stride's width
    for m, e in zip(maps, out[-3:]):
        torch.testing.assert_close(m, e, rtol=0, atol=1e-12)
    alone = branch(a, torch.zeros(300, dtype=torch.long), batch_size=1)
    for m_alone, m_both in zip(alone, maps):
        torch.testing.assert_close(m_alone[0], m_both[0], rtol=0, atol=1e-12)
    branch.train()
    sum(m.sum() for m in branch(events, batch, batch_size=2)).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in branch.parameters())


def test_dense_pooled_stages_refuse_image_features_after_the_input_level_and_odd_cells():
    with pytest.raises(ValueError, match="input level alone"):
        EventBranch(height=48, width=64, channels=(8, 8, 8, 8), strides=STRIDES, graph=SPEC, time_scale_us=1e5,
                    blocks=1, image_channels=(4, 4, 0, 0), dense=8)
    for cell in (6, 16):
        with pytest.raises(ValueError, match=f"event_dense must be 0 or the first stride 8 halved .*got {cell}"):
            EventBranch(height=48, width=64, channels=(8, 8, 8, 8), strides=STRIDES, graph=SPEC,
                        time_scale_us=1e5, blocks=1, dense=cell)


@pytest.mark.parametrize("geometry,directional", [(True, False), (False, True), (True, True)])
def test_an_events_only_branch_answers_the_same_whatever_time_counts_from(geometry, directional):
    # A sample counts times from its image's time, the streaming detector from an origin of its own:
    # an events-only branch (no time feature) must give the same maps, to the bit in float32. Events in
    # whole pixels and microseconds, with pairs exactly the radius apart (2 px and 4,000 us at radius 3).
    torch.manual_seed(0)
    spec = EventGraphSpec(radius=3.0, beta=5e-4, max_neighbors=8)
    branch = EventBranch(height=48, width=64, channels=(8, 8, 8, 8), strides=STRIDES, graph=spec,
                         time_scale_us=None, blocks=1, geometry=geometry, directional=directional).eval()
    rows = []
    for i in range(40):
        x, y, t = 3 + 7 * (i % 8), 3 + 8 * (i // 8), 100 + 53 * i
        rows += [(x, y, t, 1), (x + 2, y + 1, t + 4_000, 0), (x, y + 2, t + 4_000, 1), (x + 1, y, t + 5_000, 0)]
    events = events_of(400, 5)
    events[:, 2] = events[:, 2].round()
    events = torch.cat([events, torch.tensor(rows, dtype=torch.float32)])
    events = events[torch.sort(events[:, 2], stable=True).indices]
    batch = torch.zeros(len(events), dtype=torch.long)
    with torch.no_grad():
        reference = branch(events, batch, batch_size=1)
        for shift in (300_000, 633_333, 4_000_037):
            shifted = events.clone()
            shifted[:, 2] += shift  # whole microseconds, exact in float32 below 2^24
            for m_ref, m in zip(reference, branch(shifted, batch, batch_size=1)):
                assert torch.equal(m_ref, m), shift
