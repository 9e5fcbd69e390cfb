"""Streaming detector speed: one update plus ``detect()`` against a full batch pass on the same samples.

    python benchmarks/streaming.py --ckpt <hybrid>/checkpoints/best.pt [<events_only>/checkpoints/best.pt]
                                   [--seconds 0.5] [--sizes 320x180 640x360] [--camera 320x240]
                                   [--camera-rate 450000] [--updates-ms 0.1 1 5] [--threads 2]
                                   [--keep-camera DIR]

Scenes: the stub's first test video (320x180); a hand scene of the stub's generator rendered and
emulated at 640x360; and a camera-rate scene at 320x240 (``--camera``): the same generator
emulated with contrast thresholds lowered until it emits ``--camera-rate`` events/s (up to 25 %
more), as a real sensor of one moving hand does (made once into a temporary folder; ``--keep-camera
DIR`` also keeps it, in the dataset layout, for ``python detect.py input=DIR/test/events/<video>.h5``). Images
arrive at 30 Hz and are part of the update they arrive in. For each checkpoint, scene and update size it prints:
  * the median and p95 latency of one update (push_events, any push_image, detect) against the
    median of full batch passes (graph build, model, decoding) on the samples of the same moments;
  * the real-time factor: seconds of recording per second of compute, detecting after every update,
    and the events per second sustained (events in / compute seconds);
  * the multiply-adds per event of the GCN layers (all stages), streaming against a full pass;
  * where an update's time goes.
The last three lines read ``1 ms update: <ratio>x faster than a full pass`` (the stub scene),
``5 ms updates, stub: real-time factor <f>`` and ``5 ms updates, 320x240 at <rate>k events/s:
real-time factor <f>``, each for every checkpoint given.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dagr_lite.data import format as fmt
from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import CarryPicture, Sample, channels_first, sample_start_us
from dagr_lite.data.labels import list_videos
from dagr_lite.data.writer import VideoWriter
from dagr_lite.apps.demo import Recording
from dagr_lite.data.spec import SampleSpec
from dagr_lite.engine.checkpoint import Checkpoint, load_checkpoint
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.nn.detector import Detector
from dagr_lite.nn import kernels
from dagr_lite.nn.gcn import GCNConv, GraphOperator
from dagr_lite.stream import StreamingDetector
from dagr_lite.synth.dvs import DVSParams, preset
from dagr_lite.synth.stub import STUB_DVS_MODEL, STUB_UPSAMPLE, HandScene, stub_root
from dagr_lite.synth.video import emulate_video

FIRST_FRAME = 3  # streams start at this frame (earlier events are the first image's context)


def recording(size: tuple[int, int], seconds: float, workdir: Path) -> tuple[str, Recording]:
    """The stub's first test video at 320x180; a scene of the same generator at any other size."""
    height, width = size
    if size == (180, 320):
        root = stub_root()
        video = list_videos(root, "test")[0]
        return f"stub test video {video}", Recording(root, "test", video)
    return f"hand scene {width}x{height}", emulated(workdir, f"scene{width}x{height}", height, width, seconds,
                                                    preset(STUB_DVS_MODEL))


def emulated(workdir: Path, video: str, height: int, width: int, seconds: float, params: DVSParams) -> Recording:
    """Hand scene 7 of the stub's generator, emulated with ``params`` into ``workdir``."""
    scene = HandScene(7, height=height, width=width, seconds=seconds + 0.3)
    with VideoWriter(workdir, "test", video, num_frames=scene.num_frames, height=height, width=width,
                     compression=None) as writer:
        emulate_video(scene, writer, params=params, upsample=STUB_UPSAMPLE, seed=7)
    return Recording(workdir, "test", video)


def streamed(rec: Recording, seconds: float) -> tuple[float, float, float]:
    """The span ``[t0, t1)`` streamed from frame ``FIRST_FRAME`` (at most ``seconds``) and its events per second."""
    t = rec.events["t"]
    t0 = float(rec.frame_times[FIRST_FRAME])
    t1 = min(t0 + seconds * 1e6, float(t[-1]))
    return t0, t1, np.count_nonzero((t >= t0) & (t < t1)) / ((t1 - t0) * 1e-6)


