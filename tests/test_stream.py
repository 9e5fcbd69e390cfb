"""The streaming detector equals the batch model on the same sample, at any moment."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dagr_lite.data.align import background_shift, frame_gradients, max_shift_px, shifted_frame
from dagr_lite.data.collate import collate
from dagr_lite.data.dataset import Sample, event_picture, sample_start_us
from dagr_lite.data.denoise import support_keep_reference
from dagr_lite.data.spec import SampleSpec
from dagr_lite.errors import UserError
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.nn.detector import Detector
from dagr_lite.nn.head import postprocess
from dagr_lite.nn.head import TowerCache, conv3x3_at
from dagr_lite.stream import REORIGIN_US, StreamingDetector
from tests.data.test_event_picture import history_by_loop
from tests.models import small_detector_config
from tests.settings import EVAL

H, W = 48, 64
CONTEXT_US, WINDOW_US = 10_000, 33_333
RECENT_US = 12_000  # a four-channel carry picture's recent window
CONFIRM_US = 15_000  # a carry picture's confirmation (six or seven channels): longer than the context
ALIGN_US = 8_000  # the recent window a moved frame is aligned with (three more channels)
SPANS_US = (15_000, 40_000)  # a carry picture's spans of time since the image, with carry_history
SHIFTS: list[tuple[int, int]] = []  # the moved frames' shifts at the answers checked


def streaming(model: Detector, *, refractory_us: int = 0, score: float = 0.0,
              graph_context_us: int = 0, support_us: int = 0, carry_align_us: int = 0,
              carry_history: bool = False) -> StreamingDetector:
    """The streaming detector on this module's sample, answering every box of ``score`` or more;
    a carry picture's channels say which of its windows it has (less three with ``carry_align_us``,
    less the spans' and the onset's with ``carry_history``: :data:`SPANS_US` and an onset)."""
    picture = model.cfg.carry_channels - (3 if carry_align_us else 0) - (len(SPANS_US) + 2 if carry_history else 0)
    return StreamingDetector(model, SampleSpec(window_us=WINDOW_US, context_us=CONTEXT_US, refractory_us=refractory_us,
                                               max_events=None, event_picture=False,
                                               graph_context_us=graph_context_us,
                                               carry_picture=model.carry is not None,
                                               carry_recent_us=RECENT_US if picture in (4, 7) else 0,
                                               carry_confirm_us=CONFIRM_US if picture >= 6 else 0,
                                               support_us=support_us, carry_align_us=carry_align_us,
                                               carry_spans_us=SPANS_US if carry_history else (),
                                               carry_onset=carry_history),
                             OperatingPoint(score=score, nms_iou=EVAL["nms_threshold"]))


def small_model(variant: str, seed: int = 0, **changes) -> Detector:
    """A small ``variant`` with weights away from the identity; without a carry branch unless
    ``carry_width`` is given (the tests that give one add its picture to their samples)."""
    torch.manual_seed(seed)
    changes = {"carry_width": 0, **changes}
    cfg = small_detector_config(H, W, variant=variant, image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16,
                                **changes)
    model = Detector(cfg).double()
    for module in model.modules():  # batch-norm statistics away from the identity
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.2, 0.2)
            module.running_var.uniform_(0.5, 2.0)
    if model.head.has_image:  # age gates away from their initial 1
        for gate in model.head.gates:
            torch.nn.init.uniform_(gate.weight, -2.0, 2.0)
            torch.nn.init.uniform_(gate.bias, -1.0, 1.0)
    return model.eval()


def sample_of(image, events, origin_us: float, t_query: float, t_start: int = 0) -> Sample:
    """The batch sample: events ``(x, y, t, p)`` with times counted from ``origin_us``; those before
    ``t_start`` (a graph context) are read by the graph and not pooled."""
    x, y, t, p = events
    ev = torch.from_numpy(np.stack([x, y, t - origin_us, p], axis=1).astype(np.float64)).reshape(-1, 4)
    pixels = (torch.zeros((3, H, W), dtype=torch.uint8) if image is None
              else torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))))
    return Sample(events=ev, image=pixels, boxes=torch.tensor([[10.0, 8.0, 30.0, 26.0]]),
                  labels=torch.zeros(1, dtype=torch.int64), video="v", frame=0, image_frame=0, t_start_us=int(t_start),
                  t_end_us=int(t_query), t_image_us=int(origin_us))


def trained(model: Detector, seed: int = 1) -> Detector:
    """``model`` after a few optimiser steps on random samples (weights away from their initialisation)."""
    rng = np.random.default_rng(seed)
    optimiser = torch.optim.AdamW(model.parameters(), lr=3e-3)
    model.train()
    for _ in range(4):
        stream = random_stream(rng, 800, 60_000)
        image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        batch = collate([sample_of(image, tuple(stream.values()), 20_000, 60_000)])
        batch.events = batch.events.double()
        losses = model(batch)
        optimiser.zero_grad()
        losses["loss"].backward()
        optimiser.step()
    return model.eval()


def random_stream(rng, n: int, duration_us: int, gap_at: float | None = None, gap_us: int = 0) -> dict:
    t = np.sort(rng.integers(0, duration_us, n)).astype(np.int64)
    if gap_at is not None:
        t[int(gap_at * n):] += gap_us
    return {"x": rng.integers(0, W, n), "y": rng.integers(0, H, n), "t": t, "p": rng.integers(0, 2, n)}


def check_against_batch(stream: StreamingDetector, model: Detector, events: dict, upto: int, image, t_image,
                        t_query: float) -> int:
    """Compare one answer with the batch model; returns the number of events the sample held."""
    t = events["t"][:upto]
    hybrid = model.image is not None
    start = sample_start_us(t_query, WINDOW_US, t_image if hybrid else None, CONTEXT_US)
    keep = t >= sample_start_us(t_query, WINDOW_US + stream.graph_context_us, t_image if hybrid else None, CONTEXT_US)
    kept = np.ones(upto, dtype=bool)
    if stream.refractory_us:  # brute force: each event against every earlier one at its pixel
        kept = brute_refractory(events, upto, stream.refractory_us)
    if stream.support_us:  # and against every earlier one at a neighbouring pixel
        kept &= support_keep_reference(events["x"][:upto], events["y"][:upto], t, stream.support_us, W, H)
    keep &= kept
    if model.carry is not None:  # the frame and the picture of every event (kept) since it
        since = kept & (t >= t_image)
        picture = event_picture(*(v[:upto][since] for v in events.values()), t_query, max(t_query - t_image, 1.0), H, W,
                                stream.sample.carry_recent_us)
        pictures = [image, picture]
        if stream.sample.carry_confirm_us:  # and of those since it that a neighbour's kept event confirms
            kept_events = {key: v[:upto][kept] for key, v in events.items()}
            confirmed = support_keep_reference(kept_events["x"], kept_events["y"], kept_events["t"],
                                               stream.sample.carry_confirm_us, W, H) & (kept_events["t"] >= t_image)
            pictures.append(event_picture(*(v[confirmed] for v in kept_events.values()), t_query,
                                          max(t_query - t_image, 1.0), H, W))
        if stream.sample.carry_spans_us:  # and the counts per span since the image and the first events (a loop)
            assert stream.sample.carry_onset
            pictures.append(history_by_loop(events["x"][:upto][since], events["y"][:upto][since], t[since], t_image,
                                            t_query, stream.sample.carry_spans_us, H, W))
        if stream.sample.carry_align_us:  # and, last, the frame moved by the shift the recently fired pixels give
            signs, last = np.zeros((H, W)), np.full((H, W), -np.inf)  # each pixel's latest event since the image
            for i in np.nonzero(since)[0]:
                signs[events["y"][i], events["x"][i]] = 1.0 if events["p"][i] == 1 else -1.0
                last[events["y"][i], events["x"][i]] = max(last[events["y"][i], events["x"][i]], t[i])
            signs[last < t_query - stream.sample.carry_align_us] = 0.0  # where recent
            shift = background_shift(frame_gradients(image), signs, max_shift_px(t_query - t_image))
            pictures.append(shifted_frame(image, *shift))
            SHIFTS.append(shift)
        image = np.concatenate(pictures, axis=2)
    origin = t_image if hybrid else stream.origin_us
    sample = sample_of(image, tuple(v[:upto][keep] for v in events.values()), origin, t_query, math.ceil(start))
    with torch.no_grad():
        raw, shapes = stream.head_outputs(t_query)
        expected_raw, expected_shapes, _ = model.outputs(collate([sample]))  # the answer: with event_answers, both heads
    assert raw.dtype == torch.float64 and shapes == expected_shapes
    torch.testing.assert_close(raw, expected_raw, rtol=0, atol=1e-9)
    answer = stream.detect(t_query)
    expected = postprocess(expected_raw, shapes, model.answer_strides(shapes), conf_threshold=stream.operating.score,
                           nms_threshold=stream.operating.nms_iou, image_size=(H, W))[0]
    assert answer["t_us"] == t_query
    np.testing.assert_allclose(answer["boxes"], expected["boxes"].numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(answer["scores"], expected["scores"].numpy(), rtol=0, atol=1e-9)
    return int((keep & (t >= start)).sum())


def brute_refractory(events: dict, upto: int, refractory_us: int) -> np.ndarray:
    keep = np.ones(upto, dtype=bool)
    for i in range(upto):
        same = (events["x"][:i] == events["x"][i]) & (events["y"][:i] == events["y"][i])
        keep[i] = not np.any(same & (events["t"][:i] > events["t"][i] - refractory_us))
    return keep


def replay(model: Detector, events: dict, images: list, seed: int, *, detect_prob: float = 0.4,
           sizes=(0, 1, 1, 2, 5, 40, 300), refractory_us: int = 0,
           graph_context_us: int = 0, support_us: int = 0, carry_align_us: int = 0, carry_history: bool = False
           ) -> tuple[int, int, StreamingDetector]:
    """Push ``events`` in random sizes (0, 1 and more), images at their times, and check random
    detect calls (at the latest event or a little later) against the batch model."""
    rng = np.random.default_rng(seed)
    stream = streaming(model, refractory_us=refractory_us, graph_context_us=graph_context_us, support_us=support_us,
                       carry_align_us=carry_align_us, carry_history=carry_history)
    n, i, checks, largest = len(events["t"]), 0, 0, 0
    pending = sorted(images, key=lambda item: item[1])
    image, t_image = None, None
    while i < n:
        size = min(int(rng.choice(sizes)), n - i)
        batch = {key: values[i:i + size] for key, values in events.items()}
        # An image may come before events older than it (a camera's latency): up to 5 ms early.
        while size and pending and pending[0][1] <= batch["t"][-1] + 5_000:
            image, t_image = pending.pop(0)
            stream.push_image(image, t_image)
        stream.push_events(**batch)
        i += size
        ready = model.image is None or image is not None
        if i and ready and rng.random() < detect_prob:
            t_query = float(events["t"][i - 1]) + float(rng.choice([0, 0, 7, 2_500]))
            t_query = max(t_query, t_image if t_image is not None else -np.inf)
            largest = max(largest, check_against_batch(stream, model, events, i, image, t_image, t_query))
            checks += 1
    return checks, largest, stream


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
@pytest.mark.parametrize("weights", ["untrained", "trained"])
@pytest.mark.parametrize("late_query", [False, True])
@pytest.mark.parametrize("event_dense", [4, 0])
def test_streaming_equals_the_batch_model_at_any_moment(variant, weights, late_query, event_dense):
    """The query maps joined in the fusion (the head run whole) or after the towers (the towers
    updated at changed cells, run whole where events changed most of a map); the pooled stages
    dense (the default) or GCN blocks over the pooled graphs."""
    model = small_model(variant, late_query=late_query, event_dense=event_dense)
    if weights == "trained":
        model = trained(model)
    rng = np.random.default_rng(5)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 96_000, 190_000)]
    checks, largest, _ = replay(model, events, images, seed=7)
    assert checks >= 20 and largest >= 300  # many answers, some over large samples


@pytest.mark.parametrize("carry_width", [0, 4])
def test_streaming_with_the_event_heads_answers_equals_the_batch_model(carry_width):
    """``event_answers``: the event head's anchors join every answer, in the stream as in the batch model."""
    model = small_model("hybrid", seed=9, event_head_weight=1.0, event_answers=True, carry_width=carry_width)
    if not carry_width:  # (the random training samples hold no carry picture)
        model = trained(model)
    rng = np.random.default_rng(23)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, stream = replay(model, events, images, seed=11, detect_prob=0.6)
    raw, shapes = stream.head_outputs(stream.last_event_us)
    fused = sum(h * w for h, w in shapes[:len(model.strides)])  # the fused head's anchors, then the event head's
    assert len(shapes) == 2 * len(model.strides) and raw.shape[1] == 2 * fused
    assert checks >= 10 and largest >= 300


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
def test_streaming_with_neighbourhood_geometry_equals_the_batch_model(variant):
    """Nodes that carry their causal neighbourhood's shape: computed for new nodes only, and at the
    horizon's start from the window's own graph, as the batch model does."""
    model = trained(small_model(variant, seed=4, geometry=True))
    rng = np.random.default_rng(13)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, _ = replay(model, events, images, seed=8)
    assert checks >= 20 and largest >= 300


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
def test_streaming_with_directional_messages_equals_the_batch_model(variant):
    """A first stage whose messages are weighted by the neighbour's offset (``directional``):
    computed for new nodes only, from their edges and the cached positions, as the batch model does."""
    model = trained(small_model(variant, seed=5, geometry=True, directional=True, event_blocks=2))
    rng = np.random.default_rng(19)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, _ = replay(model, events, images, seed=10)
    assert checks >= 20 and largest >= 300


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
@pytest.mark.parametrize("geometry", [False, True])
def test_with_a_graph_context_the_horizons_nodes_are_never_recomputed_and_answers_stay_exact(variant, geometry,
                                                                                              monkeypatch):
    """``graph_context_us``: the sample's first stage also reads that long before the horizon, so
    an answer after events left the horizon pools cached nodes: no node is recomputed (the event
    branch's first stage runs on new nodes only), and the answer equals the batch model's."""
    model = trained(small_model(variant, seed=6, geometry=geometry))
    reach = streaming(model).reach_us
    rng = np.random.default_rng(17)
    events = random_stream(rng, 3000, 300_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 150_000)]
    checks, largest, stream = replay(model, events, images, seed=9, graph_context_us=math.ceil(reach),
                                     detect_prob=0.6)
    assert checks >= 20 and largest >= 300
    real, stream_calls = model.events.event_nodes, []
    monkeypatch.setattr(model.events, "event_nodes",
                        lambda *args, **kwargs: stream_calls.append(1) or real(*args, **kwargs))
    stream.push_events(**{key: values[-1:] + (0 if key != "t" else 1) for key, values in events.items()})
    for t_query in (events["t"][-1] + 1, events["t"][-1] + 20_000):
        stream.head_outputs(float(t_query))
    assert not stream_calls  # the horizon's first nodes were not recomputed
    with pytest.raises(ValueError, match="graph_context_us=100 is shorter than the .* us a node's features reach"):
        streaming(model, graph_context_us=100)


