"""Event graph and GCN speed, against baselines measured in the same run.

    python benchmarks/graph.py [--sizes 50000 200000] [--repeats 3] [--no-loader]

Clouds: N events in a 33 ms window at 640x360, moving blobs (events on their outlines) plus
10 % uniform noise; R = 5 px, beta = 5 px / 10 ms, K = 16. Prints:
  * batch graph build (causal, capped; the compiled builder, ``backend="auto"`` on a CPU) vs a
    plain ``cKDTree`` build + ``query(k=K+1, distance_upper_bound=R)`` over all events
    (non-causal, no cap handling), on all cores and on one; and the KD-tree and torch builders
    (identical edges) against it;
  * streaming insertion in 1 ms and 5 ms batches, compiled against the KD-tree backend, cost per
    event, and over three windows of events: the cost per event while the window fills and after;
  * streams at a camera's rates, inserted in 1 ms and 5 ms batches, with integer microseconds:
    the stub's rate at 320x180, 500,000 events/s at 320x240, and a Prophesee-like 5 million
    events/s at 1280x720 with a hot pixel firing every 3 us and bursts of events at one pixel and
    one microsecond;
  * the training loader's graph per batch of the stub recipe (its own samples, augmented), the
    KD-tree builder against the compiled one (``--no-loader`` skips it: it needs the stub dataset);
  * GCN layer forward + backward, 32 -> 64 channels, vs ``torch_geometric.nn.GCNConv`` if it is
    installed, else an ``index_add_`` message-passing layer written here;
  * peak memory the batch build adds (peak resident size, in a fresh process);
  * with a CUDA GPU: the torch backend on it against the compiled builder on this CPU (identical
    edges), and the GCN layer on it against the reference layer on it.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from dagr_lite.data import format as fmt
from dagr_lite.graph import StreamingGraph, radius_graph
from dagr_lite.nn import GCNConv, GraphOperator

WIDTH, HEIGHT, WINDOW_US = 640, 360, fmt.DEFAULT_WINDOW_US
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
        return radius_graph(pos_t, RADIUS, K, backend="kdtree")
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


def stream(pos: np.ndarray, batch_us: float = 1000.0, times: list | None = None, backend: str = "compiled") -> int:
    """Insert ``pos`` in batches of ``batch_us``; returns the edge count, appends (t, seconds, events)."""
    graph = StreamingGraph(RADIUS, K, backend=backend)
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


def camera_stream(rate: float, seconds: float, width: int, height: int, *, hot_us: int = 0, bursts: int = 0,
                  seed: int = 0) -> np.ndarray:
    """``(n, 3)`` positions of a camera-like stream: integer pixels and microseconds, hands as moving
    blob outlines plus 10 % noise, optionally a hot pixel firing every ``hot_us`` and ``bursts``
    per second of 20 events at one pixel and one microsecond."""
    rng = np.random.default_rng(seed)
    n = int(rate * seconds)
    t = rng.integers(0, int(seconds * 1e6), n)
    blobs = 6
    centre = rng.uniform([0.2 * width, 0.2 * height], [0.8 * width, 0.8 * height], (blobs, 2))
    velocity = rng.uniform(-0.3, 0.3, (blobs, 2)) * width / 1e6  # px / us
    radius = rng.uniform(0.03, 0.1, blobs) * width
    which = rng.integers(0, blobs, n)
    angle = rng.uniform(0, 2 * np.pi, n)
    xy = centre[which] + velocity[which] * t[:, None] + np.stack([np.cos(angle), np.sin(angle)], 1) * radius[which, None]
    noise = rng.random(n) < 0.1
    xy[noise] = rng.uniform([0, 0], [width, height], (int(noise.sum()), 2))
    xy = np.mod(np.round(xy), [width, height])
    parts = [np.concatenate([xy, t[:, None]], 1)]
    if hot_us:
        hot_t = np.arange(0, int(seconds * 1e6), hot_us)
        parts.append(np.stack([np.full(len(hot_t), width // 3), np.full(len(hot_t), height // 3), hot_t], 1))
    if bursts:
        at = rng.integers(0, int(seconds * 1e6), int(bursts * seconds))
        pixel = rng.integers(0, [width, height], (len(at), 2))
        parts.append(np.repeat(np.concatenate([pixel, at[:, None]], 1), 20, axis=0))
    events = np.concatenate(parts).astype(np.float64)
    events = events[np.argsort(events[:, 2], kind="stable")]
    events[:, 2] *= BETA
    return events


def streams_at_camera_rates(seconds: float) -> None:
    """Per-event cost of streaming insertion at a camera's rates, compiled against the KD-tree backend."""
    scenes = [("stub rate, 320x180", camera_stream(155_000, seconds, 320, 180)),
              ("500k events/s, 320x240", camera_stream(500_000, seconds, 320, 240)),
              ("5M events/s, 1280x720, hot pixel + bursts",
               camera_stream(5_000_000, seconds / 4, 1280, 720, hot_us=3, bursts=2000))]
    print(f"\nstreams at a camera's rates ({seconds:g} s; the 5M stream {seconds / 4:g} s), us per event:")
    for name, pos in scenes:
        row = []
        for batch_us in (1000.0, 5000.0):
            edges = stream(pos, batch_us)  # also the warm-up
            compiled_s = best_of(lambda: stream(pos, batch_us), 2)
            row.append(f"{batch_us / 1000:g} ms: {compiled_s / len(pos) * 1e6:5.2f}")
        kdtree_s = best_of(lambda: stream(pos, 5000.0, backend="kdtree"), 1)
        assert stream(pos, 5000.0, backend="kdtree") == edges
        print(f"  {name:42s} {len(pos) / seconds if 'hot' not in name else len(pos) * 4 / seconds:10,.0f} ev/s  "
              f"compiled {'; '.join(row)}   KD-tree 5 ms: {kdtree_s / len(pos) * 1e6:5.2f} "
              f"({kdtree_s / compiled_s:.1f}x the compiled time)")


