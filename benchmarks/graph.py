"""Event graph and GCN speed, against baselines measured in the same run.

    python benchmarks/graph.py [--sizes 50000 200000] [--repeats 3]

Clouds: N events in a 33 ms window at 640x360, moving blobs (events on their outlines) plus
10 % uniform noise; R = 5 px, beta = 5 px / 10 ms, K = 16. Prints:
  * batch graph build (causal, capped) vs a plain ``cKDTree`` build + ``query(k=K+1,
    distance_upper_bound=R)`` over all events (non-causal, no cap handling), and vs the same
    build forced onto its k-nearest-query path;
  * the pure-torch backend (``backend="torch"``, for GPUs) against the KD-tree on this CPU, its
    candidate pairs per event, and on paper the graph-building rate a GPU needs;
  * streaming insertion in 1 ms batches, cost per event vs the batch build, and over three
    windows of events: the cost per event while the window fills and once it slides;
  * GCN layer forward + backward, 32 -> 64 channels, vs ``torch_geometric.nn.GCNConv`` if it is
    installed, else an ``index_add_`` message-passing layer written here;
  * peak memory of the batch build (numpy allocations traced in a fresh process);
  * with a CUDA GPU: the torch backend on it against the KD-tree on this CPU (identical edges),
    and the GCN layer on it against the reference layer on it.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import time
import tracemalloc

import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.graph import StreamingGraph, radius_graph
from dagr_lite.nn import GCNConv, GraphOperator

WIDTH, HEIGHT, WINDOW_US = 640, 360, 33_333
RADIUS, K = 5.0, 16
BETA = RADIUS / 10_000  # 10 ms of time count as R pixels


def event_cloud(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` positions (x, y, beta * t), time-sorted: moving blob outlines plus noise."""
    rng = np.random.default_rng(seed)
    n_noise = n // 10
    n_blob = n - n_noise
    blobs = 12
    centre = rng.uniform([60, 60], [WIDTH - 60, HEIGHT - 60], (blobs, 2))
    velocity = rng.uniform(-2000, 2000, (blobs, 2)) / 1e6  # px / us
    radius = rng.uniform(10, 40, blobs)
    which = rng.integers(0, blobs, n_blob)
    t = rng.uniform(0, WINDOW_US, n_blob)
    angle = rng.uniform(0, 2 * np.pi, n_blob)
    ring = radius[which] * (1 + 0.1 * rng.standard_normal(n_blob))
    xy = centre[which] + velocity[which] * t[:, None] + np.stack([np.cos(angle), np.sin(angle)], 1) * ring[:, None]
    xy = np.concatenate([xy, rng.uniform([0, 0], [WIDTH, HEIGHT], (n_noise, 2))])
    t = np.concatenate([t, rng.uniform(0, WINDOW_US, n_noise)])
    xy = np.clip(np.round(xy), 0, [WIDTH - 1, HEIGHT - 1])
    order = np.argsort(t, kind="stable")
    return np.concatenate([xy[order], BETA * t[order, None]], axis=1)


def candidate_pairs(pos: torch.Tensor) -> int:
    """Pairs (node, earlier node within the 3x3 cells around it and r in time) the torch backend examines."""
    import dagr_lite.graph.radius as radius_module

    seen = []
    original = radius_module._nearest_in_chunk

    def counting(points, order, lo, count, first_node, r, k):
        seen.append(int(count.sum()))
        return original(points, order, lo, count, first_node, r, k)

    radius_module._nearest_in_chunk = counting
    try:
        radius_module.radius_graph_torch(pos, RADIUS, K)
    finally:
        radius_module._nearest_in_chunk = original
    return sum(seen)


def gpu_needed(n: int, pairs: int, edges: int, step_s: float = 0.5, batch: int = 16) -> None:
    """On paper: the rate a GPU must build graphs at to take under a tenth of a training step.

    A step of ``batch`` samples of ``n`` events taking ``step_s`` leaves ``step_s / 10`` for the
    graphs. The torch backend's work is memory-bound: per candidate pair it gathers two float64
    positions and two int64 ids and writes a distance and a flag (about 64 bytes), and it sorts the
    kept pairs three times (about 3 x 24 bytes read and written, twice, per pair).
    """
    events_per_s = batch * n / (step_s / 10)
    kept = pairs  # the sorts run over the pairs within r, bounded by all candidates
    bytes_per_event = (64 * pairs + 3 * 2 * 24 * kept) / n
    print(f"  on paper: a {step_s} s step of {batch} x {n:,} events needs {events_per_s / 1e6:.0f} M events/s of "
          f"graph building; at {bytes_per_event / 1e3:.1f} kB of memory traffic per event that is "
          f"{events_per_s * bytes_per_event / 1e12:.2f} TB/s, against about 3 TB/s on an H100 "
          f"({edges / n:.1f} edges per event kept)")