def camera_recording(size: tuple[int, int], seconds: float, rate: float, workdir: Path) -> tuple[str, Recording]:
    """A hand scene at ``size`` emitting ``rate`` to ``1.25 rate`` events/s after frame ``FIRST_FRAME``:
    the stub's DVS model with its contrast thresholds (and their spread) scaled, the scale found by
    bisection in log scale."""
    height, width = size
    base = preset(STUB_DVS_MODEL)
    low, high = 0.01, 1.0  # threshold scales: the lower emits more than wanted, the higher less (or enough)
    for attempt in range(12):
        scale = high if attempt == 0 else math.sqrt(low * high)
        params = dataclasses.replace(base, pos_threshold=base.pos_threshold * scale,
                                     neg_threshold=base.neg_threshold * scale,
                                     sigma_threshold=base.sigma_threshold * scale)
        rec = emulated(workdir, f"camera{attempt}", height, width, seconds, params)
        _, _, got = streamed(rec, seconds)
        if rate <= got <= 1.25 * rate:
            return (f"camera-rate hand scene {width}x{height} (contrast thresholds {params.pos_threshold:.3f})", rec)
        low, high = (low, scale) if got < rate else (scale, high)
    raise RuntimeError(f"could not emulate {rate:.0f} to {1.25 * rate:.0f} events/s at {width}x{height} "
                       f"(the last try gave {got:.0f})")


def kept_elsewhere(dest: Path) -> str | None:
    """Why ``dest`` cannot take a kept scene (it exists and is not an empty folder), or None."""
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        return f"--keep-camera {dest}: exists and is not an empty folder; choose a new one"
    return None


def keep_scene(workdir: Path, video: str, dest: Path) -> Path:
    """Copies ``video`` of ``workdir``'s test split (its event file and frame folder) into ``dest``,
    a new or empty folder, in the same layout; returns the event file's path there."""
    refused = kept_elsewhere(dest)
    if refused:
        raise SystemExit(refused)
    events = fmt.events_path(dest, "test", video)
    events.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(fmt.events_path(workdir, "test", video), events)
    shutil.copytree(fmt.frames_dir(workdir, "test", video), fmt.frames_dir(dest, "test", video))
    return events


def model_at(checkpoint: Checkpoint, height: int, width: int) -> Detector:
    """The checkpoint's EMA weights in its architecture at ``height x width`` (the weights do not depend on it)."""
    return checkpoint.model(dataclasses.replace(checkpoint.detector, height=height, width=width)).eval()


class MacCounter:
    """Multiply-adds of every GCN layer call: the sparse product on the narrower side plus the weight."""

    def __init__(self, model: Detector):
        self.total = 0
        self.handles = [m.register_forward_hook(self.hook) for m in model.modules() if isinstance(m, GCNConv)]
        kernels.OBSERVERS.append(self.compiled)

    def hook(self, module: GCNConv, args, output) -> None:
        x, graph = args
        nnz = len(graph._triplets[0]) if isinstance(graph, GraphOperator) else graph.shape[1] + len(x)
        self.add(module, nnz, output.shape[0])

    def compiled(self, block, x: torch.Tensor, graph: kernels.NodeGraph) -> None:
        """A block of one compiled pass (nn/kernels.py): its messages are summed before the weight."""
        rows = graph.num_nodes - graph.first
        self.total += (len(graph.src) + rows) * block.conv.in_channels
        self.total += rows * block.conv.in_channels * block.conv.out_channels

    def add(self, module: GCNConv, nnz: int, rows: int) -> None:
        self.total += nnz * min(module.in_channels, module.out_channels)
        self.total += rows * module.in_channels * module.out_channels

    def close(self) -> None:
        for handle in self.handles:
            handle.remove()
        kernels.OBSERVERS.remove(self.compiled)


