import pytest
import torch

from dagr_lite.data.collate import collate
from dagr_lite.engine.checkpoint import upgraded_detector
from dagr_lite.nn.detector import CarryAttention, Detector, DetectorConfig
from dagr_lite.nn.head import box_iou, postprocess
from dagr_lite.synth.stub import stub_root
from tests.models import small_detector_config
from tests.settings import sample_set
from tests.settings import EVAL


def test_the_hybrid_model_overfits_one_batch():
    torch.manual_seed(0)
    dataset = sample_set(stub_root(), "train", window_us=20_000, carry_picture=True)
    batch = collate([dataset[i] for i in (5, 60, 150, 260)])
    model = Detector(small_detector_config(image_width=8, event_channels=(8, 16, 16, 16), head_hidden=32))
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(100):
        out = model(batch)
        optimizer.zero_grad()
        out["loss"].backward()
        optimizer.step()
        losses.append(float(out["loss"].detach()))
    assert losses[-1] < losses[0] / 4
    model.eval()
    with torch.no_grad():
        detections = model(batch, **EVAL)
    found = []
    for det, boxes in zip(detections, batch.boxes):
        confident = det["boxes"][det["scores"] > 0.3]
        assert len(boxes) and len(confident)
        found += (box_iou(boxes, confident).max(dim=1).values > 0.5).tolist()
    assert sum(found) / len(found) >= 0.75  # most true boxes come out right


def test_training_output_names_and_variants():
    dataset = sample_set(stub_root(), "valid", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (0, 40)])
    for use_events, use_image in ((True, True), (True, False), (False, True)):
        model = Detector(small_detector_config(use_events=use_events, use_image=use_image, image_width=8,
                                               event_channels=(8, 8, 8, 8), head_hidden=16,
                                               carry_width=8 if use_events and use_image else 0))
        out = model(batch)
        assert set(out) == {"loss", "iou_loss", "obj_loss", "cls_loss", "num_fg"} and torch.isfinite(out["loss"])
        model.eval()
        assert len(model(batch, **EVAL)) == 2


def test_the_event_head_adds_its_weighted_loss_in_training_and_leaves_detection_alone():
    dataset = sample_set(stub_root(), "valid", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (0, 40)])
    torch.manual_seed(0)
    sizes = dict(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16)
    with_head = Detector(small_detector_config(**sizes, event_head_weight=0.5))
    without = Detector(small_detector_config(**sizes, event_head_weight=0.0))
    assert without.event_head is None and with_head.event_head is not None
    own = {k: v for k, v in with_head.state_dict().items() if not k.startswith("event_head.")}
    without.load_state_dict(own)  # strict: the event head is the only difference
    out, reference = with_head(batch), without(batch)
    assert set(out) == set(reference) | {"event_head_loss"}
    assert float(out["event_head_loss"]) > 0
    torch.testing.assert_close(out["loss"], reference["loss"] + 0.5 * out["event_head_loss"])
    out["loss"].backward()
    assert all(p.grad is not None for p in with_head.event_head.parameters())
    assert all(stem[0].weight.grad.abs().sum() > 0 for stem in with_head.event_head.stems)  # it trains
    with_head.eval(), without.eval()
    with torch.no_grad():
        for a, b in zip(with_head(batch, **EVAL), without(batch, **EVAL)):  # detection reads the fused head only
            for key in ("boxes", "scores", "labels"):
                torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    for variant in ("events_only", "image_only"):  # only a hybrid has a second head to train
        assert Detector(small_detector_config(variant=variant, **sizes, event_head_weight=1.0)).event_head is None


