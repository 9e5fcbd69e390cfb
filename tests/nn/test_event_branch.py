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