def frame_at(rec: Recording, t_us: float) -> int:
    return int(np.searchsorted(rec.frame_times, t_us, side="right")) - 1


def stream_run(model: Detector, rec: Recording, update_us: float, t0: float, t1: float, *, sample: SampleSpec) -> dict:
    """Updates of ``update_us`` over ``[t0, t1)``: latencies, the time spent per part, GCN multiply-adds."""
    stream = StreamingDetector(model, dataclasses.replace(sample, refractory_us=0, support_us=0, max_events=None),
                               OperatingPoint(score=0.25, nms_iou=0.65))
    t, ev = rec.events["t"], rec.events
    k = frame_at(rec, t0)
    begin = int(np.searchsorted(t, rec.frame_times[k] - sample.context_us - sample.window_us - sample.graph_context_us))
    start = int(np.searchsorted(t, t0))
    if stream.hybrid:
        stream.push_image(rec.frames[k], rec.frame_times[k])
    stream.push_events(**{key: v[begin:start] for key, v in ev.items()})  # warm-up, not timed
    stream.detect(t0)
    stream.timings = {}
    counter = MacCounter(stream.net)  # the copy that answers
    latencies, events_in, next_frame = [], 0, k + 1
    now = t0
    while now < t1:
        end_t = now + update_us
        stop = int(np.searchsorted(t, end_t))
        tic = time.perf_counter()
        while stream.hybrid and next_frame < len(rec.frames) and rec.frame_times[next_frame] < end_t:
            stream.push_image(rec.frames[next_frame], rec.frame_times[next_frame])
            next_frame += 1
        stream.push_events(**{key: v[start:stop] for key, v in ev.items()})
        stream.detect(end_t)
        latencies.append(time.perf_counter() - tic)
        events_in += stop - start
        start, now = stop, end_t
    counter.close()
    return {"latency": np.array(latencies), "events": events_in, "macs": counter.total, "timings": stream.timings,
            "seconds": (t1 - t0) * 1e-6}


def sample_at(model: Detector, rec: Recording, t_query: float, *, sample: SampleSpec) -> Sample:
    """The batch sample a query at ``t_query`` reads: the latest frame (a model with an image), the
    events of its horizon (and graph context), and a carry branch's picture of every event since the
    image."""
    k = frame_at(rec, t_query)
    t_image = rec.frame_times[k]
    t = rec.events["t"]
    with_image = t_image if model.image is not None else None
    begin = math.ceil(sample_start_us(t_query, sample.window_us, with_image, sample.context_us))
    graph = sample.graph_start_us(t_query, with_image)
    keep = slice(int(np.searchsorted(t, graph)), int(np.searchsorted(t, t_query, side="right")))
    x, y, tt, p = (rec.events[key][keep] for key in ("x", "y", "t", "p"))
    events = torch.from_numpy(np.stack([x, y, tt - t_image, p], 1).astype(np.float32)).reshape(-1, 4)
    parts = [rec.frames[k]]
    if model.carry is not None:  # and the picture of every event since the image, which its carry branch reads
        height, width = parts[0].shape[:2]
        carry = CarryPicture(height, width, t_image, sample.carry_recent_us, sample.carry_confirm_us,
                             sample.carry_align_us, rec.frames[k], sample.carry_spans_us, sample.carry_onset)
        since = slice(int(np.searchsorted(t, carry.reads_from_us)), keep.stop)
        carry.add(*(rec.events[key][since] for key in ("x", "y", "t", "p")))
        parts.append(carry.picture(t_query))
    return Sample(events=events, image=torch.from_numpy(channels_first(parts)),
                  boxes=torch.zeros((0, 4)), labels=torch.zeros(0, dtype=torch.int64), video=rec.video, frame=k,
                  image_frame=k, t_start_us=int(begin), t_end_us=int(t_query), t_image_us=int(t_image),
                  moved_frame=bool(model.carry is not None and sample.carry_align_us))