def test_event_answers_add_the_event_heads_boxes_to_the_fused_heads_before_one_nms():
    """With ``event_answers`` an answer holds the boxes each head decodes on its own, suppressed
    together; training and its losses are the event head's model's, unchanged."""
    dataset = sample_set(stub_root(), "valid", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (0, 40, 80)])
    torch.manual_seed(0)
    sizes = dict(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16, event_head_weight=0.5)
    answering = Detector(small_detector_config(**sizes, event_answers=True))
    training_only = Detector(small_detector_config(**sizes))
    training_only.load_state_dict(answering.state_dict())
    torch.testing.assert_close(answering(batch)["loss"], training_only(batch)["loss"], rtol=0, atol=0)
    answering.eval(), training_only.eval()
    iou = 0.5

    def scores(raw, shift=0.0):
        return (torch.sigmoid(raw[..., 4] + shift) * torch.sigmoid(raw[..., 5])).flatten()
    with torch.no_grad():
        maps, query, image_inputs, event_inputs = answering._features(batch)
        fused_raw, shapes = answering.head(maps, query, image_inputs)
        event_raw, _ = answering.event_head(*event_inputs)
        score = float(scores(fused_raw).sort().values[-30])  # 30 of the fused head's boxes pass
        low, high = -30.0, 30.0  # and about 20 of the event head's, its objectness shifted to make it so
        for _ in range(50):
            low, high = ((low + high) / 2, high) if int((scores(event_raw, (low + high) / 2) >= score).sum()) < 20 \
                else (low, (low + high) / 2)
        for pred in answering.event_head.obj_preds:
            pred.bias += high
        training_only.load_state_dict(answering.state_dict())
        event_raw, _ = answering.event_head(*event_inputs)
        answers = answering(batch, conf_threshold=score, nms_threshold=iou)  # (50 boxes or so: none cut)
        strides = list(answering.strides)
        alone = [postprocess(raw, shapes, strides, conf_threshold=score, nms_threshold=1.0, image_size=(180, 320))
                 for raw in (fused_raw, event_raw)]  # each head's boxes, none suppressed
        fused_only = training_only(batch, conf_threshold=score, nms_threshold=iou)
    from_events = from_fused = 0
    for b, answer in enumerate(answers):
        boxes = torch.cat([alone[0][b]["boxes"], alone[1][b]["boxes"]])
        scores = torch.cat([alone[0][b]["scores"], alone[1][b]["scores"]])
        keep = greedy_nms(boxes, scores, iou)
        torch.testing.assert_close(answer["boxes"], boxes[keep], rtol=0, atol=1e-5)
        torch.testing.assert_close(answer["scores"], scores[keep], rtol=0, atol=0)
        from_events += int((torch.as_tensor(keep) >= len(alone[0][b]["boxes"])).sum())
        from_fused += int((torch.as_tensor(keep) < len(alone[0][b]["boxes"])).sum())
    assert from_events > 0 and from_fused > 0  # answers of both heads
    assert sum(len(a["boxes"]) for a in answers) > sum(len(a["boxes"]) for a in fused_only)
    with pytest.raises(ValueError, match="event_answers needs a hybrid with an event head"):
        small_detector_config(**{**sizes, "event_head_weight": 0.0}, event_answers=True)


def greedy_nms(boxes: torch.Tensor, scores: torch.Tensor, iou: float) -> list[int]:
    """Greedy suppression, one box at a time: the highest remaining score stays, and every box
    overlapping it by more than ``iou`` goes."""
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    kept: list[int] = []
    for i in order:
        if all(float(box_iou(boxes[i:i + 1], boxes[j:j + 1])[0, 0]) <= iou for j in kept):
            kept.append(i)
    return kept