@pytest.mark.parametrize("geometry", [False, True])
def test_a_graph_context_of_the_reach_makes_the_batch_model_blind_to_earlier_events(geometry):
    """With ``graph_context_us`` at least the reach, the events before the context change nothing
    (the horizon's nodes see their whole causal past); without a context they do."""
    model = trained(small_model("events_only", seed=3, geometry=geometry))
    reach = math.ceil(streaming(model).reach_us)
    rng = np.random.default_rng(21)
    events = random_stream(rng, 2500, 150_000)
    t_query, start = 150_000.0, 150_000 - WINDOW_US

    def raw(context_us: int) -> torch.Tensor:
        keep = events["t"] >= start - context_us
        sample = sample_of(None, tuple(v[keep] for v in events.values()), 0, t_query, start)
        with torch.no_grad():
            return model.head(*model.features(collate([sample])))[0]

    torch.testing.assert_close(raw(reach), raw(3 * reach), rtol=0, atol=1e-12)
    assert not torch.allclose(raw(0), raw(reach), rtol=0, atol=1e-6)


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
@pytest.mark.parametrize("weights", ["untrained", "trained"])
def test_towers_recomputed_at_changed_cells_only_equal_the_batch_model(variant, weights, monkeypatch):
    """Events in a corner of a larger frame, the towers never run whole after an image: each
    answer recomputes the cells the new event maps can reach, and still equals the batch model."""
    monkeypatch.setattr(TowerCache, "FULL_FRACTION", math.inf)
    partial = []
    original = TowerCache._partial
    monkeypatch.setattr(TowerCache, "_partial", lambda self, *a: partial.append(1) or original(self, *a))
    model = small_model(variant, seed=6, late_query=True)
    if weights == "trained":
        model = trained(model)
    rng = np.random.default_rng(8)
    events = random_stream(rng, 2000, 200_000)
    events["x"], events["y"] = events["x"] // 3, events["y"] // 3  # a 21 x 16 pixel corner of the 64 x 48 frame
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 120_000)]
    checks, largest, _ = replay(model, events, images, seed=9, detect_prob=0.5, sizes=(0, 1, 2, 5, 40))
    assert checks >= 20 and largest >= 300 and len(partial) >= 20