def loader_graphs(batches: int) -> None:
    """The training loader's graph per batch of the stub recipe: KD-tree builder against the compiled one."""
    from dagr_lite.config import build_dataset, compose_config, graph_spec
    from dagr_lite.data.collate import collate

    cfg = compose_config("train")
    dataset = build_dataset(cfg, "train", train=True, with_image=True)
    spec = graph_spec(cfg.model)
    rng = np.random.default_rng(0)
    size = cfg.loader.batch_size
    samples = [collate([dataset[int(i)] for i in rng.integers(0, len(dataset), size)]) for _ in range(batches)]
    times = {}
    for backend in ("kdtree", "compiled"):
        for batch in samples[:1]:  # warm-up
            spec.edges(batch.events, batch.batch_index, workers=1, backend=backend)
        times[backend] = best_of(lambda: [spec.edges(b.events, b.batch_index, workers=1, backend=backend)
                                          for b in samples], 2) / batches
    for batch in samples:
        assert torch.equal(spec.edges(batch.events, batch.batch_index, workers=1, backend="kdtree"),
                           spec.edges(batch.events, batch.batch_index, workers=1, backend="compiled"))
    events = np.mean([len(b.events) for b in samples])
    print(f"\nthe training loader's graph, stub recipe (batch {size}, {events:,.0f} events, one worker's thread): "
          f"KD-tree {times['kdtree'] * 1e3:.1f} ms, compiled {times['compiled'] * 1e3:.1f} ms per batch -> "
          f"{times['kdtree'] / times['compiled']:.1f}x less (identical edges)")


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


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith(field + ":"))