def batch_pass(model: Detector, batch) -> None:
    """The batch model's answer to ``batch``: its event graph built (a model with events), the model,
    decoding and NMS."""
    with torch.no_grad():
        if model.events is not None:
            batch.edge_index = model.graph_spec.edges(batch.events, batch.batch_index)
        model(batch, conf_threshold=0.25, nms_threshold=0.65)


def full_pass(model: Detector, rec: Recording, t_query: float, *, sample: SampleSpec,
              repeats: int = 2) -> tuple[float, int, int]:
    """Seconds (best of ``repeats``) of one batch pass on the sample at ``t_query``, its GCN
    multiply-adds and its event count (its graph context included)."""
    one = sample_at(model, rec, t_query, sample=sample)
    best, macs = np.inf, 0
    for _ in range(repeats):
        batch = collate([one])
        counter = MacCounter(model)
        tic = time.perf_counter()
        batch_pass(model, batch)
        best = min(best, time.perf_counter() - tic)
        counter.close()
        macs = counter.total
    return best, macs, len(one.events)


def bench_scene(state: Checkpoint, name: str, rec: Recording, args) -> tuple[float, dict[float, dict]]:
    """Prints the scene's table and where the time goes; returns its event rate and, per update
    size, the speed-up, the real-time factor and the events per second sustained."""
    model = model_at(state, rec.height, rec.width)
    sample = state.sample
    if args.graph_context_us is not None:
        sample = dataclasses.replace(sample, graph_context_us=args.graph_context_us)
    t0, t1, rate = streamed(rec, args.seconds)
    print(f"\n{name}: {rec.width}x{rec.height}, {(t1 - t0) / 1e6:.2f} s streamed from frame {FIRST_FRAME}, "
          f"{rate / 1e3:.0f}k events/s; {label(state)} model, images at 30 Hz, graph context "
          f"{sample.graph_context_us} us")
    moments = np.linspace(t0 + 2_000, t1 - 1, args.full_passes)
    passes = [full_pass(model, rec, m, sample=sample) for m in moments]
    full_s = float(np.median([p[0] for p in passes]))
    full_macs = sum(p[1] for p in passes) / max(1, sum(p[2] for p in passes))
    print(f"full batch pass (graph, model, decoding), median of {len(passes)} moments: {1e3 * full_s:.1f} ms, "
          f"{np.median([p[2] for p in passes]):.0f} events per sample")
    header = (f"{'update':>8} {'events':>7} {'median ms':>10} {'p95 ms':>8} {'speed-up':>9} {'real-time':>10} "
              f"{'sustained ev/s':>15} {'GCN MACs/event':>22}")
    print(header + "\n" + "-" * len(header))
    result, parts = {}, {}
    for update_ms in args.updates_ms:
        seconds = min(t1 - t0, args.seconds * 1e6 * min(1.0, update_ms / 1.0)) if update_ms < 1 else t1 - t0
        run = stream_run(model, rec, update_ms * 1e3, t0, t0 + seconds, sample=sample)
        latency = run["latency"]
        median, p95 = float(np.median(latency)), float(np.percentile(latency, 95))
        speedup = full_s / median
        rtf = run["seconds"] / latency.sum()
        macs = run["macs"] / max(1, run["events"])
        sustained = run["events"] / latency.sum()
        print(f"{update_ms:>6g}ms {run['events'] / len(latency):>7.0f} {1e3 * median:>10.2f} {1e3 * p95:>8.2f} "
              f"{speedup:>8.1f}x {rtf:>10.2f} {sustained:>15,.0f} {macs:>10.0f} / {full_macs:<9.0f}")
        parts[update_ms] = {name: 1e3 * value / len(latency) for name, value in run["timings"].items()}
        result[update_ms] = {"speedup": speedup, "rtf": rtf, "sustained": sustained}
    print("where an update's time goes (ms per update):")
    names = sorted({name for p in parts.values() for name in p}, key=lambda n: -max(p.get(n, 0) for p in parts.values()))
    print("  " + f"{'part':<30}" + "".join(f"{f'{u:g} ms':>10}" for u in parts))
    for name in names:
        print("  " + f"{name:<30}" + "".join(f"{p.get(name, 0.0):>10.2f}" for p in parts.values()))
    return rate, result