@pytest.mark.parametrize(("late_query", "carry_attend"), [(False, 0), (True, 0), (False, 2)])
def test_with_its_image_weights_zeroed_a_hybrid_answers_what_it_answers_without_an_image(late_query, carry_attend):
    """zero_image_weights: the hybrid's features with any frame (the stub's, or noise) equal, to
    the last bit, those of forward(image=False), which runs no image branch; before zeroing, the
    image changes them (the check can fail). In training the zeroed weights get no gradient."""
    dataset = sample_set(stub_root(), "valid", window_us=10_000, carry_picture=not late_query)
    batch = collate([dataset[i] for i in (0, 40)])
    noise = collate([dataset[i] for i in (0, 40)])
    frame = noise.images[:, :3]  # the camera frame (a picture of events beside it is events)
    frame.copy_(torch.randint(0, 256, frame.shape, dtype=frame.dtype))
    torch.manual_seed(0)
    model = Detector(small_detector_config(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16,
                                           late_query=late_query, carry_width=0 if late_query else 8,
                                           carry_attend=carry_attend)).eval()
    with torch.no_grad():
        blank = model._features(batch, image=False)[0]
        assert any(not torch.equal(a, b) for a, b in zip(model.features(batch)[0], blank))
        model.zero_image_weights()
        blank = model._features(batch, image=False)[0]
        for images in (batch, noise):
            for a, b in zip(model.features(images)[0], blank):
                assert torch.equal(a, b)
        for a, b in zip(model(batch, **EVAL), model(batch, image=False, **EVAL)):
            for key in ("boxes", "scores", "labels"):
                assert torch.equal(a[key], b[key])
    model.train()
    model(batch, image=False)["loss"].backward()
    first = model.events.stages[0][0]
    assert first.conv.weight.grad[-8:].abs().sum() == 0 and first.conv.weight.grad[:-8].abs().sum() > 0
    assert first.skip.weight.grad[:, -8:].abs().sum() == 0
    assert model.fuse[0][0].weight.grad[:, :model.image.channels[1]].abs().sum() == 0
    if late_query:  # the stems of the head's image towers read the image maps
        assert all(stem[0].weight.grad.abs().sum() == 0 for stem in model.head.image_stems)
    assert all(p.grad is None for p in [*model.image.parameters(), *model.to_nodes.parameters()])
    if carry_attend:  # the carry attention's keys and values read the image map; its queries the carry's
        assert model.attend.key.weight.grad.abs().sum() == 0 and model.attend.value.weight.grad.abs().sum() == 0
    for variant in ("events_only", "image_only"):
        with pytest.raises(ValueError, match="only a hybrid"):
            Detector(small_detector_config(variant=variant, image_width=8, event_channels=(8, 8, 8, 8),
                                           head_hidden=16)).zero_image_weights()


def test_a_detector_config_saved_before_the_event_head_loads_without_one():
    saved = small_detector_config(event_head_weight=2.0).as_dict()
    assert DetectorConfig.from_dict(saved).event_head_weight == 2.0
    del saved["event_head_weight"]
    with pytest.raises(ValueError, match="missing keys \\['event_head_weight'\\]"):
        DetectorConfig.from_dict(saved)  # a checkpoint's older config is upgraded where checkpoints are read
    assert DetectorConfig.from_dict(upgraded_detector(saved)).event_head_weight == 0.0
    saved["event_heads"] = 1
    with pytest.raises(ValueError, match="unknown keys \\['event_heads'\\]"):
        DetectorConfig.from_dict(saved)
    with pytest.raises(ValueError, match="event_head_weight must be a number >= 0, got -1"):
        small_detector_config(event_head_weight=-1.0)


def test_a_detector_config_saved_before_the_patch_stem_rebuilds_its_conv_stem():
    saved = small_detector_config().as_dict()
    assert saved["image_stem"] == "patch"  # the default of conf/model/hybrid.yaml
    del saved["image_stem"]
    old = DetectorConfig.from_dict(upgraded_detector(saved))
    assert old.image_stem == "conv"
    assert [type(layer).__name__ for layer in Detector(old).image.stem] == ["Sequential", "Sequential", "Residual"]
    with pytest.raises(ValueError, match="image_stem must be one of"):
        small_detector_config(image_stem="big")


