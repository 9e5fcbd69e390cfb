"""The floor of a streaming answer's cost: the multiply-adds each part of the model must redo from
one answer to the next, and the real-time factor they leave on this machine.

    python benchmarks/answer_floor.py --ckpt <hybrid>/checkpoints/best.pt [<events_only>/checkpoints/best.pt]
                                      [--updates-ms 5] [--answers 24] [--camera 320x240]
                                      [--set late_query=true carry_width=0]

For each checkpoint and scene (the stub's first test video at 320x180; with ``--camera``, the
camera-rate scene of ``benchmarks/streaming.py``), the batch model answers at ``--answers`` moments
``--updates-ms`` apart, on the samples the streaming detector answers (``streaming.sample_at``).
Every convolution's output map is kept. Between two answers with the same image, a cell of a
layer's output that differs (exact equality) is one that an exact answer must compute again: an
answer that recomputes those cells and reuses every other is the best that "an answer that costs
what changed" can do by recomputing cells (an update of a linear layer by the difference of its
inputs alone could cost less; the activation after each layer still needs the cell's new value).
Per part of the model (image branch, carry branch, the event branch's dense stages, fusion, head)
it prints the convolutions' multiply-adds in a full pass and those whose output changed (the mean
over the pairs), then:
  * the convolutions' throughput here: their multiply-adds over their time in full passes, each
    convolution timed alone (hooks before and after it; the best of five passes);
  * the floor of an answer: each convolution's time scaled by the share of its cells that changed,
    nothing else counted (no graph, no GCN layer, no normalisation or activation, no decoding), and
    the real-time factor such an answer would allow, ``update / floor``, beside the one of every
    cell recomputed;
  * the changed multiply-adds at the throughput of a 1024 x 1024 float32 matrix product (the best of
    ten): a reference for convolutions that ran as fast as the library's large products.
An answer whose image is new is left out (the image's side runs once a frame). ``--set key=value``
rebuilds the checkpoint's architecture with changed settings (``DetectorConfig`` fields) and
untrained weights, to price a design before training it: which cells change depends on the events
and on where the query time enters, hardly on the weights.
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml
from torch import nn

from dagr_lite.data.collate import collate
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.nn.detector import Detector, DetectorConfig
from streaming import batch_pass, camera_recording, frame_at, model_at, recording, sample_at, size_of, streamed

PARTS = (("image.", "image branch"), ("carry.", "carry branch"), ("events.", "event branch (dense stages)"),
         ("to_nodes.", "fusion"), ("fuse.", "fusion"), ("attend.", "fusion"), ("event_head.", "event head"),
         ("head.", "head"))


def part_of(name: str) -> str:
    """The part of the model that the module called ``name`` belongs to."""
    return next((part for prefix, part in PARTS if name.startswith(prefix)), "other")


def conv_macs_per_cell(conv: nn.Conv2d) -> int:
    """Multiply-adds of one output cell of ``conv``: every output channel reads its group's input channels
    over the kernel."""
    kh, kw = conv.kernel_size
    return conv.out_channels * (conv.in_channels // conv.groups) * kh * kw


def changed_cells(before: torch.Tensor, after: torch.Tensor) -> int:
    """Cells of a ``(1, C, H, W)`` map where any channel differs."""
    return int((before != after).any(dim=1).sum())


class ConvRecorder:
    """Keeps every convolution's output of one pass and, when asked, times each convolution alone."""

    def __init__(self, model: nn.Module):
        self.convs = {name: m for name, m in model.named_modules() if isinstance(m, nn.Conv2d)}
        self.outputs: dict[str, torch.Tensor] = {}
        self.seconds: dict[str, float] = {}
        self._tic: dict[str, float] = {}
        self.handles = []
        for name, conv in self.convs.items():
            self.handles.append(conv.register_forward_pre_hook(self._before(name)))
            self.handles.append(conv.register_forward_hook(self._after(name)))

    def _before(self, name: str):
        def hook(module, args):
            self._tic[name] = time.perf_counter()
        return hook

    def _after(self, name: str):
        def hook(module, args, output):
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - self._tic[name]
            self.outputs[name] = output.detach().clone()
        return hook

    def close(self) -> None:
        for handle in self.handles:
            handle.remove()


def product_throughput() -> float:
    """Multiply-adds per second of a 1024 x 1024 float32 matrix product (the best of ten)."""
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    for _ in range(3):
        a @ b
    best = np.inf
    for _ in range(10):
        tic = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - tic)
    return 1024 ** 3 / best


def answer(model: Detector, recorder: ConvRecorder, one) -> dict[str, torch.Tensor]:
    """Every convolution's output map on the sample ``one`` (a batch of one)."""
    recorder.outputs = {}
    batch_pass(model, collate([one]))
    return recorder.outputs


