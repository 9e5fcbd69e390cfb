import numpy as np
import pytest
import torch

from dagr_lite.graph import radius_graph


def brute_force(pos, r, k, batch=None):
    """Reference: all pairs, at the distance the builders define (float64 ``sqrt(dx^2 + dy^2 + dz^2)``
    summed in that order), then per node the k nearest earlier ones (ties by index)."""
    pos = torch.as_tensor(pos, dtype=torch.float64)
    n = len(pos)
    if n == 0:
        return torch.zeros((2, 0), dtype=torch.int64)
    diff = (pos[:, None, :] - pos[None, :, :]).numpy()
    # numpy's square root is correctly rounded; torch's vectorised CPU one may be an ulp off
    d = np.sqrt(diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2])
    same = np.ones((n, n), bool) if batch is None else (np.asarray(batch)[:, None] == np.asarray(batch)[None, :])
    edges = []
    for i in range(n):
        js = np.flatnonzero((d[i, :i] <= r) & same[i, :i])  # earlier nodes within r, in index order
        nearest = js[np.lexsort((js, d[i, js]))[:k]]  # by distance, ties by index
        edges += [(j, i) for j in sorted(nearest.tolist())]
    return torch.tensor(edges, dtype=torch.int64).reshape(-1, 2).T


def time_sorted_cloud(rng, n, extent=10.0, grid=None):
    pos = rng.uniform(0, extent, (n, 3))
    if grid:  # on a grid: many equal distances
        pos = np.round(pos * grid) / grid
    return pos[np.argsort(pos[:, 2], kind="stable")]


@pytest.mark.parametrize("grid", [None, 2])
def test_equals_brute_force_on_random_clouds(grid):
    rng = np.random.default_rng(0)
    for _ in range(25):
        pos = time_sorted_cloud(rng, int(rng.integers(2, 250)), grid=grid)
        r, k = float(rng.uniform(0.5, 4.0)), int(rng.integers(1, 10))
        assert torch.equal(radius_graph(torch.from_numpy(pos), r, k), brute_force(pos, r, k))


def test_without_a_binding_cap_every_earlier_neighbour_within_r_is_kept():
    rng = np.random.default_rng(1)
    pos = time_sorted_cloud(rng, 200)
    got = radius_graph(torch.from_numpy(pos), 2.0, 10_000)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    want = {(j, i) for i in range(200) for j in range(i) if d[i, j] <= 2.0}
    assert set(map(tuple, got.T.tolist())) == want


def test_ties_are_broken_by_index():
    # Node 4 sees nodes 0..3 all at distance 1; with k = 2 it keeps the two smallest indices.
    pos = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 0]])
    edges = radius_graph(pos, 1.0, 2)
    assert edges[:, edges[1] == 4].tolist() == [[0, 1], [4, 4]]


def test_edges_never_cross_samples():
    rng = np.random.default_rng(2)
    parts = [time_sorted_cloud(rng, n, extent=5.0) for n in (30, 0, 45, 1, 20)]
    pos = torch.from_numpy(np.concatenate(parts))
    batch = torch.repeat_interleave(torch.arange(5), torch.tensor([len(p) for p in parts]))
    got = radius_graph(pos, 1.5, 6, batch)
    assert torch.all(batch[got[0]] == batch[got[1]])
    assert torch.equal(got, brute_force(pos, 1.5, 6, batch))
    with pytest.raises(ValueError, match="batch must be sorted"):
        radius_graph(pos, 1.5, 6, batch.flip(0))


def test_small_inputs_and_output_format():
    assert radius_graph(torch.zeros((0, 3)), 1.0, 4).shape == (2, 0)
    assert radius_graph(torch.zeros((1, 3)), 1.0, 4).shape == (2, 0)
    two = radius_graph(torch.tensor([[0.0, 0, 0], [0.5, 0, 0]]), 1.0, 4)
    assert two.tolist() == [[0], [1]] and two.dtype == torch.int64  # earlier -> later only
    far = radius_graph(torch.tensor([[0.0, 0, 0], [5.0, 0, 0]]), 1.0, 4)
    assert far.shape == (2, 0)
    rng = np.random.default_rng(3)
    edges = radius_graph(torch.from_numpy(time_sorted_cloud(rng, 300)), 2.0, 5)
    assert torch.all(edges[0] < edges[1])  # causal, no self-loops
    key = edges[1] * 1000 + edges[0]
    assert torch.all(key[1:] > key[:-1])  # sorted by destination, then source
    assert torch.bincount(edges[1]).max() <= 5


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"pos must have shape \(N, 3\)"):
        radius_graph(torch.zeros(5), 1.0, 2)
    with pytest.raises(ValueError, match="non-finite"):
        radius_graph(torch.tensor([[0.0, 0, float("nan")]]), 1.0, 2)
    with pytest.raises(ValueError, match="r and k must be positive"):
        radius_graph(torch.zeros((3, 3)), 0.0, 2)