def _memory_probe(n: int, queue) -> None:
    """Peak resident memory the build adds (numpy's and the compiled kernels' arrays alike; Linux)."""
    pos = event_cloud(n)
    radius_graph(pos[:2_000], RADIUS, K)  # load and compile everything once before measuring
    with open("/proc/self/clear_refs", "w") as clear:
        clear.write("5")  # the peak (VmHWM) starts again from the resident size now
    before = _status_kib("VmRSS")
    edges = radius_graph(pos, RADIUS, K)
    queue.put(((_status_kib("VmHWM") - before) * 1024, pos.nbytes, edges.numel() * 8))


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
          f"vs the compiled builder on this CPU {cpu_build:6.3f} s -> {cpu_build / gpu_build:.1f}x faster (identical edges)")
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
    parser.add_argument("--stream-seconds", type=float, default=1.0, help="length of the camera-rate streams")
    parser.add_argument("--no-loader", action="store_true", help="skip the loader's graphs (needs the stub dataset)")
    parser.add_argument("--loader-batches", type=int, default=8)
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
        edges = radius_graph(pos_t, RADIUS, K)  # also the warm-up (the first call compiles, once per machine)
        baseline = best_of(lambda: baseline_knn(pos), args.repeats)
        ours = best_of(lambda: radius_graph(pos_t, RADIUS, K), args.repeats)
        one = best_of(lambda: radius_graph(pos_t, RADIUS, K, workers=1), args.repeats)
        print(f"\nN = {n:,}: {edges.shape[1]:,} edges ({edges.shape[1] / n:.1f} per event)")
        print(f"  batch build       {ours:6.3f} s  {n / ours / 1e6:5.2f} M events/s   "
              f"plain cKDTree query(k={K + 1}) {baseline:6.3f} s -> {baseline / ours:.2f}x faster "
              f"(one thread {one:6.3f} s -> {baseline / one:.2f}x)")
        kdtree = best_of(lambda: radius_graph(pos_t, RADIUS, K, backend="kdtree"), args.repeats)
        assert torch.equal(radius_graph(pos_t, RADIUS, K, backend="kdtree"), edges)
        queries = best_of(lambda: query_path(pos_t), 1)
        assert torch.equal(query_path(pos_t), edges)
        print(f"  KD-tree builder   {kdtree:6.3f} s (all pairs within R), {queries:6.3f} s (k-nearest queries) "
              f"-> the compiled one {kdtree / ours:.1f}x faster (identical edges)")
        torch_backend = best_of(lambda: radius_graph(pos_t, RADIUS, K, backend="torch"), args.repeats)
        assert torch.equal(radius_graph(pos_t, RADIUS, K, backend="torch"), edges)
        pairs = candidate_pairs(pos_t)
        print(f"  torch backend     {torch_backend:6.3f} s  {n / torch_backend / 1e6:5.2f} M events/s   "
              f"-> {torch_backend / ours:.1f}x the compiled time (identical edges); "
              f"{pairs / n:.0f} candidate pairs per event")
        gpu_needed(n, pairs, edges.shape[1])
        for batch_us in (1000.0, 5000.0):
            assert stream(pos, batch_us) == edges.shape[1]
            streamed = best_of(lambda: stream(pos, batch_us), 2)
            streamed_kd = best_of(lambda: stream(pos, batch_us, backend="kdtree"), 1)
            print(f"  streaming, {batch_us / 1000:g} ms   {streamed:6.3f} s  {streamed / n * 1e6:5.2f} us/event  "
                  f"KD-tree backend {streamed_kd / n * 1e6:5.2f} us/event -> {streamed_kd / streamed:.1f}x; "
                  f"batch {ours / n * 1e6:5.2f} us/event")
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
    streams_at_camera_rates(args.stream_seconds)
    if not args.no_loader:
        loader_graphs(args.loader_batches)
    n = max(args.sizes)
    queue = mp.get_context("spawn").Queue()
    process = mp.get_context("spawn").Process(target=_memory_probe, args=(n, queue))
    process.start()
    added, pos_bytes, edge_bytes = queue.get()
    process.join()
    print(f"\npeak memory the batch build adds at N = {n:,}: {added / 2**20:.0f} MiB (peak resident size, a fresh "
          f"process); input {pos_bytes / 2**20:.1f} MiB, output {edge_bytes / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