def detector_settings(items: list[str]) -> dict:
    """``KEY=VALUE`` items as :class:`DetectorConfig` fields, each value of its field's type (a list for a
    tuple field); an unknown key, the input size (the scene's) or a value of the wrong type is an error
    naming it."""
    defaults = {f.name: f for f in dataclasses.fields(DetectorConfig)}
    settings = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise ValueError(f"--set takes KEY=VALUE, got {item!r}")
        if key not in defaults or key in ("height", "width", "graph"):
            known = sorted(set(defaults) - {"height", "width", "graph"})
            raise ValueError(f"--set {key}: not a detector setting that can be priced; one of {known}")
        value = yaml.safe_load(text)
        kind = defaults[key].type
        kind = kind if isinstance(kind, str) else getattr(kind, "__name__", str(kind))
        if kind.startswith("bool") and isinstance(value, bool):
            pass
        elif kind.startswith("int") and isinstance(value, int) and not isinstance(value, bool):
            pass
        elif kind.startswith("float") and isinstance(value, (int, float, str)) and not isinstance(value, bool):
            try:
                value = float(value)  # YAML reads 1e5 as a string
            except ValueError:
                raise ValueError(f"--set {key}={text}: expected a number, got {value!r}") from None
        elif kind.startswith("tuple") and isinstance(value, list):
            value = tuple(value)
        elif kind.startswith("str") and isinstance(value, str):
            pass
        else:
            raise ValueError(f"--set {key}={text}: expected a value of type {kind}, got {value!r}")
        settings[key] = value
    return settings


def built(state, height: int, width: int, settings: dict) -> tuple[Detector, str]:
    """The checkpoint's model, or with ``settings`` its architecture changed and untrained."""
    if not settings:
        return model_at(state, height, width), state.model_name
    cfg = dataclasses.replace(state.detector, height=height, width=width, **settings)
    torch.manual_seed(0)
    changes = " ".join(f"{k}={v}" for k, v in settings.items())
    return Detector(cfg).eval(), f"{state.model_name} with {changes} (untrained)"


def rtf(update_ms: float, ms: float) -> float:
    """The real-time factor of answers ``update_ms`` apart that each take ``ms`` (infinite at 0 ms)."""
    return update_ms / ms if ms > 0 else float("inf")