def query_path(pos_t: torch.Tensor) -> torch.Tensor:
    """The KD-tree build forced onto its k-nearest-query path (as for clouds too dense for all pairs)."""
    import dagr_lite.graph.radius as radius_module

    budget, radius_module.PAIR_BUDGET = radius_module.PAIR_BUDGET, -1
    try:
        return radius_graph(pos_t, RADIUS, K)
    finally:
        radius_module.PAIR_BUDGET = budget


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def baseline_knn(pos: np.ndarray) -> None:
    tree = cKDTree(pos)
    tree.query(pos, k=K + 1, distance_upper_bound=RADIUS)


def stream(pos: np.ndarray, batch_us: float = 1000.0, times: list | None = None) -> int:
    """Insert ``pos`` in batches of ``batch_us``; returns the edge count, appends (t, seconds, events)."""
    graph = StreamingGraph(RADIUS, K)
    duration = pos[-1, 2] / BETA
    bounds = np.searchsorted(pos[:, 2], BETA * np.arange(0, duration + 2 * batch_us, batch_us))
    edges = 0
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        start = time.perf_counter()
        edges += graph.insert(pos[a:b]).shape[1]
        if times is not None:
            times.append((i * batch_us, time.perf_counter() - start, b - a))
    return edges


def stream_cost_as_the_window_fills(n: int) -> None:
    """Three windows of events at the same rate: cost per event while the window fills and after."""
    clouds = [event_cloud(n, seed=s) for s in range(3)]
    for i, cloud in enumerate(clouds):
        cloud[:, 2] += i * BETA * WINDOW_US
    times: list = []
    stream(np.concatenate(clouds), times=times)
    spans = [(0, 5_000), (5_000, 15_000), (15_000, 33_333), (33_333, 66_666), (66_666, 100_000)]
    parts = []
    for lo, hi in spans:
        sel = [(s, e) for t, s, e in times if lo <= t < hi]
        seconds, events = sum(s for s, _ in sel), sum(e for _, e in sel)
        parts.append(f"{lo / 1000:.0f}-{hi / 1000:.0f} ms: {seconds / max(events, 1) * 1e6:.2f}")
    print(f"  streaming cost per event (us) as the window fills, then slides: {'; '.join(parts)}")


