"""The training state, one step and one validation pass, called directly."""
import copy

import numpy as np
import pytest
import torch

from dagr_lite.config import build_model, build_optimizer, compose_config, resolve_config
from dagr_lite.data.collate import collate
from dagr_lite.engine.loading import batch_maker, make_loader
from dagr_lite.engine.state import TrainState, train_step, validate
from dagr_lite.eval.coco import METRIC_KEYS
from dagr_lite.eval.score import score_model
from dagr_lite.synth.stub import stub_root
from tests.settings import sample_set
from tests.settings import EVAL


def fresh_state(variant="image_only", seed=0):
    torch.manual_seed(seed)
    cfg = resolve_config(compose_config("train", [f"model={variant}", "optim.lr=1e-3"]))
    model = build_model(cfg, height=180, width=320)
    return TrainState.create(model, build_optimizer(cfg, model.parameters()), total_steps=20, warmup_steps=4,
                             min_lr_ratio=0.05, ema_decay=0.99, ema_tau=5.0, grad_clip=10.0, amp=False)


def a_batch(indices=(3, 40, 77, 120)):
    dataset = sample_set(stub_root(), "train", window_us=10_000)
    return collate([dataset[i] for i in indices])


def test_a_step_updates_weights_schedule_ema_and_count():
    state, batch = fresh_state(), a_batch()
    before = [p.detach().clone() for p in state.model.parameters()]
    out = train_step(state, batch)
    assert state.step == 1 and state.ema.updates == 1
    assert {"loss", "iou_loss", "obj_loss", "cls_loss", "num_fg"} <= set(out) and not out["loss"].requires_grad
    assert any(not torch.equal(a, b) for a, b in zip(before, state.model.parameters()))
    assert state.lr == pytest.approx(1e-3 * 2 / 4)  # after one step the warm-up factor is (1 + 1) / 4


def test_state_dict_round_trip_continues_identically():
    state, batch = fresh_state(), a_batch()
    train_step(state, batch)
    saved = torch.load(_to_bytes(state.state_dict()), weights_only=True)  # through serialisation, as a checkpoint is
    other = fresh_state(seed=1)
    other.load_state_dict(saved)
    assert other.step == 1 and other.best_metric == state.best_metric
    for a, b in zip(state.model.parameters(), other.model.parameters()):
        assert torch.equal(a, b)
    first, second = train_step(state, batch), train_step(other, batch)
    assert float(first["loss"]) == float(second["loss"]) and other.lr == state.lr
    with pytest.raises(KeyError, match="scheduler"):
        other.load_state_dict({k: v for k, v in saved.items() if k != "scheduler"})


def _to_bytes(obj):
    import io
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    buffer.seek(0)
    return buffer


def test_a_non_finite_loss_stops_before_any_weight_changes(monkeypatch):
    state, batch = fresh_state(), a_batch()
    before = [p.detach().clone() for p in state.model.parameters()]
    real = state.model.forward
    monkeypatch.setattr(state.model, "forward", lambda b: {**real(b), "loss": torch.tensor(float("inf"))})
    with pytest.raises(FloatingPointError, match="non-finite loss inf at step 0"):
        train_step(state, batch)
    assert all(torch.equal(a, b) for a, b in zip(before, state.model.parameters())) and state.step == 0


def test_validate_scores_the_ema_weights_over_every_sample():
    state = fresh_state()
    dataset = sample_set(stub_root(), "valid", window_us=10_000)
    loader = make_loader(dataset, batch_size=8, num_workers=0)
    metrics = validate(state, loader, backend="numpy", progress=False, **EVAL)
    assert set(METRIC_KEYS) <= set(metrics) and all(-1 <= metrics[k] <= 1 for k in METRIC_KEYS)
    # What is scored is the EMA module: silence its objectness and nothing is found, while the
    # trained module itself still detects.
    with torch.no_grad():
        for pred in state.ema.module.head.obj_preds:
            pred.bias.fill_(-30.0)
    silenced = validate(state, loader, backend="numpy", conf_threshold=1e-6, nms_threshold=EVAL["nms_threshold"], progress=False)
    assert silenced["mAP"] == 0 and silenced["AR100"] == 0
    _, evaluator = score_model(state.model, loader, state.device, backend="numpy", conf_threshold=1e-6,
                               nms_threshold=EVAL["nms_threshold"], progress=False)
    assert len(evaluator.detections) > 0