def test_conv3x3_at_cells_equals_the_convolution():
    """A 3x3 layer at chosen cells of a padded channels-last map, against the whole convolution
    (zero padding at the borders)."""
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(5, 7, 3, padding=1, bias=False).double()
    x = torch.randn(1, 5, 6, 9, dtype=torch.float64)
    rows, cols = torch.tensor([0, 0, 5, 3, 5]), torch.tensor([0, 8, 8, 4, 0])  # corners, borders, inside
    padded = torch.nn.functional.pad(x, (1, 1, 1, 1))[0].permute(1, 2, 0).reshape(-1, 5)  # (8 * 11, 5)
    weight = conv.weight.permute(0, 2, 3, 1).reshape(7, -1)
    with torch.no_grad():
        got = conv3x3_at(padded, 9, weight, (rows + 1) * 11 + cols + 1)
        want = conv(x)[0][:, rows, cols].T
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_streaming_equals_the_batch_model_with_head_strides_from_16():
    """A hybrid that reads strides 16 and 32 only (its image branch still passes stride 8)."""
    torch.manual_seed(4)
    cfg = small_detector_config(H, W, variant="hybrid", image_width=8, event_channels=(8, 8, 8), head_hidden=16,
                                strides=(16, 32), carry_width=0)
    model = trained(Detector(cfg).double())
    rng = np.random.default_rng(6)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, _ = replay(model, events, images, seed=8)
    assert checks >= 20 and largest >= 300


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
@pytest.mark.parametrize("late_query", [False, True])
def test_streaming_stays_exact_across_long_gaps(variant, late_query):
    """Gaps longer than the window (everything leaves it) and than the float32 re-origin span."""
    model = small_model(variant, seed=3, late_query=late_query)
    rng = np.random.default_rng(11)
    events = random_stream(rng, 1500, 120_000, gap_at=0.3, gap_us=150_000)
    events["t"][int(0.7 * 1500):] += REORIGIN_US + 500_000
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (10_000, 200_000,
                                                                             REORIGIN_US + 600_000)]
    checks, _, stream = replay(model, events, images, seed=2, detect_prob=0.8, sizes=(0, 1, 2, 5, 40))
    assert checks >= 20 and stream.origin_us > REORIGIN_US  # the events-only origin moved forward


