import numpy as np
import pytest
import torch

from dagr_lite.graph import StreamingGraph, radius_graph
from dagr_lite.graph.streaming import edges_after
from tests.graph.test_radius import time_sorted_cloud


@pytest.mark.parametrize("grid", [None, 2])
def test_any_sequence_of_insertions_gives_the_batch_graph(grid):
    rng = np.random.default_rng(0)
    for _ in range(20):
        pos = time_sorted_cloud(rng, int(rng.integers(0, 400)), extent=12.0, grid=grid)
        r, k = float(rng.uniform(0.5, 3.0)), int(rng.integers(1, 9))
        graph = StreamingGraph(r, k)
        parts, i = [], 0
        while i < len(pos):
            size = int(rng.choice([0, 1, 1, 2, 3, 8, 30, 120]))  # empty batches and single events too
            edges = graph.insert(pos[i:i + size])
            assert edges.shape[0] == 2 and (edges.numel() == 0 or edges[1].min() >= i)
            parts.append(edges)
            i += size
        got = torch.cat(parts, dim=1) if parts else torch.zeros((2, 0), dtype=torch.int64)
        assert torch.equal(got, radius_graph(torch.from_numpy(pos), r, k))


def test_old_events_expire_and_ids_keep_counting():
    graph = StreamingGraph(1.0, 4)
    for step in range(200):
        graph.insert(np.array([[0.0, 0.0, 0.1 * step]]))
    assert graph.num_inserted == 200
    assert graph.num_nodes == 11  # the events within r = 1.0 of the latest (z 18.9 to 19.9)
    edges = graph.insert(np.array([[0.0, 0.0, 20.0]]))
    assert edges[1].tolist() == [200] * 4 and edges[0].tolist() == [196, 197, 198, 199]


def test_bad_use_is_refused():
    with pytest.raises(ValueError, match="r and k must be positive"):
        StreamingGraph(0.0, 4)
    graph = StreamingGraph(1.0, 4)
    graph.insert(np.array([[0.0, 0.0, 5.0]]))
    with pytest.raises(ValueError, match="time order"):
        graph.insert(np.array([[0.0, 0.0, 4.0]]))


def test_events_exactly_r_apart():
    pos = np.array([[0.0, 0.0, 0.62], [0.0, 0.0, 4.04], [0.0, 0.0, 4.04]])
    graph = StreamingGraph(3.42, 4)
    got = torch.cat([graph.insert(pos[i:i + 1]) for i in range(3)], dim=1)
    assert torch.equal(got, radius_graph(torch.from_numpy(pos), 3.42, 4))
    assert got.shape[1] == 3  # 0 -> 1, 0 -> 2, 1 -> 2


def test_positions_must_have_three_columns():
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        StreamingGraph(1.0, 2).insert(np.zeros((3, 2)))


@pytest.mark.parametrize("grid", [None, 1])
def test_the_edges_after_a_start_from_those_on_arrival_are_the_batch_graphs(grid):
    """edges_after: the graph of the nodes from ``start`` on, into its first ``count`` nodes, from
    the whole graph's edges on arrival and a search of only the nodes that lost one of k nearest,
    equals the batch builder's over those nodes alone; the query search equals the whole search's
    edges into the marked nodes, for every backend."""
    rng = np.random.default_rng(3)
    searched = 0
    for _ in range(30):
        pos = time_sorted_cloud(rng, int(rng.integers(20, 400)), extent=float(rng.uniform(4, 12)), grid=grid)
        r, k = float(rng.uniform(1.0, 3.0)), int(rng.integers(1, 6))
        whole = radius_graph(torch.from_numpy(pos), r, k)
        start = int(rng.integers(0, len(pos) - 1))
        count = int(rng.integers(1, len(pos) - start + 1))
        rest = torch.from_numpy(pos[start:])
        want = radius_graph(rest, r, k)
        want = want[:, want[1] < count]
        into = whole[:, (whole[1] >= start) & (whole[1] < start + count)]
        asked = []

        def search(query):
            asked.append(int(query.sum()))
            marks = np.zeros(len(rest), dtype=bool)
            marks[:count] = query.numpy()
            found = radius_graph(rest, r, k, query=marks)
            for backend in ("kdtree", "torch"):
                assert torch.equal(radius_graph(rest, r, k, backend=backend, query=marks), found)
            return found

        got = edges_after(into.T.contiguous(), start, count, k, search)
        assert torch.equal(got, want)
        searched += sum(asked)
    assert searched  # some nodes lost one of their k nearest and were searched again
    with pytest.raises(ValueError, match="query must be"):
        radius_graph(torch.from_numpy(pos), r, k, query=np.ones(3, dtype=bool))