def brute_force_edges(pos: np.ndarray, radius: float, k: int) -> set[tuple[int, int]]:
    """Each node's k nearest earlier nodes within radius (ties by smaller index), by a dense distance matrix."""
    dist = np.sqrt(((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1))
    edges = set()
    for i in range(len(pos)):
        candidates = [(dist[i, j], j) for j in range(i) if dist[i, j] <= radius]
        edges |= {(j, i) for _, j in sorted(candidates)[:k]}
    return edges


def test_the_loaders_graph_is_the_models_own():
    cfg = resolve_config(compose_config("train", ["model=events_only", "model.graph.radius=4",
                                                  "model.graph.max_neighbors=6"]))
    model = build_model(cfg, height=180, width=320).eval()
    dataset = sample_set(stub_root(), "valid", window_us=6_000)
    batch = next(iter(make_loader(dataset, batch_size=2, num_workers=0, graph=model.graph_spec)))
    spec = model.graph_spec
    events = batch.events.double()
    expected = set()
    for b in range(2):
        a, z = int(batch.ptr[b]), int(batch.ptr[b + 1])
        pos = np.stack([events[a:z, 0], events[a:z, 1], spec.time_scale * events[a:z, 2]], 1)
        expected |= {(s + a, d + a) for s, d in brute_force_edges(pos, 4.0, 6)}
    assert set(map(tuple, batch.edge_index.t().tolist())) == expected and expected
    with torch.no_grad():
        from_loader = model(batch, **EVAL)
        batch.edge_index = None  # the model builds its own graph
        own = model(batch, **EVAL)
    for x, y in zip(from_loader, own):
        assert torch.equal(x["boxes"], y["boxes"]) and torch.equal(x["scores"], y["scores"])


@pytest.mark.parametrize("native", [True, False])
def test_the_cpu_trains_in_bfloat16_only_where_it_has_it_natively(monkeypatch, native):
    from omegaconf import OmegaConf

    import dagr_lite.engine.precision as train_module

    monkeypatch.setattr(train_module, "cpu_has_bfloat16", lambda: native)
    cpu = torch.device("cpu")
    for dtype in ("auto", "bfloat16"):
        chosen = train_module.amp_dtype(OmegaConf.create({"amp": True, "amp_dtype": dtype}), cpu)
        assert chosen == (torch.bfloat16 if native else None)
    assert train_module.amp_dtype(OmegaConf.create({"amp": True, "amp_dtype": "float16"}), cpu) is None
    assert train_module.amp_dtype(OmegaConf.create({"amp": False, "amp_dtype": "auto"}), cpu) is None
    # Only auto on a native CPU times the two (bfloat16 asked for is kept; CUDA never times).
    asks = {dtype: train_module.prefers_trial(OmegaConf.create({"amp": True, "amp_dtype": dtype}), cpu)
            for dtype in ("auto", "bfloat16")}
    assert asks == {"auto": native, "bfloat16": False}
    cuda = OmegaConf.create({"amp": True, "amp_dtype": "auto"})
    assert not train_module.prefers_trial(cuda, torch.device("cuda"))


def test_the_precision_trial_times_a_copy_and_keeps_bfloat16_only_when_clearly_faster():
    """Timing both precisions leaves the model as it was (weights, batch-norm statistics, no
    gradients, the random state) and chooses bfloat16 only when clearly faster, as hand-made trials say."""
    from dagr_lite.engine.precision import PrecisionTrial, time_precisions

    assert PrecisionTrial(float32_s=0.2, bfloat16_s=0.3).dtype is None
    assert PrecisionTrial(float32_s=0.3, bfloat16_s=0.2).dtype == torch.bfloat16
    # within a tenth float32 stays: the trial's step alone does not tell the faster run (BFLOAT16_MARGIN)
    assert PrecisionTrial(float32_s=0.2, bfloat16_s=0.19).dtype is None
    assert PrecisionTrial(float32_s=0.2, bfloat16_s=0.181).dtype is None
    assert PrecisionTrial(float32_s=0.2, bfloat16_s=0.179).dtype == torch.bfloat16
    state = fresh_state("hybrid")
    before = {key: value.clone() for key, value in state.model.state_dict().items()}
    dataset = sample_set(stub_root(), "train", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (3, 40)])
    torch.manual_seed(7)
    expected_draw = torch.rand(3)
    torch.manual_seed(7)
    trial = time_precisions(state.model, batch, rounds=1)
    assert torch.equal(torch.rand(3), expected_draw)
    assert 0 < trial.float32_s < float("inf") and 0 < trial.bfloat16_s < float("inf")
    assert all(torch.equal(before[key], value) for key, value in state.model.state_dict().items())
    assert all(parameter.grad is None for parameter in state.model.parameters())
    # a first phase's step: the graph left out, as trainer.dense_first's steps run (the flag reaches
    # the model: its event branch runs in the whole step's trial and not in the phase's)
    ran = []
    state.model.events.register_forward_hook(lambda *_: ran.append(1))
    graph_batch = batch_maker(state.model.graph_spec)([dataset[i] for i in (3, 40)])
    time_precisions(state.model, graph_batch, rounds=1)
    assert ran
    ran.clear()
    dense = time_precisions(state.model, graph_batch, rounds=1, graph=False)
    assert not ran
    assert 0 < dense.float32_s < float("inf") and 0 < dense.bfloat16_s < float("inf")
    assert all(torch.equal(before[key], value) for key, value in state.model.state_dict().items())


