"""The compiled cell-chain builder against brute force and the KD-tree, batch and streaming."""
import numpy as np
import pytest
import torch

import dagr_lite.graph.compiled as compiled
from dagr_lite.graph import StreamingGraph, radius_graph
from tests.graph.test_radius import brute_force, time_sorted_cloud

BETA = 5e-4  # 10 ms count as 5 px


def event_stream(rng, n, width=40, height=30, span_us=20_000, hot=None, burst=0):
    """Integer pixels, integer microseconds, time-sorted: several events per pixel and microsecond,
    optionally a hot pixel firing every ``hot`` us and bursts of ``burst`` events at one pixel and one us."""
    x, y, t = rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, span_us, n)
    parts = [np.stack([x, y, t], 1)]
    if hot:
        times = np.arange(0, span_us, hot)
        parts.append(np.stack([np.full_like(times, width // 2), np.full_like(times, height // 2), times], 1))
    if burst:
        at = rng.integers(0, span_us, 5)
        parts += [np.array([[int(rng.integers(0, width)), int(rng.integers(0, height)), int(moment)]] * burst)
                  for moment in at]
    events = np.concatenate(parts).astype(np.float64)
    events = events[np.argsort(events[:, 2], kind="stable")]
    return np.stack([events[:, 0], events[:, 1], BETA * events[:, 2]], 1)


def both(pos, r, k, batch=None, workers=1):
    pos_t = torch.from_numpy(np.asarray(pos, dtype=np.float64))
    got = radius_graph(pos_t, r, k, batch, backend="compiled", workers=workers)
    want = radius_graph(pos_t, r, k, batch, backend="kdtree")
    return got, want


@pytest.mark.parametrize("grid", [None, 2, 1])
def test_equals_brute_force_and_the_kdtree_on_random_clouds(grid):
    rng = np.random.default_rng(30)
    for _ in range(40):
        pos = time_sorted_cloud(rng, int(rng.integers(0, 300)), extent=float(rng.uniform(2, 15)), grid=grid)
        r, k = float(rng.choice([0.5, 1.0, 2.0, 3.0, float(rng.uniform(0.3, 4))])), int(rng.integers(1, 12))
        got, want = both(pos, r, k)
        assert torch.equal(got, want)
        assert torch.equal(got, brute_force(pos, r, k))


def test_event_streams_with_hot_pixels_bursts_and_exact_radius_ties():
    """Integer pixels at 1 us resolution: many pairs exactly r apart (3-4-5), a hot pixel firing every
    3 us, bursts of identical events, several samples."""
    rng = np.random.default_rng(31)
    for trial in range(10):
        pos = event_stream(rng, int(rng.integers(50, 2500)), hot=int(rng.choice([3, 7])), burst=int(rng.integers(2, 40)))
        batch = torch.from_numpy(np.sort(rng.integers(0, 3, len(pos))))
        for r, k in ((5.0, 16), (1.0, 2), (3.0, 40), (2.0, 1)):
            got, want = both(pos, r, k, batch)
            assert torch.equal(got, want), (trial, r, k)
    pos = np.array([[0.0, 0, 0], [3, 4, 0], [0, 0, 5.0], [4, 3, 5.0], [0, 0, 5.0], [0, 0, 5.0]])
    got, _ = both(pos, 5.0, 8)
    assert torch.equal(got, brute_force(pos, 5.0, 8))


def test_fractional_positions_as_the_zoom_augmentation_makes_them():
    rng = np.random.default_rng(32)
    for scale in (1.0, 1.17, 1.5):
        pos = event_stream(rng, 2000)
        pos[:, :2] = scale * (pos[:, :2] + 0.5) + 0.31 - 0.5  # augment.zoom_translate's mapping
        got, want = both(pos, 5.0, 16)
        assert torch.equal(got, want)
        part = pos[:400]
        assert torch.equal(radius_graph(torch.from_numpy(part), 5.0, 16, backend="compiled"), brute_force(part, 5.0, 16))


def test_fractional_positions_exactly_r_apart_and_at_cell_borders():
    """Quarter-pixel positions (pairs exactly r apart across cell borders, ties in time) and points a
    hair either side of a cell border: each point's own least distance to a cell may never cut a
    neighbour, and every builder breaks ties between distances an ulp apart alike."""
    rng = np.random.default_rng(33)
    for trial in range(12):
        n = int(rng.integers(50, 600))
        xy = rng.integers(0, 48, (n, 2)) / 4.0
        hair = rng.random((n, 2)) < 0.2
        xy[hair] = np.nextafter(np.round(xy[hair]), rng.choice([-np.inf, np.inf], int(hair.sum())))
        z = np.sort(rng.integers(0, 12, n) / 4.0)
        pos = np.concatenate([xy, z[:, None]], 1)
        for r, k in ((2.5, 16), (1.25, 3), (5.0, 30), (0.75, 1)):
            got, want = both(pos, r, k)
            assert torch.equal(got, want), (trial, r, k)
            assert torch.equal(got, brute_force(pos, r, k)), (trial, r, k)
            assert torch.equal(got, radius_graph(torch.from_numpy(pos), r, k, backend="torch")), (trial, r, k)


@pytest.mark.parametrize("side", [1.0, 2.0, 2.5, 5.0, 8.0])
def test_any_cell_side_gives_the_same_edges(monkeypatch, side):
    """The cell side is a speed setting only: at sides below, at and above r (so that cells r apart,
    whose points are exactly r apart at best, are still visited), for integer and fractional positions."""
    monkeypatch.setattr(compiled, "CELL_SIZE", side)
    monkeypatch.setattr(compiled, "FRACTIONAL_CELL_SIZE", side)
    rng = np.random.default_rng(34)
    for trial in range(6):
        pos = event_stream(rng, int(rng.integers(100, 1500)), hot=5, burst=4)
        if trial % 2:
            pos[:, :2] = pos[:, :2] * 1.25 + 0.5  # fractional: quarter pixels, pairs exactly 5 apart
        batch = torch.from_numpy(np.sort(rng.integers(0, 2, len(pos))))
        for r, k in ((5.0, 16), (2.5, 4), (1.0, 2)):
            got, want = both(pos, r, k, batch)
            assert torch.equal(got, want), (trial, r, k)
        assert torch.equal(both(pos[:300], 5.0, 16)[0], brute_force(pos[:300], 5.0, 16))


def test_the_threaded_build_equals_one_thread(monkeypatch):
    """Chunks on threads, each rebuilding the cell heads at its start, with chunks and samples not aligned."""
    monkeypatch.setattr(compiled, "PARALLEL_MIN", 10)
    rng = np.random.default_rng(33)
    for _ in range(6):
        pos = event_stream(rng, int(rng.integers(100, 4000)), hot=5, burst=10)
        batch = torch.from_numpy(np.sort(rng.integers(0, 4, len(pos))))
        got_threads, want = both(pos, 5.0, 16, batch, workers=2)
        got_one, _ = both(pos, 5.0, 16, batch, workers=1)
        assert torch.equal(got_threads, want) and torch.equal(got_one, want)


def test_wide_clouds_take_larger_cells(monkeypatch):
    monkeypatch.setattr(compiled, "GRID_BUDGET", 5000)
    rng = np.random.default_rng(34)
    pos = event_stream(rng, 1500, width=400, height=300)
    grid = compiled.Grid(pos[:, :2].min(0), pos[:, :2].max(0), 5.0, True)
    assert grid.s > 1 and not grid.integer and grid.size <= 5000 * 4
    got, want = both(pos, 5.0, 16)
    assert torch.equal(got, want)
    far = np.array([[-1e7, 0.0, 0.0], [-1e7 + 1, 0, 0.1], [3e7, 5, 0.2], [3e7, 5, 0.3]])
    got, want = both(far, 2.0, 4)
    assert torch.equal(got, want) and got.tolist() == [[0, 2], [1, 3]]


def test_time_order_is_required_and_named():
    pos = np.array([[0.0, 0, 0], [1, 0, 2], [2, 0, 1], [0, 0, 3]])
    with pytest.raises(ValueError, match=r"1 event\(s\) earlier than the event before, the first at index 2"):
        radius_graph(torch.from_numpy(pos), 2.0, 2, backend="compiled")
    # A new sample may start earlier than the last event of the one before.
    batch = torch.tensor([0, 0, 1, 1])
    pos = np.array([[0.0, 0, 5], [1, 0, 6], [0, 0, 1], [1, 0, 2]])
    assert torch.equal(*both(pos, 2.0, 2, batch))


@pytest.mark.parametrize("source", ["random", "events"])
def test_streaming_in_random_chunks_equals_the_batch_graph(source):
    rng = np.random.default_rng(35)
    for trial in range(12):
        if source == "random":
            pos = time_sorted_cloud(rng, int(rng.integers(0, 500)), extent=12.0, grid=[None, 2][trial % 2])
            r, k = float(rng.uniform(0.5, 3.0)), int(rng.integers(1, 9))
        else:
            pos = event_stream(rng, int(rng.integers(10, 3000)), hot=4, burst=8)
            r, k = 5.0, 16
        graph = StreamingGraph(r, k)
        graph._chains = compiled.CellChains(r, k, capacity=16)  # a small ring: it has to grow
        parts, i = [], 0
        while i < len(pos):
            size = int(rng.choice([0, 1, 1, 2, 7, 64, 500]))
            parts.append(graph.insert(pos[i:i + size]))
            i += size
        got = torch.cat(parts, dim=1) if parts else torch.zeros((2, 0), dtype=torch.int64)
        assert torch.equal(got, radius_graph(torch.from_numpy(pos), r, k, backend="kdtree"))


def test_streaming_grid_grows_and_turns_fractional():
    """Events wander outside the grid, then fractional positions arrive: the chains are relinked."""
    rng = np.random.default_rng(36)
    pos = event_stream(rng, 3000, width=20, height=20)
    pos[1000:2000, :2] += 300  # far outside the first grid
    pos[2000:, :2] += rng.uniform(0, 1, (1000, 2))  # fractional from here on
    pos[2500:, 0] -= 500
    graph = StreamingGraph(5.0, 16)
    got = torch.cat([graph.insert(pos[i:i + 100]) for i in range(0, len(pos), 100)], dim=1)
    assert torch.equal(got, radius_graph(torch.from_numpy(pos), 5.0, 16, backend="kdtree"))
    assert not graph._chains.grid.integer


def test_streaming_cost_does_not_depend_on_history():
    """The held events stay those within reach of the latest, however long the stream."""
    graph = StreamingGraph(5.0, 16)
    rng = np.random.default_rng(37)
    for second in range(3):
        pos = event_stream(rng, 20_000, span_us=1_000_000)
        pos[:, 2] += BETA * 1_000_000 * second
        for i in range(0, len(pos), 500):
            graph.insert(pos[i:i + 500])
            held_z = graph._chains._held()["z"]
            assert held_z.min() >= pos[i, 2] - 5.0 * (1 + 1e-9)  # only what a new event can reach
    assert graph.num_inserted == 60_000 and len(graph._chains.nodes) <= 4096


def test_both_streaming_backends_are_selectable():
    rng = np.random.default_rng(38)
    pos = event_stream(rng, 800)
    edges = {}
    for backend in StreamingGraph.BACKENDS:
        graph = StreamingGraph(5.0, 16, backend=backend)
        edges[backend] = torch.cat([graph.insert(pos[i:i + 37]) for i in range(0, len(pos), 37)], dim=1)
    assert torch.equal(edges["compiled"], edges["kdtree"])
    with pytest.raises(ValueError, match="backend must be one of"):
        StreamingGraph(5.0, 16, backend="faiss")