def test_mixed_precision_keeps_losses_and_graph_products_in_float32(monkeypatch):
    import dagr_lite.nn.head as head_module
    real_bce = head_module.F.binary_cross_entropy

    def guarded_bce(*args, **kwargs):  # CUDA autocast refuses BCE: it must run with autocast off
        assert not torch.is_autocast_enabled("cpu")
        return real_bce(*args, **kwargs)

    monkeypatch.setattr(head_module.F, "binary_cross_entropy", guarded_bce)
    dataset = sample_set(stub_root(), "valid", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (3, 50)])
    model = Detector(small_detector_config(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(batch)
    assert out["loss"].dtype == torch.float32 and torch.isfinite(out["loss"])
    out["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def in_float64(sample):
    batch = collate([sample])
    batch.events = batch.events.double()
    return batch


def test_node_features_ignore_later_events_and_the_query_time():
    """The rule streaming depends on: a node depends on its event, its causal past and the image."""
    torch.manual_seed(0)
    dataset = sample_set(stub_root(), "valid", image_age=3, max_events=None, carry_picture=True)
    sample = dataset[20]
    model = Detector(small_detector_config(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16)).double().eval()
    n = len(sample.events)
    early = sample.replace(events=sample.events[: n // 2], t_end_us=sample.t_image_us + 40_000)
    later = sample.replace(t_end_us=sample.t_end_us + 50_000)  # more events, asked for later
    with torch.no_grad():
        a = model.event_node_features(in_float64(early))
        b = model.event_node_features(in_float64(later))
        c = model.event_node_features(in_float64(sample.replace(t_end_us=sample.t_end_us + 1)))
    assert a.shape[0] == n // 2 and b.shape[0] == n
    assert torch.equal(a, b[: n // 2]) and torch.equal(b, c)
    # ...while the detections do follow the query time, through the image's age at the fusion
    with torch.no_grad():
        now = model(in_float64(sample), conf_threshold=0.0, nms_threshold=EVAL["nms_threshold"])[0]["scores"]
        later_scores = model(in_float64(later), conf_threshold=0.0, nms_threshold=EVAL["nms_threshold"])[0]["scores"]
    assert not torch.equal(now, later_scores)


def attention_by_loops(query: torch.Tensor, image: torch.Tensor, attend: CarryAttention) -> torch.Tensor:
    """:class:`CarryAttention` cell by cell: each cell's dot products with the image cells within
    ``radius`` each way (inside the map), a softmax with the nothing slot's logit 0, the weighted sum."""
    q, k, v = attend.query(query), attend.key(image), attend.value(image)
    b, _, h, w = q.shape
    r = attend.radius
    out = torch.zeros(b, v.shape[1], h, w, dtype=q.dtype)
    for n in range(b):
        for y in range(h):
            for x in range(w):
                logits, values = [torch.zeros((), dtype=q.dtype)], [torch.zeros(v.shape[1], dtype=q.dtype)]
                for yy in range(max(y - r, 0), min(y + r, h - 1) + 1):
                    for xx in range(max(x - r, 0), min(x + r, w - 1) + 1):
                        logits.append(q[n, :, y, x] @ k[n, :, yy, xx] / attend.dim ** 0.5)
                        values.append(v[n, :, yy, xx])
                weights = torch.softmax(torch.stack(logits), dim=0)
                out[n, :, y, x] = (weights[:, None] * torch.stack(values)).sum(0)
    return out


@pytest.mark.parametrize("radius", [1, 2, 6])
def test_the_carry_attention_equals_its_cell_by_cell_definition(radius):
    """Values and gradients in float64, on maps smaller than the window (radius 6 on 5 x 7 cells)
    and larger (radius 1), so the cells beyond the map are left out at every border."""
    torch.manual_seed(radius)
    attend = CarryAttention(6, 5, radius, dim=4, value_channels=3).double()
    query = torch.randn(2, 6, 5, 7, dtype=torch.float64, requires_grad=True)
    image = torch.randn(2, 5, 5, 7, dtype=torch.float64, requires_grad=True)
    fast, slow = attend(query, image), attention_by_loops(query, image, attend)
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    weights = torch.randn_like(fast)
    grads = torch.autograd.grad((fast * weights).sum(), (query, image, attend.key.weight))
    reference = torch.autograd.grad((slow * weights).sum(), (query, image, attend.key.weight))
    for a, b in zip(grads, reference):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="carry_attend must be an integer >= 1"):
        CarryAttention(6, 5, 0)


def test_the_carry_attention_gathers_a_moved_feature_and_joins_every_stride():
    """A hand-computed case: one image cell matches the query of a cell two cells away, strongly;
    that cell gathers its value and the others almost nothing. In a detector, the gathered map
    joins the carry maps at every head stride; it needs a carry branch and stride 16."""
    attend = CarryAttention(1, 1, 2, dim=1, value_channels=1).double()
    with torch.no_grad():
        for conv in (attend.query, attend.key, attend.value):
            conv.weight.fill_(1.0), conv.bias.zero_()
    query, image = torch.zeros(1, 1, 5, 5, dtype=torch.float64), torch.zeros(1, 1, 5, 5, dtype=torch.float64)
    query[0, 0, 1, 1], image[0, 0, 3, 3] = 10.0, 3.0  # the "hand" was at (3, 3), its events are at (1, 1)
    with torch.no_grad():
        out = attend(query, image)[0, 0]
    # (1, 1) sees 16 of the image cells within 2 (the nothing slot and 15 zeros at logit 0, the hand at 30)
    expected = 3.0 * torch.exp(torch.tensor(30.0, dtype=torch.float64)) / (16 + torch.exp(torch.tensor(30.0)))
    torch.testing.assert_close(out[1, 1], expected)
    assert float(out[0, 0]) == 0.0  # the hand's cell is 3 cells away: out of its window
    torch.testing.assert_close(out[2, 2], torch.tensor(3.0 / 26, dtype=torch.float64))  # all 25 cells plus nothing
    model = Detector(small_detector_config(180, 320, image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16,
                                           carry_width=4, carry_attend=3)).eval()
    dataset = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True)
    batch = collate([dataset[i] for i in (3, 30)])
    with torch.no_grad():
        image_maps, carry = model.frame_maps(batch.images), model.carry_maps(batch.images)
        joined = model.attended(image_maps, carry)
        gathered = model.attend(carry[1], image_maps[2])
    for c, j in zip(carry, joined):
        assert j.shape == (2, c.shape[1] + model.attend.value_channels, *c.shape[-2:])
        torch.testing.assert_close(j[:, :c.shape[1]], c, rtol=0, atol=0)
    torch.testing.assert_close(joined[1][:, carry[1].shape[1]:], gathered, rtol=0, atol=0)
    torch.testing.assert_close(joined[0][:, carry[0].shape[1]:, ::2, ::2], gathered, rtol=0, atol=0)  # repeated
    torch.testing.assert_close(joined[2][:, carry[2].shape[1]:, 0, 0], gathered[:, :, :2, :2].mean((-1, -2)))
    with pytest.raises(ValueError, match="carry_attend=3 needs a carry branch"):
        small_detector_config(180, 320, carry_width=0, carry_attend=3)
    with pytest.raises(ValueError, match="the head stride 16"):
        small_detector_config(180, 320, carry_width=4, carry_attend=3, strides=(32,), event_channels=(8, 8))


@pytest.mark.parametrize("carry_attend", [0, 2])
def test_a_carry_branch_reads_the_picture_into_the_fusion_and_nothing_else_does(carry_attend):
    """``carry_width``: the picture beside the frame reaches the output only through the carry
    branch's maps at the fusion. The event nodes and the image branch read the frame alone (a
    different picture leaves them as they were); the picture changes the answer; with the event
    weights zeroed (which include the carry's) the answer is ``forward(events=False)``'s."""
    torch.manual_seed(0)
    model = Detector(small_detector_config(180, 320, carry_width=4, carry_attend=carry_attend)).eval()
    assert model.carry is not None and model.image.stem[0][0].weight.shape[1] == 3
    dataset = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True)
    batch = collate([dataset[i] for i in (3, 30)])
    assert batch.images.shape[1] == 7
    other = collate([dataset[i] for i in (3, 30)])
    other.images[:, 3:] = torch.flip(other.images[:, 3:], dims=[-1])  # another picture, the same frame
    with torch.no_grad():
        torch.testing.assert_close(model.event_node_features(batch), model.event_node_features(other), rtol=0, atol=0)
        assert all(torch.equal(a, b) for a, b in zip(model.frame_maps(batch.images), model.frame_maps(other.images)))
        answer, _, _ = model.outputs(batch)
        assert not torch.allclose(answer, model.outputs(other)[0])
        blind, _, _ = model.outputs(batch, events=False)
        model.zero_event_weights()
        torch.testing.assert_close(model.outputs(other)[0], blind, rtol=0, atol=0)
    with pytest.raises(ValueError, match="reads images of 7 channels"):
        model.carry_maps(batch.images[:, :3])
    with pytest.raises(ValueError, match="carry_width=4 .a carry branch. needs a hybrid"):
        small_detector_config(180, 320, carry_width=4, late_query=True)


def test_a_carry_branch_with_the_frame_reads_both_and_the_nodes_still_only_the_frame():
    """``carry_frame``: the carry branch's stem reads the frame and the picture (seven channels with
    the recent window); its maps follow either, the event nodes the frame alone; with the image
    off (``forward(image=False)``) it reads a grey frame."""
    torch.manual_seed(0)
    model = Detector(small_detector_config(180, 320, carry_width=4, carry_channels=4, carry_frame=True)).eval()
    assert model.carry.stem[0][0].weight.shape[1] == 7 and model.image.stem[0][0].weight.shape[1] == 3
    dataset = sample_set(stub_root(), "valid", image_age=(1, 10), carry_picture=True, carry_recent_us=10_000)
    batch = collate([dataset[i] for i in (3, 30)])
    assert batch.images.shape[1] == 7
    picture, frame = collate([dataset[i] for i in (3, 30)]), collate([dataset[i] for i in (3, 30)])
    picture.images[:, 3:] = torch.flip(picture.images[:, 3:], dims=[-1])
    frame.images[:, :3] = torch.flip(frame.images[:, :3], dims=[-1])
    grey = collate([dataset[i] for i in (3, 30)])
    grey.images[:, :3] = 128
    with torch.no_grad():
        carry = model.carry_maps(batch.images)
        for changed in (picture, frame):
            assert not all(torch.equal(a, b) for a, b in zip(carry, model.carry_maps(changed.images)))
        torch.testing.assert_close(model.event_node_features(batch), model.event_node_features(picture), rtol=0, atol=0)
        blank = model._features(batch, image=False)[0]
        torch.testing.assert_close(blank, model._features(grey, image=False)[0], rtol=0, atol=0)
    assert Detector(small_detector_config(180, 320, carry_width=0, carry_frame=True)).carry is None  # no branch to read it


@pytest.mark.parametrize("carry_width, carry_attend, grown", [(0, 0, 0), (0, 0, 1), (4, 0, 1), (4, 2, 0)])
def test_the_split_fusion_gives_the_whole_fusion(carry_width, carry_attend, grown):
    """split_fusion: the image's share once, the rest's product an answer, the age's column as a
    vector; the same fused maps as the 1x1 convolution over the joined maps (float64, 1e-9), event
    maps of another size than the image's interpolated as fuse_at does (``grown``)."""
    import copy

    from dagr_lite.nn.blocks import fold_batch_norms

    torch.manual_seed(0)
    model = Detector(small_detector_config(45, 61, carry_width=carry_width, carry_attend=carry_attend)).double().eval()
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    split = fold_batch_norms(copy.deepcopy(model))
    with pytest.raises(ValueError, match="split_fusion needs"):
        copy.deepcopy(model).split_fusion()
    assert split.split_fusion() and split.split_fusion()  # once; a second call keeps it
    assert not Detector(small_detector_config(45, 61, variant="events_only")).split_fusion()
    frame = torch.randint(0, 256, (2, 3, 45, 61), dtype=torch.uint8)
    age = torch.tensor([12_000.0, 70_000.0], dtype=torch.float64)
    with torch.no_grad():
        image_maps = model.frame_maps(frame)
        sizes = [m.shape[-2:] for m in image_maps[1:]]
        events = [torch.randn(2, c, h + grown, w + grown, dtype=torch.float64)
                  for c, (h, w) in zip(model.events.out_channels, sizes)]
        recency = [torch.rand(2, model.num_recency, h + grown, w + grown, dtype=torch.float64) for h, w in sizes]
        carry = None
        if carry_width:
            picture = torch.randint(0, 256, (2, model.cfg.carry_channels, 45, 61), dtype=torch.uint8)
            carry = [torch.nn.functional.interpolate(c, size=(h + grown, w + grown)) if grown else c
                     for c, (h, w) in zip(model.carry_maps(torch.cat([frame, picture], dim=1)), sizes)]
        want = model.combine(image_maps, events, recency, age, carry)[0]
        got = split.combine(image_maps, events, recency, age, carry,
                            image_parts=split.fusion_image_part(image_maps))[0]
    for one, expected in zip(got, want):
        assert one.shape == expected.shape
        assert one.is_contiguous(memory_format=torch.channels_last)
        torch.testing.assert_close(one, expected, rtol=1e-9, atol=1e-9)