def test_a_schedule_with_a_first_phase_weighs_its_two_steps_by_their_shares():
    """A run with a first phase (its cheaper steps for the first share of the schedule) chooses by
    its mean step: by time, the harmonic mean (the shares are of the run's time, so more steps in
    it is faster); by steps, the arithmetic mean. Hand-computed cases, and a choice the phase turns."""
    from dagr_lite.engine.precision import PrecisionTrial

    dense, graph = PrecisionTrial(float32_s=0.1, bfloat16_s=0.05), PrecisionTrial(float32_s=0.3, bfloat16_s=0.32)
    by_steps = PrecisionTrial.of_schedule(dense, 0.5, graph, by_time=False)
    assert by_steps.float32_s == pytest.approx(0.2) and by_steps.bfloat16_s == pytest.approx(0.185)
    by_time = PrecisionTrial.of_schedule(dense, 0.5, graph, by_time=True)
    assert by_time.float32_s == pytest.approx(1 / (0.5 / 0.1 + 0.5 / 0.3))  # 0.15
    assert by_time.bfloat16_s == pytest.approx(1 / (0.5 / 0.05 + 0.5 / 0.32))  # 0.0865
    assert graph.dtype is None  # the graph's step alone keeps float32,
    assert by_steps.dtype is None  # as the mean step does when the shares are of steps (0.185 > 0.9 x 0.2),
    assert by_time.dtype == torch.bfloat16  # but not of time: the phase makes twice its steps in bfloat16
    assert by_time.parts == ((0.5, dense), (0.5, graph))
    line = by_time.describe("without the graph (trainer.dense_first)")
    assert line.startswith("a step of the run's schedule took 0.150 s in float32 and 0.086 s in bfloat16 on this CPU "
                           "(its first 50%, without the graph (trainer.dense_first): 0.100 s and 0.050 s; the rest: "
                           "0.300 s and 0.320 s)")
    assert PrecisionTrial.of_schedule(dense, 0.0, graph, by_time=True).float32_s == pytest.approx(0.3)  # no phase