class IndexAddGCN(torch.nn.Module):
    """The baseline: message passing with gather + index_add_ (PyG-style, linear first)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.lin = torch.nn.Linear(in_channels, out_channels, bias=False)
        self.bias = torch.nn.Parameter(torch.zeros(out_channels))

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        n = x.shape[0]
        src, dst = edge_index
        loops = torch.arange(n, device=x.device)
        src, dst = torch.cat([src, loops]), torch.cat([dst, loops])
        deg = torch.bincount(dst, minlength=n).float()
        norm = (deg[src] * deg[dst]).rsqrt()
        h = self.lin(x)
        out = h.new_zeros(n, h.shape[1]).index_add_(0, dst, h[src] * norm[:, None])
        return out + self.bias


def _memory_probe(n: int, queue) -> None:
    """Peak of the build's numpy allocations (tracemalloc; the KD-tree's own nodes are not traced)."""
    pos = event_cloud(n)
    radius_graph(pos[:1000], RADIUS, K)  # load everything once before measuring
    tracemalloc.start()
    edges = radius_graph(pos, RADIUS, K)
    _, traced_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    queue.put((traced_peak, pos.nbytes, edges.numel() * 8))


def on_gpu(pos_t: torch.Tensor, edges: torch.Tensor, cpu_build: float, ReferenceGCN, reference_name: str,
           repeats: int) -> None:
    """The torch backend and the GCN layer on the first CUDA GPU (times after synchronising)."""
    device = torch.device("cuda")
    name, n = torch.cuda.get_device_name(device), len(pos_t)
    pos_c = pos_t.to(device)

    def build():
        out = radius_graph(pos_c, RADIUS, K, backend="torch")
        torch.cuda.synchronize(device)
        return out

    assert torch.equal(build().cpu(), edges)  # also the warm-up
    gpu_build = best_of(build, repeats)
    print(f"  torch backend on {name} {gpu_build:6.3f} s  {n / gpu_build / 1e6:5.2f} M events/s   "
          f"vs the KD-tree on this CPU {cpu_build:6.3f} s -> {cpu_build / gpu_build:.1f}x faster (identical edges)")
    x = torch.randn(n, 32, device=device, requires_grad=True)
    conv, reference = GCNConv(32, 64).to(device), ReferenceGCN(32, 64).to(device)
    edges_c = edges.to(device)
    op = GraphOperator(edges_c, n)

    def ours_step():
        conv(x, op).sum().backward()
        torch.cuda.synchronize(device)

    def reference_step():
        reference(x, edges_c).sum().backward()
        torch.cuda.synchronize(device)

    ours_step(), reference_step()
    t_ours, t_ref = best_of(ours_step, repeats), best_of(reference_step, repeats)
    print(f"  GCN 32->64 fwd+bwd on the GPU {t_ours * 1e3:6.2f} ms   {reference_name} {t_ref * 1e3:6.2f} ms "
          f"-> ratio {t_ref / t_ours:.2f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50_000, 200_000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{WIDTH}x{HEIGHT}, {WINDOW_US} us, R={RADIUS} px, beta={BETA} px/us, K={K}, "
          f"{torch.get_num_threads()} threads")
    try:
        from torch_geometric.nn import GCNConv as ReferenceGCN  # optional, never a dependency
        reference_name = "torch_geometric GCNConv"
    except ImportError:
        ReferenceGCN, reference_name = IndexAddGCN, "index_add_ message passing"
    for n in args.sizes:
        pos = event_cloud(n)
        pos_t = torch.from_numpy(pos)
        baseline = best_of(lambda: baseline_knn(pos), args.repeats)
        ours = best_of(lambda: radius_graph(pos_t, RADIUS, K), args.repeats)
        edges = radius_graph(pos_t, RADIUS, K)
        print(f"\nN = {n:,}: {edges.shape[1]:,} edges ({edges.shape[1] / n:.1f} per event)")
        print(f"  batch build       {ours:6.3f} s  {n / ours / 1e6:5.2f} M events/s   "
              f"plain cKDTree query(k={K + 1}) {baseline:6.3f} s -> ratio {baseline / ours:.2f}x")
        queries = best_of(lambda: query_path(pos_t), args.repeats)
        assert torch.equal(query_path(pos_t), edges)
        print(f"  k-nearest queries {queries:6.3f} s  (the dense-cloud path) vs all pairs within R "
              f"{ours:6.3f} s -> all pairs {queries / ours:.2f}x faster (identical edges)")
        torch_backend = best_of(lambda: radius_graph(pos_t, RADIUS, K, backend="torch"), args.repeats)
        assert torch.equal(radius_graph(pos_t, RADIUS, K, backend="torch"), edges)
        pairs = candidate_pairs(pos_t)
        print(f"  torch backend     {torch_backend:6.3f} s  {n / torch_backend / 1e6:5.2f} M events/s   "
              f"vs the KD-tree {ours:6.3f} s -> {torch_backend / ours:.2f}x its time (identical edges); "
              f"{pairs / n:.0f} candidate pairs per event")
        gpu_needed(n, pairs, edges.shape[1])
        streamed = best_of(lambda: stream(pos), 1)
        assert stream(pos) == edges.shape[1]
        print(f"  streaming, 1 ms   {streamed:6.3f} s  {streamed / n * 1e6:5.2f} us/event  "
              f"vs batch {ours / n * 1e6:5.2f} us/event -> {streamed / ours:.2f}x the batch cost")
        stream_cost_as_the_window_fills(n)
        x = torch.randn(n, 32, requires_grad=True)
        conv, reference = GCNConv(32, 64), ReferenceGCN(32, 64)
        op = GraphOperator(edges, n)

        def ours_step():
            conv(x, op).sum().backward()

        def reference_step():
            reference(x, edges).sum().backward()

        ours_step(), reference_step()
        t_ours, t_ref = best_of(ours_step, args.repeats), best_of(reference_step, args.repeats)
        prepare = best_of(lambda: GraphOperator(edges, n), 1)
        print(f"  GCN 32->64 fwd+bwd {t_ours * 1e3:6.1f} ms   {reference_name} {t_ref * 1e3:6.1f} ms "
              f"-> ratio {t_ref / t_ours:.1f}x   (operator prepared once per graph: {prepare * 1e3:.0f} ms)")
        if torch.cuda.is_available():
            on_gpu(pos_t, edges, ours, ReferenceGCN, reference_name, args.repeats)
    n = max(args.sizes)
    queue = mp.get_context("spawn").Queue()
    process = mp.get_context("spawn").Process(target=_memory_probe, args=(n, queue))
    process.start()
    traced, pos_bytes, edge_bytes = queue.get()
    process.join()
    print(f"\npeak memory of the batch build at N = {n:,}: {traced / 2**20:.0f} MiB of numpy allocations "
          f"(tracemalloc); input {pos_bytes / 2**20:.1f} MiB, output {edge_bytes / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