@pytest.mark.parametrize("late_query", [False, True])
def test_the_hybrid_stays_exact_while_its_events_leave_the_horizon(late_query):
    """One image for a long stretch: events leave the horizon, the forgotten rows are dropped and
    the horizon's own pooled graph serves instead of the cells kept since the image."""
    model = trained(small_model("hybrid", seed=2, late_query=late_query))
    rng = np.random.default_rng(12)
    events = random_stream(rng, 8000, 400_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), 20_000)]
    checks, largest, stream = replay(model, events, images, seed=3, detect_prob=0.3, sizes=(1, 5, 40, 300))
    assert checks >= 20 and largest >= 500
    assert stream._segment.base > 0 and stream._segment.cells is None  # rows were forgotten


@pytest.mark.parametrize("geometry", [False, True])
def test_a_dense_context_that_leaves_before_the_next_events_arrive(geometry):
    """A fresh image's dense context is ingested, then forgotten in one step when the horizon passes
    it; the next events arrive with edges to rows that are gone (a camera of millions of events per
    second: more forgotten rows than new ones). The answers stay the batch model's."""
    model = trained(small_model("hybrid", seed=6, geometry=geometry))
    rng = np.random.default_rng(21)
    t_image = 50_000
    before = random_stream(rng, 3000, CONTEXT_US)  # 3,000 events in the image's 10 ms context
    before["t"] += t_image - CONTEXT_US
    after = random_stream(rng, 300, 45_000)
    after["t"] += t_image
    events = {key: np.concatenate([before[key], after[key]]) for key in before}
    image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    stream = streaming(model)
    stream.push_events(**before)
    stream.push_image(image, t_image)
    assert check_against_batch(stream, model, events, 3000, image, t_image, t_image) == 3000
    stream.push_events(**after)
    base = stream._segment.base
    check_against_batch(stream, model, events, len(events["t"]), image, t_image, t_image + 45_000)
    assert stream._segment.base >= base + 3000  # the context's rows were forgotten


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
def test_streaming_with_a_refractory_period_equals_the_batch_model_on_the_filtered_sample(variant):
    """Hot pixels and bursts: few pixels, several events per pixel and microsecond."""
    model = small_model(variant, seed=5)
    rng = np.random.default_rng(21)
    n = 1500
    events = {"x": rng.integers(20, 26, n), "y": rng.integers(10, 14, n),
              "t": np.sort(rng.integers(0, 120_000, n) // 50 * 50), "p": rng.integers(0, 2, n)}
    assert len(np.unique(events["t"])) < n  # ties in time
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (10_000, 70_000)]
    checks, largest, stream = replay(model, events, images, seed=4, detect_prob=0.6, sizes=(1, 3, 20, 100),
                                     refractory_us=400)
    assert checks >= 10 and 0 < largest < len(events["t"])


@pytest.mark.parametrize("variant", ["hybrid", "events_only", "carry"])
def test_streaming_with_the_background_activity_filter_equals_the_batch_model_on_the_filtered_sample(variant):
    """Both arrival filters, decided chunk by chunk as events come; the carry picture reads the kept events."""
    model = small_model("hybrid", seed=6, carry_width=4) if variant == "carry" else small_model(variant, seed=6)
    rng = np.random.default_rng(22)
    n = 1500
    events = {"x": rng.integers(20, 30, n), "y": rng.integers(10, 16, n),
              "t": np.sort(rng.integers(0, 120_000, n) // 40 * 40), "p": rng.integers(0, 2, n)}
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (10_000, 70_000)]
    checks, largest, stream = replay(model, events, images, seed=5, detect_prob=0.6, sizes=(1, 3, 20, 100),
                                     refractory_us=200, support_us=600)
    kept = support_keep_reference(events["x"], events["y"], events["t"], 600, W, H)
    assert 0.2 < kept.mean() < 0.9  # the filter drops some events and keeps others
    assert checks >= 10 and 0 < largest < len(events["t"])


def test_events_only_window_empties_and_refills():
    model = small_model("events_only")
    stream = streaming(model)
    empty = stream.detect(5_000.0)  # nothing pushed yet
    assert empty["boxes"].shape[1] == 4
    rng = np.random.default_rng(0)
    events = random_stream(rng, 400, 20_000)
    stream.push_events(**events)
    stream.push_image(np.zeros((H, W, 3), np.uint8), 0)  # an events-only model ignores images, even old ones
    check_against_batch(stream, model, events, 400, None, None, 20_000.0)
    check_against_batch(stream, model, events, 400, None, None, 20_000.0 + WINDOW_US + 1)  # all left the window


def test_bad_input_is_refused_and_leaves_the_state_valid():
    model = small_model("hybrid")
    stream = streaming(model)
    rng = np.random.default_rng(1)
    events = random_stream(rng, 600, 40_000)
    image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    stream.push_events(**{k: v[:10] for k, v in events.items()})
    with pytest.raises(ValueError, match="needs an image"):
        stream.detect()
    stream.push_image(image, 5_000)
    stream.push_events(**{k: v[10:300] for k, v in events.items()})
    before = stream.detect(events["t"][299] + 1.0)
    bad = [
        ({"x": [1, 2], "y": [1, 1], "t": [50_000, 49_000], "p": [0, 1]}, "sorted by t"),
        ({"x": [1], "y": [1], "t": [events["t"][299] - 1], "p": [0]}, "older than"),
        ({"x": [W], "y": [1], "t": [60_000], "p": [0]}, r"x must lie in \[0, 64\)"),
        ({"x": [1], "y": [-1], "t": [60_000], "p": [0]}, r"y must lie in \[0, 48\)"),
        ({"x": [1], "y": [1], "t": [60_000], "p": [2]}, "p must be 0 or 1"),
        ({"x": [1, 2], "y": [1], "t": [60_000], "p": [0]}, "same length"),
    ]
    for arrays, message in bad:
        with pytest.raises(ValueError, match=message):
            stream.push_events(**arrays)
    with pytest.raises(ValueError, match=r"image must be \(48, 64, 3\) uint8"):
        stream.push_image(np.zeros((H, W + 1, 3), np.uint8), 40_000)
    with pytest.raises(ValueError, match="older than the previous image"):
        stream.push_image(image, 4_000)
    with pytest.raises(ValueError, match="earlier than the latest event"):
        stream.detect(float(events["t"][299] - 5))
    for when in (math.nan, math.inf, -math.inf):  # never "no hands" at a time that is not one
        with pytest.raises(ValueError, match="detect time must be finite"):
            stream.detect(when)
    after = stream.detect(events["t"][299] + 1.0)  # nothing above changed the state
    np.testing.assert_array_equal(before["boxes"], after["boxes"])
    stream.push_events(**{k: v[300:] for k, v in events.items()})
    check_against_batch(stream, model, events, 600, image, 5_000, float(events["t"][-1]))
    with pytest.raises(ValueError, match="event branch"):
        streaming(Detector(small_detector_config(H, W, variant="image_only")), score=EVAL["conf_threshold"])
    events_only = streaming(small_model("events_only"))
    events_only.push_events(**{k: v[:10] for k, v in events.items()})
    for when in (math.nan, math.inf):
        with pytest.raises(ValueError, match="detect time must be finite"):
            events_only.detect(when)


@pytest.fixture
def hybrid_checkpoint(trained_checkpoints) -> Path:
    """A hybrid trained for a few steps on the stub by the training loop."""
    return trained_checkpoints["hybrid"]


@pytest.mark.parametrize(("name", "full_fraction"), [("hybrid", TowerCache.FULL_FRACTION),
                                                     ("hybrid_late", TowerCache.FULL_FRACTION),
                                                     ("hybrid_late", math.inf)])
def test_from_checkpoint_matches_the_batch_model_in_float32(trained_checkpoints, name, full_fraction, monkeypatch):
    """A trained checkpoint, float32: equal to the batch model to 1e-5 (relative); with
    ``late_query``, the towers run whole where events changed most of a map, or always at the
    changed cells only; the default hybrid's carry branch reads the picture of the events since the image."""
    monkeypatch.setattr(TowerCache, "FULL_FRACTION", full_fraction)
    stream = StreamingDetector.from_checkpoint(trained_checkpoints[name], score=0.0, nms_iou=EVAL["nms_threshold"])
    assert stream.model.cfg.late_query == name.endswith("_late")
    assert (stream.model.carry is not None) == (name == "hybrid")
    model = stream.model
    assert stream.context_us == 10_000 and next(model.parameters()).dtype == torch.float32
    height, width = model.cfg.height, model.cfg.width
    rng = np.random.default_rng(4)
    n = 4000
    events = {"x": rng.integers(0, width, n), "y": rng.integers(0, height, n),
              "t": np.sort(rng.integers(0, 60_000, n)), "p": rng.integers(0, 2, n)}
    image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    stream.push_image(image, 20_000)
    for part in np.array_split(np.arange(n), 9):
        stream.push_events(**{k: v[part] for k, v in events.items()})
        t_query = float(events["t"][part[-1]])
        keep = (events["t"] >= sample_start_us(t_query, stream.window_us, 20_000, 10_000)) & (np.arange(n) <= part[-1])
        x, y, t, p = (v[keep] for v in events.values())
        pixels = image
        if model.carry is not None:
            since = (events["t"] >= 20_000) & (np.arange(n) <= part[-1])
            pixels = np.concatenate([image, event_picture(*(v[since] for v in events.values()), t_query,
                                                          max(t_query - 20_000, 1.0), height, width,
                                                          stream.sample.carry_recent_us)], axis=2)
        sample = Sample(events=torch.from_numpy(np.stack([x, y, t - 20_000, p], 1).astype(np.float32)),
                        image=torch.from_numpy(np.ascontiguousarray(pixels.transpose(2, 0, 1))),
                        boxes=torch.zeros((0, 4)), labels=torch.zeros(0, dtype=torch.int64), video="v", frame=0,
                        image_frame=0, t_start_us=0, t_end_us=int(t_query), t_image_us=20_000)
        with torch.no_grad():
            raw, _ = stream.head_outputs(t_query)
            expected, _ = model.head(*model.features(collate([sample])))
        torch.testing.assert_close(raw, expected, rtol=1e-5, atol=1e-5)


def test_demo_writes_a_playable_animation_and_a_strip(hybrid_checkpoint, tmp_path, monkeypatch):
    from PIL import Image

    from dagr_lite.config import ConfigError
    from dagr_lite.apps.demo import demo
    from tests.engine.test_train import config

    out = tmp_path / "demo.webp"
    cfg = config("demo", f"ckpt={hybrid_checkpoint}", f"out={out}", "rate_hz=100", "seconds=0.2", "strip_frame=2",
                 "strip_moments=3", "device=cpu")
    result = demo(cfg)
    with Image.open(out) as animation:
        assert animation.n_frames == len(result["latencies"]) - 3  # 20 updates of 10 ms, the strip's 3 apart
        assert animation.size == (2 * 320, 180 + 14)
    with Image.open(result["strip"]) as strip:
        assert strip.size == (2 * 320, 3 * (180 + 14))
    with pytest.raises(ConfigError, match="already exists"):
        demo(cfg)  # nothing is overwritten
    with pytest.raises(ConfigError, match="not in"):
        demo(config("demo", f"ckpt={hybrid_checkpoint}", f"out={tmp_path / 'b.gif'}", "video=nope"))
    for seconds in (0, -1):
        with pytest.raises(ConfigError, match=rf"seconds must be a positive number of seconds .*got {seconds}"):
            demo(config("demo", f"ckpt={hybrid_checkpoint}", f"out={tmp_path / 'c.gif'}", f"seconds={seconds}"))
    assert not (tmp_path / "c.gif").exists()
    with pytest.raises(FileNotFoundError, match="checkpoint file is missing"):  # named before any output
        demo(config("demo", f"ckpt={tmp_path / 'nope.pt'}", f"out={out}"))
    monkeypatch.chdir(tmp_path)  # no out=: each demo in a folder of its own under runs/demo/
    short = ("rate_hz=50", "seconds=0.1", "strip_frame=1", "strip_moments=2", "device=cpu")
    first, second = (demo(config("demo", f"ckpt={hybrid_checkpoint}", *short))["out"] for _ in range(2))
    assert first != second and first.is_file() and second.is_file() and first.parts[:2] == ("runs", "demo")


@pytest.mark.parametrize(("refractory_us", "carry_channels", "carry_frame", "carry_attend"),
                         [(0, 3, False, 0), (3_000, 3, False, 0), (0, 4, True, 0), (0, 4, True, 1), (0, 6, False, 0),
                          (3_000, 7, True, 0)])
def test_streaming_with_a_carry_branch_equals_the_batch_model(refractory_us, carry_channels, carry_frame,
                                                              carry_attend):
    """The picture of every event since the image (those the refractory period keeps), kept as
    per-pixel counts and latest times from the image on and read at each answer by the carry
    branch (with four channels also the recency over the last ``RECENT_US``, with six or seven
    also the picture of the events a neighbour confirms within ``CONFIRM_US``, with ``carry_frame``
    beside the frame), gives the batch model's answer; events up to 5 ms older than an image may
    come after it."""
    model = small_model("hybrid", seed=7, carry_width=4, carry_channels=carry_channels, carry_frame=carry_frame,
                        carry_attend=carry_attend)
    rng = np.random.default_rng(23)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, stream = replay(model, events, images, seed=11, refractory_us=refractory_us, detect_prob=0.5)
    assert checks >= 20 and largest >= 300
    assert stream._carry is not None and stream._carry.counts.sum() > 0
    if carry_channels >= 6:  # some events are confirmed, not all
        assert 0 < stream._carry.confirmed[0].sum() < 0.9 * stream._carry.counts.sum()


@pytest.mark.parametrize(("carry_channels", "refractory_us"), [(7, 0), (10, 3_000)])
def test_streaming_with_a_moved_frame_equals_the_batch_model(carry_channels, refractory_us):
    """A carry picture with the frame moved by the camera's motion (``carry_align_us``): its shift,
    found at each answer from the pixels the kept events fired in the last ``ALIGN_US``, and so
    the answer, are the batch model's; the shift moves as events arrive."""
    model = small_model("hybrid", seed=9, carry_width=4, carry_channels=carry_channels, carry_frame=True)
    rng = np.random.default_rng(29)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    SHIFTS.clear()
    checks, largest, stream = replay(model, events, images, seed=13, refractory_us=refractory_us, detect_prob=0.9,
                                     carry_align_us=ALIGN_US)
    assert checks >= 20 and largest >= 300
    assert len(SHIFTS) == checks and len(set(SHIFTS)) > 1  # the moved frame's shift moves from answer to answer


def test_a_confirmation_longer_than_the_context_serves_close_and_late_images():
    """The log keeps ``CONFIRM_US`` before each image, so a second image 4 ms after the first and an
    image pushed 30 ms after newer events both read the events that confirm their first ones."""
    model = small_model("hybrid", seed=8, carry_width=4, carry_channels=6)
    rng = np.random.default_rng(31)
    events = random_stream(rng, 2000, 200_000)
    t = events["t"]
    stream = streaming(model)
    images = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(3)]
    pushed = 0
    checks = 0
    for t_push, image, t_image, queries in ((30_000, images[0], 30_000, ()), (33_000, images[1], 34_000, (41_000,)),
                                            (100_000, images[2], 70_000, (100_000, 104_000))):
        upto = int(np.searchsorted(t, t_push, side="left"))
        stream.push_events(*(events[key][pushed:upto] for key in ("x", "y", "t", "p")))
        pushed = upto
        stream.push_image(image, t_image)
        for t_query in queries:
            upto = int(np.searchsorted(t, t_query, side="left"))
            stream.push_events(*(events[key][pushed:upto] for key in ("x", "y", "t", "p")))
            pushed = upto
            check_against_batch(stream, model, events, upto, image, t_image, t_query)
            checks += 1
    assert checks == 3 and stream._carry.confirmed[0].sum() > 0


def test_a_model_reading_a_picture_of_events_is_refused_by_its_key():
    model = small_model("hybrid")
    for key in ("event_picture", "carry_picture"):
        spec = SampleSpec(window_us=WINDOW_US, context_us=CONTEXT_US, refractory_us=0, support_us=0, max_events=None,
                          graph_context_us=0, carry_recent_us=0, carry_confirm_us=0, carry_align_us=0,
                          carry_spans_us=(), carry_onset=False, **{"event_picture": False, "carry_picture": False, key: True})
        with pytest.raises(UserError, match=f"data.{key}"):
            StreamingDetector(model, spec, OperatingPoint(score=0.0, nms_iou=EVAL["nms_threshold"]))


@pytest.mark.parametrize(("carry_channels", "refractory_us", "carry_frame"), [(3 + 4, 0, True), (4 + 3 + 4, 3_000, False)])
def test_streaming_with_the_carry_spans_and_onset_equals_the_batch_model(carry_channels, refractory_us, carry_frame):
    """A carry picture with counts per span of time since the image and each pixel's first event
    (``carry_spans_us``, ``carry_onset``; the second case beside the recent and confirmed
    channels): kept per pixel as events arrive, read at each answer, the batch model's answer,
    its channels by a plain loop over the events."""
    model = small_model("hybrid", seed=5, carry_width=4, carry_channels=carry_channels, carry_frame=carry_frame)
    rng = np.random.default_rng(31)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, stream = replay(model, events, images, seed=17, refractory_us=refractory_us, detect_prob=0.6,
                                     carry_history=True)
    assert checks >= 20 and largest >= 300
    carry = stream._carry
    assert carry.spans.shape[0] == 3 and carry.spans[2].sum() > 0 and np.isfinite(carry.first).sum() > 100


def test_a_carry_branch_is_refused_a_picture_of_other_channels():
    """A four-channel carry branch on a sample of three-channel pictures (no recent window)."""
    model = small_model("hybrid", carry_width=4, carry_channels=4)
    spec = SampleSpec(window_us=WINDOW_US, context_us=CONTEXT_US, refractory_us=0, support_us=0, max_events=None,
                      graph_context_us=0, event_picture=False, carry_picture=True, carry_recent_us=0,
                      carry_confirm_us=0, carry_align_us=0, carry_spans_us=(), carry_onset=False)
    with pytest.raises(UserError, match=r"reads pictures of 4 channels, but data.carry_recent_us=0, "
                                        r"data.carry_confirm_us=0, data.carry_align_us=0, data.carry_spans_us=\[\] "
                                        "and data.carry_onset=False make pictures of 3"):
        StreamingDetector(model, spec, OperatingPoint(score=0.0, nms_iou=EVAL["nms_threshold"]))
    with pytest.raises(UserError, match=r"data.carry_spans_us=\[50000\] and data.carry_onset=False make pictures "
                                        "of 5"):  # spans of time since the image: one channel each
        StreamingDetector(model, replace(spec, carry_spans_us=(50_000,)),
                          OperatingPoint(score=0.0, nms_iou=EVAL["nms_threshold"]))


@pytest.mark.parametrize("variant", ["hybrid", "events_only"])
def test_streaming_with_dense_pooled_stages_from_the_first_stride_equals_the_batch_model(variant):
    """``event_dense`` at the first stride (8; the default 4 runs in every other test): the cells
    kept up to date are written out as a map and convolved, as the batch model pools and convolves
    its sample's nodes."""
    cell = 8
    model = trained(small_model(variant, seed=8, geometry=True, event_dense=cell))
    assert model.events.pool_stride == cell
    rng = np.random.default_rng(29)
    events = random_stream(rng, 2500, 250_000)
    images = [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), t) for t in (30_000, 95_000, 190_000)]
    checks, largest, _ = replay(model, events, images, seed=12, detect_prob=0.7)
    assert checks >= 20 and largest >= 300


@pytest.mark.parametrize("variant, carry_width", [("hybrid", 8), ("events_only", 0)])
def test_a_warm_up_leaves_the_detector_as_new(variant, carry_width):
    """After :meth:`warm_up` the detector answers a stream as a fresh one does, to the bit."""
    model = small_model(variant, carry_width=carry_width)
    rng = np.random.default_rng(3)
    events = random_stream(rng, 600, 40_000)
    image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    answers = []
    for warm in (False, True):
        stream = streaming(model)
        if warm:
            assert stream.warm_up() > 0
            assert stream._segment is None and stream.last_event_us == -math.inf
        if stream.hybrid:
            stream.push_image(image, 0)
        stream.push_events(**{key: value[:300] for key, value in events.items()})
        first = stream.head_outputs(float(events["t"][299]))[0]
        stream.push_events(**{key: value[300:] for key, value in events.items()})
        answers.append((first, stream.head_outputs(45_000.0)[0]))
    for fresh, warmed in zip(*answers):
        assert torch.equal(fresh, warmed)