def test_a_sample_gets_the_same_edges_alone_and_in_a_batch():
    # Values where shifting x would change float rounding: exactly at r, and ties on pixels.
    pair = torch.tensor([[0.1, 0.0, 0.0], [0.3, 0.0, 0.0]], dtype=torch.float64)
    r = 0.3 - 0.1
    alone = radius_graph(pair, r, 4)
    batched = radius_graph(torch.cat([pair, pair]), r, 4, torch.tensor([0, 0, 1, 1]))
    assert alone.tolist() == [[0], [1]] and batched.tolist() == [[0, 2], [1, 3]]
    rng = np.random.default_rng(5)
    pixels = np.concatenate([rng.integers(0, 512, (80, 2)), np.sort(rng.integers(0, 40, (80, 1)), 0)], 1) * 1.0
    sample = torch.from_numpy(pixels)
    single = radius_graph(sample, 2.7, 3)
    both = radius_graph(torch.cat([sample, sample]), 2.7, 3, torch.repeat_interleave(torch.arange(2), 80))
    assert torch.equal(both[:, both[1] >= 80] - 80, single)


def test_many_identical_points_keep_the_smallest_indices():
    pos = torch.zeros((3000, 3), dtype=torch.float64)
    edges = radius_graph(pos, 1.0, 4)
    assert edges.shape[1] == 4 * 2999 - 6  # node i keeps min(i, 4) earlier nodes
    assert torch.all(edges[0, edges[1] >= 4].reshape(-1, 4) == torch.arange(4))


def test_distances_closer_than_the_sorting_quantum_keep_their_exact_order():
    """The all-pairs path ranks by an integer key holding the distance quantised to 52 bits of
    [0, r] (few nodes); distances closer than that share a key and are reordered exactly.
    Here node 0 is farther from node 2 than node 1 by one float64 step: with k = 1, node 2 keeps node 1."""
    r, k = 16.0, 1  # a quantum of r / 2^52: 16 float64 steps at 1.5
    pos = np.zeros((3, 3))
    pos[0, 0], pos[1, 0] = np.nextafter(1.5, 2.0), 1.5
    top = 2 ** 52 - 1
    assert np.floor(pos[0, 0] * (top / r)) == np.floor(pos[1, 0] * (top / r))  # one quantum
    edges = radius_graph(torch.from_numpy(pos), r, k)
    assert edges.tolist() == [[0, 1], [1, 2]]
    # Many such near-ties, against the pair-by-pair reference of (distance, index).
    rng = np.random.default_rng(21)
    steps = rng.permutation(40)
    pos = np.zeros((41, 3))
    pos[:40, 0] = [1.5 + s * np.spacing(1.5) for s in steps]
    dist = np.sqrt(pos[:40, 0] * pos[:40, 0])
    for k in (1, 5, 17):
        edges = radius_graph(torch.from_numpy(pos), r, k)
        assert edges[0, edges[1] == 40].tolist() == sorted(sorted(range(40), key=lambda j: (dist[j], j))[:k])


@pytest.mark.parametrize("grid", [None, 2, 1])
def test_torch_backend_equals_the_kdtree_and_brute_force(grid):
    rng = np.random.default_rng(10)
    for _ in range(30):
        pos = time_sorted_cloud(rng, int(rng.integers(0, 200)), extent=float(rng.uniform(3, 12)), grid=grid)
        r, k = float(rng.choice([0.7, 1.0, 2.0, 3.3])), int(rng.integers(1, 12))
        torch_edges = radius_graph(torch.from_numpy(pos), r, k, backend="torch")
        assert torch.equal(torch_edges, radius_graph(torch.from_numpy(pos), r, k, backend="kdtree"))
        assert torch.equal(torch_edges, brute_force(pos, r, k))