def test_mixed_precision_choices_run_a_step_on_the_cpu():
    """The CUDA path's precision choices, exercised on the CPU: bfloat16 autocast runs without a
    scaler (the hybrid's sparse products and the losses stay float32), float16 gets the scaler."""
    from omegaconf import OmegaConf

    from dagr_lite.engine.precision import amp_dtype

    torch.manual_seed(0)
    cfg = resolve_config(compose_config("train", ["model=hybrid", "optim.lr=1e-3"]))
    model = build_model(cfg, height=180, width=320)
    common = dict(total_steps=20, warmup_steps=4, min_lr_ratio=0.05, ema_decay=0.99, ema_tau=5.0, grad_clip=10.0)
    bf16 = TrainState.create(model, build_optimizer(cfg, model.parameters()), amp=torch.bfloat16, **common)
    assert bf16.amp and not bf16.scaler.is_enabled()
    dataset = sample_set(stub_root(), "train", window_us=10_000, carry_picture=True)
    out = train_step(bf16, collate([dataset[i] for i in (3, 40)]))
    assert torch.isfinite(out["loss"]) and out["loss"].dtype == torch.float32
    fp16 = TrainState.create(model, build_optimizer(cfg, model.parameters()), amp=True, **common)
    assert fp16.amp_dtype == torch.float16
    assert fp16.scaler.is_enabled()
    with pytest.raises(ValueError, match="float16 or bfloat16"):
        TrainState.create(model, build_optimizer(cfg, model.parameters()), amp=torch.float64, **common)
    trainer = OmegaConf.create({"amp": True, "amp_dtype": "bfloat16"})
    assert amp_dtype(trainer, torch.device("cuda")) == torch.bfloat16
    assert amp_dtype(OmegaConf.create({"amp": False, "amp_dtype": "auto"}), torch.device("cuda")) is None


def test_channels_last_is_the_cpu_default_and_can_be_asked_for():
    from omegaconf import OmegaConf

    from dagr_lite.engine.precision import memory_format

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    chosen = {(value, device.type): memory_format(OmegaConf.create({"channels_last": value}), device)
              for value in ("auto", True, False) for device in (cpu, cuda)}
    assert chosen == {("auto", "cpu"): torch.channels_last, ("auto", "cuda"): torch.contiguous_format,
                      (True, "cpu"): torch.channels_last, (True, "cuda"): torch.channels_last,
                      (False, "cpu"): torch.contiguous_format, (False, "cuda"): torch.contiguous_format}


def test_channels_last_weights_give_the_contiguous_model_s_loss_and_gradients():
    """The layout changes how the convolutions run, not what they compute: the hybrid's loss and
    every gradient match the contiguous model's to float32 rounding, and its saved weights load
    into a contiguous model as the same numbers."""
    state = fresh_state("hybrid")
    contiguous = state.model.train()
    last = copy.deepcopy(contiguous).to(memory_format=torch.channels_last)
    assert last.image.stem[0][0].weight.is_contiguous(memory_format=torch.channels_last)
    dataset = sample_set(stub_root(), "train", window_us=10_000, carry_picture=True)
    batch = collate([dataset[i] for i in (3, 40, 77)])
    losses = []
    for model in (contiguous, last):
        torch.manual_seed(3)
        loss = model(batch)["loss"]
        loss.backward()
        losses.append(float(loss.detach()))
    assert losses[1] == pytest.approx(losses[0], rel=1e-5)
    for (name, a), b in zip(contiguous.named_parameters(), last.parameters()):
        scale = float(a.grad.abs().max()) + 1e-6
        assert torch.allclose(b.grad, a.grad, rtol=1e-3, atol=1e-4 * scale), name
    fresh = fresh_state("hybrid", seed=5).model
    fresh.load_state_dict(last.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), last.state_dict().values()))


def test_the_fused_adamw_makes_the_loop_s_update():
    """optim.fused: the configured AdamW is fused, and given the same gradients its update is the
    per-tensor loop's to rounding, over several steps of the schedule's kind of learning rate."""
    configs = {fused: resolve_config(compose_config("train", ["optim.lr=1e-3"] + ([] if fused else ["optim.fused=null"])))
               for fused in (True, False)}
    torch.manual_seed(0)
    shapes = [(16, 3, 4, 4), (16,), (64, 32), (1,)]
    start = [torch.randn(shape) for shape in shapes]
    grads = [[torch.randn(shape) for shape in shapes] for _ in range(5)]
    runs = []
    for fused in (True, False):
        params = [torch.nn.Parameter(value.clone()) for value in start]
        optimizer = build_optimizer(configs[fused], params)
        assert optimizer.param_groups[0]["fused"] is (True if fused else None)
        for step in grads:
            for param, grad in zip(params, step):
                param.grad = grad.clone()
            optimizer.step()
        runs.append(params)
    for a, b, s in zip(*runs, start):
        assert not torch.equal(a, s)
        assert torch.allclose(a, b, rtol=0, atol=1e-6)