def floor_scene(state, rec, scene: str, args, settings: dict, peak: float | None = None) -> dict:
    """Prints one checkpoint's table on one scene; returns the model's name, the real-time factors its
    floor and a full pass allow (``floor``, ``full``; ``peak``: the floor at ``peak`` multiply-adds a
    second), the changed share of each part and the pairs of answers compared."""
    model, name = built(state, rec.height, rec.width, settings)
    sample = state.sample
    t0, t1, rate = streamed(rec, args.seconds)
    update_us = args.updates_ms * 1e3
    moments = [m for m in (t0 + 2_000 + k * update_us for k in range(args.answers + 1)) if m < t1]
    if len(moments) < 2:
        raise ValueError(f"{scene}: {(t1 - t0) / 1e3:.0f} ms streamed hold fewer than two answers "
                         f"{args.updates_ms:g} ms apart (--seconds, --updates-ms)")
    recorder = ConvRecorder(model)
    # each convolution's time in a full pass (timed alone), the best of five passes
    one = sample_at(model, rec, moments[0], sample=sample)
    best_seconds, best_total = {}, np.inf
    for _ in range(5):
        recorder.seconds = {}
        tic = time.perf_counter()
        repeat = answer(model, recorder, one)
        total = time.perf_counter() - tic
        if total < best_total:
            best_total, best_seconds = total, dict(recorder.seconds)
    again = answer(model, recorder, one)  # the last timed pass repeated: it must change no cell
    unstable = sum(changed_cells(repeat[k], again[k]) for k in repeat)
    cells = {k: out.shape[-2] * out.shape[-1] for k, out in repeat.items()}
    macs = {k: conv_macs_per_cell(recorder.convs[k]) * cells[k] for k in repeat}
    changed = {k: 0 for k in repeat}  # changed output cells of each convolution, summed over the pairs
    pairs = 0
    previous, previous_frame = None, None
    for m in moments:
        outputs = answer(model, recorder, sample_at(model, rec, m, sample=sample))
        frame = frame_at(rec, m) if model.image is not None else None
        if previous is not None and frame == previous_frame:
            pairs += 1
            for k, out in outputs.items():
                changed[k] += changed_cells(previous[k], out)
        previous, previous_frame = outputs, frame
    recorder.close()
    print(f"\n{name}, {scene}: {rec.width}x{rec.height}, {rate / 1e3:.0f}k events/s; {pairs} pairs of answers "
          f"{args.updates_ms:g} ms apart with the same image; a repeated answer changes {unstable} cells")
    if not pairs:
        print("  no two answers share an image: nothing to compare (a longer --seconds or shorter --updates-ms)")
        nan = float("nan")
        return {"name": name, "floor": nan, "full": nan, "peak": nan, "shares": {}, "pairs": 0}
    share = {k: changed[k] / pairs / cells[k] for k in repeat}  # mean share of the map that changed
    header = f"  {'part':<30}{'full pass, M MACs':>20}{'changed, M MACs':>18}{'share':>8}"
    print(header + "\n  " + "-" * (len(header) - 2))
    parts: dict[str, list[float]] = {}
    for k in repeat:
        totals = parts.setdefault(part_of(k), [0.0, 0.0])
        totals[0] += macs[k]
        totals[1] += macs[k] * share[k]
    for part, (full, moved) in sorted(parts.items(), key=lambda item: -item[1][0]):
        print(f"  {part:<30}{full / 1e6:>20.1f}{moved / 1e6:>18.1f}{moved / full:>8.0%}")
    total_full, total_changed = sum(v[0] for v in parts.values()), sum(v[1] for v in parts.values())
    print(f"  {'all convolutions':<30}{total_full / 1e6:>20.1f}{total_changed / 1e6:>18.1f}"
          f"{total_changed / total_full:>8.0%}")
    # each convolution's own time, scaled by the share of its map that changed
    conv_ms = 1e3 * sum(best_seconds.values())
    floor_ms = 1e3 * sum(best_seconds[k] * share[k] for k in repeat)
    print(f"  convolutions here: {total_full / conv_ms / 1e6:.1f} G MACs/s ({conv_ms:.1f} ms of a "
          f"{1e3 * best_total:.1f} ms full pass with these hooks)")
    print(f"  floor of an answer: {floor_ms:.2f} ms, each convolution's time times the share of its cells that "
          f"changed; {args.updates_ms:g} ms updates: real-time factor at most {rtf(args.updates_ms, floor_ms):.2f} "
          f"(every cell recomputed: {rtf(args.updates_ms, conv_ms):.2f})")
    result = {"name": name, "floor": rtf(args.updates_ms, floor_ms), "full": rtf(args.updates_ms, conv_ms),
              "shares": {part: moved / full for part, (full, moved) in parts.items()}, "pairs": pairs,
              "peak": float("nan")}
    if peak is not None:
        peak_ms = 1e3 * total_changed / peak
        print(f"  at the matrix product's {peak / 1e9:.1f} G MACs/s: {peak_ms:.2f} ms; real-time factor at most "
              f"{rtf(args.updates_ms, peak_ms):.2f}")
        result["peak"] = rtf(args.updates_ms, peak_ms)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", nargs="+", required=True, help="trained checkpoints (hybrid and/or events-only)")
    parser.add_argument("--updates-ms", type=float, default=5.0, help="time between two answers")
    parser.add_argument("--answers", type=int, default=24, help="answers per scene")
    parser.add_argument("--seconds", type=float, default=0.5, help="recording used per scene")
    parser.add_argument("--camera", default="none", help="size of the camera-rate scene, e.g. 320x240 ('none': skip)")
    parser.add_argument("--camera-rate", type=float, default=450_000, help="least events/s of the camera-rate scene")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="DetectorConfig fields changed (the model then untrained)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        settings = detector_settings(args.set)
    except ValueError as err:
        parser.error(str(err))
    peak = product_throughput()
    print(f"torch {torch.__version__}, {args.threads} threads; a 1024 x 1024 float32 matrix product: "
          f"{peak / 1e9:.1f} G multiply-adds/s")
    summary = []
    with tempfile.TemporaryDirectory() as workdir:
        scenes = [recording((180, 320), args.seconds, Path(workdir)) + ("stub",)]
        if args.camera != "none":
            scenes.append(camera_recording(size_of(args.camera), args.seconds, args.camera_rate, Path(workdir))
                          + ("camera",))
        for path in args.ckpt:
            state = load_checkpoint(path)
            for scene, rec, kind in scenes:
                result = floor_scene(state, rec, scene, args, settings, peak)
                summary.append(f"{args.updates_ms:g} ms updates, {kind}, {result['name']}: real-time factor at most "
                               f"{result['floor']:.2f} (every cell recomputed: {result['full']:.2f}; at the matrix "
                               f"product's throughput: {result['peak']:.2f})")
    print()
    print("\n".join(summary))


if __name__ == "__main__":
    main()