def test_torch_backend_on_event_clouds_with_samples_and_exact_radius_ties():
    """Integer pixels and microseconds (many neighbours exactly at r, e.g. 3-4-5 triangles), several samples."""
    rng = np.random.default_rng(11)
    for _ in range(12):
        n = int(rng.integers(1, 1500))
        t = np.sort(rng.integers(0, 20_000, n))
        pos = torch.from_numpy(np.stack([rng.integers(0, 30, n), rng.integers(0, 20, n), 5e-4 * t], 1).astype(float))
        batch = torch.from_numpy(np.sort(rng.integers(0, 3, n)))
        for r, k in ((5.0, 16), (1.0, 2), (3.0, 40)):
            got = radius_graph(pos, r, k, batch, backend="torch")
            assert torch.equal(got, radius_graph(pos, r, k, batch, backend="kdtree"))
    pos = torch.tensor([[0.0, 0, 0], [3, 4, 0], [0, 0, 5.0], [4, 3, 5.0]])  # every pair exactly 5 or farther
    assert torch.equal(radius_graph(pos, 5.0, 8, backend="torch"), brute_force(pos, 5.0, 8))


def test_torch_backend_in_small_chunks_of_candidates(monkeypatch):
    """A dense cloud (every node a candidate of every later one) split into many candidate chunks."""
    import dagr_lite.graph.radius as radius_module

    monkeypatch.setattr(radius_module, "TORCH_PAIR_BUDGET", 500)
    rng = np.random.default_rng(12)
    pos = time_sorted_cloud(rng, 300, extent=2.0)
    assert torch.equal(radius_graph(torch.from_numpy(pos), 3.0, 7, backend="torch"), brute_force(pos, 3.0, 7))


def test_backend_choice_and_refusals(monkeypatch):
    import dagr_lite.graph.radius as radius_module

    pos = torch.tensor([[0.0, 0, 1], [0, 0, 0]])  # not sorted by time
    with pytest.raises(ValueError, match="sorted by time"):
        radius_graph(pos, 1.0, 2, backend="torch")
    with pytest.raises(ValueError, match="backend must be one of"):
        radius_graph(pos, 1.0, 2, backend="faiss")

    def unused(*args, **kwargs):
        raise AssertionError("auto must not pick the torch backend for a CPU tensor")

    monkeypatch.setattr(radius_module, "radius_graph_torch", unused)
    assert radius_graph(pos.flip(0), 2.0, 2).tolist() == [[0], [1]]


def test_all_pairs_path_equals_the_nearest_query_path(monkeypatch):
    """The two kdtree paths (all pairs within r, or k-nearest queries) give identical edges, on
    random clouds, grids with many equal distances, and event clouds with exact radius ties."""
    import dagr_lite.graph.radius as radius_module

    rng = np.random.default_rng(13)
    clouds = []
    for grid in (None, 2, 1):
        clouds += [(time_sorted_cloud(rng, int(rng.integers(2, 400)), extent=float(rng.uniform(3, 12)), grid=grid),
                    None) for _ in range(8)]
    for _ in range(6):
        n = int(rng.integers(2, 3000))
        t = np.sort(rng.integers(0, 20_000, n))
        clouds.append((np.stack([rng.integers(0, 30, n), rng.integers(0, 20, n), 5e-4 * t], 1).astype(float),
                       torch.from_numpy(np.sort(rng.integers(0, 3, n)))))
    clouds.append((rng.uniform(0, 5, (300, 2)), None))  # two-dimensional positions
    for pos, batch in clouds:
        for r, k in ((5.0, 16), (1.0, 2), (2.5, 40)):
            pos_t = torch.from_numpy(pos)
            monkeypatch.setattr(radius_module, "PAIR_BUDGET", 1 << 23)
            assert radius_module.pairs_bound(pos, r) <= 1 << 23  # the all-pairs path is the one taken
            pairs = radius_graph(pos_t, r, k, batch, backend="kdtree")
            monkeypatch.setattr(radius_module, "PAIR_BUDGET", -1)  # force the query path
            assert torch.equal(pairs, radius_graph(pos_t, r, k, batch, backend="kdtree"))


@pytest.mark.parametrize("grid", [None, 1])
def test_pairs_bound_is_an_upper_bound(grid):
    from dagr_lite.graph.radius import pairs_bound

    rng = np.random.default_rng(14)
    for _ in range(20):
        pos = time_sorted_cloud(rng, int(rng.integers(1, 300)), extent=float(rng.uniform(1, 10)), grid=grid)
        r = float(rng.choice([0.5, 1.0, 3.0]))
        within = int((np.linalg.norm(pos[:, None] - pos[None], axis=2) <= r).sum())  # ordered, self included
        assert within <= pairs_bound(pos, r)
    assert pairs_bound(np.zeros((0, 3)), 1.0) == 0
    assert pairs_bound(np.zeros((100, 3)), 1.0) == 27 * 100 ** 2  # one cell: the bound is 27 n^2
