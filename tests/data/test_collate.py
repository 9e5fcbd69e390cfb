import pytest
import torch
from torch.utils.data import DataLoader

from dagr_lite.data.collate import GraphCollate, collate
from dagr_lite.data.dataset import Sample
from dagr_lite.graph.spec import EventGraphSpec


def sample(n_events, n_boxes, frame, size=(8, 10)):
    return Sample(events=torch.rand(n_events, 4), image=torch.zeros(3, *size, dtype=torch.uint8),
                  boxes=torch.rand(n_boxes, 4), labels=torch.zeros(n_boxes, dtype=torch.int64),
                  video=f"v{frame}", frame=frame, image_frame=frame - 1, t_start_us=0, t_end_us=10, t_image_us=0)


def test_collate_concatenates_events_with_a_batch_index():
    samples = [sample(3, 1, 1), sample(0, 0, 2), sample(2, 3, 3)]
    batch = collate(samples)
    assert len(batch) == 3
    assert batch.events.shape == (5, 4)
    assert batch.batch_index.tolist() == [0, 0, 0, 2, 2]
    assert batch.ptr.tolist() == [0, 3, 3, 5]
    for b, s in enumerate(samples):
        assert torch.equal(batch.events[batch.ptr[b]:batch.ptr[b + 1]], s.events)
        assert torch.equal(batch.boxes[b], s.boxes)
    assert batch.images.shape == (3, 3, 8, 10)
    assert batch.frames.tolist() == [1, 2, 3] and batch.videos == ["v1", "v2", "v3"]
    padded, mask = batch.padded_boxes()
    assert padded.shape == (3, 3, 4) and mask.sum(1).tolist() == [1, 0, 3]
    assert torch.equal(padded[2], samples[2].boxes) and torch.equal(padded[0, 0], samples[0].boxes[0])
    moved = batch.to("cpu")
    assert torch.equal(moved.events, batch.events) and moved.videos == batch.videos


def test_collate_refuses_mixed_image_sizes():
    with pytest.raises(ValueError, match="same shape"):
        collate([sample(1, 0, 1), sample(1, 0, 2, size=(9, 10))])
    with pytest.raises(ValueError, match="empty"):
        collate([])


def test_graph_collate_switches_its_workers_graph_off_and_on():
    """``building`` off: a worker process makes batches without a graph; switched on while it runs,
    every batch it makes from then on has the graph (those made before keep none), and ``complete``
    gives a batch without one exactly the graph the workers build."""
    spec = EventGraphSpec(radius=5.0, beta=5e-4, max_neighbors=16)
    generator = torch.Generator().manual_seed(0)
    samples = []
    for frame in range(12):
        s = sample(60, 1, frame)
        events = torch.rand(60, 4, generator=generator) * torch.tensor([20.0, 20.0, 20000.0, 1.0])
        events[:, 2] = events[:, 2].sort().values
        samples.append(Sample(**{**s.__dict__, "events": events.round()}))
    make = GraphCollate(spec)
    assert make.building and make([samples[0]]).edge_index is not None
    make.building = False
    batches = iter(DataLoader(samples, batch_size=1, num_workers=1, collate_fn=make, prefetch_factor=2))
    assert next(batches).edge_index is None
    make.building = True
    made = [batch.edge_index is not None for batch in batches]
    assert made[-1] and made == sorted(made)  # once on, on for good; at most the batches in flight had none
    for s in samples[:3]:
        built = make([s]).edge_index  # building is on
        bare = collate([s])
        assert bare.edge_index is None
        torch.testing.assert_close(make.complete(bare).edge_index, built, rtol=0, atol=0)
        assert built.shape[1] > 0