def label(checkpoint: Checkpoint) -> str:
    """The checkpoint's model name, with ``late query`` where its query maps join the head after its towers."""
    return checkpoint.model_name + (", late query" if checkpoint.detector.late_query else "")


def size_of(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(H, W)``."""
    width, height = (int(v) for v in text.lower().split("x"))
    return height, width


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", nargs="+", required=True, help="trained checkpoints (hybrid and/or events-only)")
    parser.add_argument("--seconds", type=float, default=0.5, help="recording streamed per update size "
                        "(updates under 1 ms stream proportionally less)")
    parser.add_argument("--sizes", nargs="+", default=["320x180", "640x360"])
    parser.add_argument("--camera", default="320x240", help="size of the camera-rate scene ('none': skip it)")
    parser.add_argument("--camera-rate", type=float, default=450_000, help="least events/s of the camera-rate scene")
    parser.add_argument("--updates-ms", nargs="+", type=float, default=[0.1, 1.0, 5.0])
    parser.add_argument("--full-passes", type=int, default=8, help="moments at which a full pass is timed")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--keep-camera", type=Path, default=None, metavar="DIR",
                        help="also keep the camera-rate scene in DIR (new or empty), for detect.py")
    parser.add_argument("--graph-context-us", type=int, default=None,
                        help="time the checkpoints on a sample with this graph context (data.graph_context_us) "
                             "instead of their own (0 or at least the graph's reach)")
    args = parser.parse_args()
    if args.keep_camera is not None and (refused := kept_elsewhere(args.keep_camera)):
        parser.error(refused)  # before any scene is made
    torch.set_num_threads(args.threads)
    states = {path: load_checkpoint(path) for path in args.ckpt}
    print(f"torch {torch.__version__}, {args.threads} threads, checkpoints {', '.join(args.ckpt)}")
    summary = []  # (line key, model name, value)
    with tempfile.TemporaryDirectory() as workdir:
        scenes = [recording(size_of(text), args.seconds, Path(workdir)) + ("stub" if size_of(text) == (180, 320) else text,)
                  for text in args.sizes]
        if args.camera != "none":
            scenes.append(camera_recording(size_of(args.camera), args.seconds, args.camera_rate, Path(workdir))
                          + ("camera",))
            if args.keep_camera is not None:
                kept = keep_scene(Path(workdir), scenes[-1][1].video, args.keep_camera)
                print(f"camera-rate scene kept: {kept} (its frames beside it); run it with python detect.py "
                      f"ckpt=CKPT input={kept} rate_hz=100 sensor.model_size=sensor")
        for path, state in states.items():
            model_name = label(state)
            for name, rec, kind in scenes:
                rate, result = bench_scene(state, name, rec, args)
                if kind == "stub" and 1.0 in result:
                    summary.append(("1 ms update", model_name, f"{result[1.0]['speedup']:.1f}x faster than a full pass"))
                if kind == "stub" and 5.0 in result:
                    summary.append(("5 ms updates, stub", model_name, f"real-time factor {result[5.0]['rtf']:.2f}"))
                if kind == "camera" and 5.0 in result:
                    summary.append((f"5 ms updates, {rec.width}x{rec.height} at {rate / 1e3:.0f}k events/s", model_name,
                                    f"real-time factor {result[5.0]['rtf']:.2f}"))
    print()
    for key in dict.fromkeys(k for k, _, _ in summary):  # one line each, every model's figure on it
        print(f"{key}: " + ", ".join(f"{value} ({model})" for k, model, value in summary if k == key))


if __name__ == "__main__":
    main()
