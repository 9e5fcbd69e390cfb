import math
import os
from functools import partial

import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader

from dagr_lite.engine.loading import EpochSampler, RunSampler, prepare_worker
from dagr_lite.engine.schedule import ModelEMA, warmup_cosine


def test_warmup_cosine_by_hand():
    schedule = [warmup_cosine(step, warmup=4, total=12, min_ratio=0.1) for step in range(16)]
    assert schedule[:4] == pytest.approx([0.25, 0.5, 0.75, 1.0])  # (step + 1) / warmup
    assert schedule[4] == pytest.approx(1.0)  # the cosine starts at its top
    assert schedule[6] == pytest.approx(0.1 + 0.45 * (1 + math.sqrt(0.5)))  # a quarter of the way: cos(pi / 4)
    assert schedule[8] == pytest.approx(0.55)  # halfway: min_ratio + (1 - min_ratio) / 2
    assert schedule[10] == pytest.approx(0.1 + 0.45 * (1 - math.sqrt(0.5)))
    assert schedule[12:] == pytest.approx([0.1] * 4)  # min_ratio at and after total
    assert all(a >= b for a, b in zip(schedule[4:], schedule[5:]))
    assert warmup_cosine(0, warmup=0, total=10, min_ratio=0.0) == pytest.approx(1.0)
    assert warmup_cosine(5, warmup=0, total=10, min_ratio=0.0) == pytest.approx(0.5)


def test_warmup_cosine_follows_the_further_of_steps_and_a_given_progress():
    # step 6 of warmup 4, total 12: a quarter of the way by steps
    assert warmup_cosine(6, warmup=4, total=12, min_ratio=0.1, progress=0.5) == pytest.approx(0.55)  # time is further
    assert warmup_cosine(6, warmup=4, total=12, min_ratio=0.1, progress=0.1) == pytest.approx(
        0.1 + 0.45 * (1 + math.sqrt(0.5)))  # the steps are further
    assert warmup_cosine(6, warmup=4, total=10**9, min_ratio=0.1, progress=2.0) == pytest.approx(0.1)  # past the end
    assert warmup_cosine(2, warmup=4, total=12, min_ratio=0.1, progress=0.9) == pytest.approx(0.75)  # warm-up by steps


def test_model_ema_follows_the_ramped_recursion():
    torch.manual_seed(0)
    model = nn.Linear(3, 2)
    decay, tau = 0.9, 2.0
    ema = ModelEMA(model, decay=decay, tau=tau)
    expected = {name: value.clone() for name, value in model.state_dict().items()}
    for update in range(1, 5):
        with torch.no_grad():
            model.weight.mul_(-1.5).add_(0.25 * update)
            model.bias.add_(1.0)
        assert torch.allclose(ema.module.bias, expected["bias"], atol=1e-6)  # unchanged until update() is called
        ema.update(model)
        d = decay * (1 - math.exp(-update / tau))
        for name, value in model.state_dict().items():
            expected[name] = d * expected[name] + (1 - d) * value
    assert ema.updates == 4
    for name, value in ema.module.state_dict().items():
        assert torch.allclose(value, expected[name], atol=1e-6), name
    assert not any(p.requires_grad for p in ema.module.parameters())


def test_model_ema_copies_integer_buffers_and_averages_float_ones():
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    ema = ModelEMA(model, decay=0.5, tau=1.0)
    for _ in range(3):
        model(torch.randn(8, 3))  # train mode: three batch-norm updates
    ema.update(model)
    d = 0.5 * (1 - math.exp(-1.0))
    assert ema.module[1].num_batches_tracked.item() == 3
    assert ema.module[1].num_batches_tracked.dtype == torch.int64
    assert torch.allclose(ema.module[1].running_mean, (1 - d) * model[1].running_mean, atol=1e-6)  # started at 0
    assert torch.allclose(ema.module[1].running_var, d * 1.0 + (1 - d) * model[1].running_var, atol=1e-6)


def test_model_ema_state_dict_round_trip():
    torch.manual_seed(0)
    model = nn.Linear(3, 2)
    ema = ModelEMA(model, decay=0.9, tau=2.0)
    for _ in range(3):
        with torch.no_grad():
            model.weight.add_(1.0)
        ema.update(model)
    restored = ModelEMA(nn.Linear(3, 2), decay=0.9, tau=2.0)
    restored.load_state_dict(ema.state_dict())
    assert restored.updates == 3
    for name, value in ema.module.state_dict().items():
        assert torch.equal(restored.module.state_dict()[name], value)
    # The next update uses the restored count: both copies move the same way.
    with torch.no_grad():
        model.weight.add_(1.0)
    ema.update(model)
    restored.update(model)
    assert restored.updates == ema.updates == 4
    assert torch.equal(restored.module.weight, ema.module.weight)


def test_epoch_sampler_orders_are_reproducible_permutations():
    size = 50
    sampler = EpochSampler(size, seed=7)
    sampler.set_epoch(3)
    order = list(sampler)
    assert sorted(order) == list(range(size)) and len(sampler) == size
    again = EpochSampler(size, seed=7)
    again.set_epoch(3)
    assert list(again) == order
    sampler.set_epoch(4)
    assert list(sampler) != order and sorted(sampler) == list(range(size))
    other_seed = EpochSampler(size, seed=8)
    other_seed.set_epoch(3)
    assert list(other_seed) != order


@pytest.mark.parametrize("start", [0, 1, 17, 49, 50])
def test_epoch_sampler_resumes_with_the_suffix(start):
    full = EpochSampler(50, seed=3)
    full.set_epoch(2)
    order = list(full)
    resumed = EpochSampler(50, seed=3)
    resumed.set_epoch(2, start=start)
    assert list(resumed) == order[start:] and len(resumed) == 50 - start
    resumed.set_epoch(2)  # a new set_epoch without start begins at the beginning again
    assert list(resumed) == order and len(resumed) == 50


def test_epoch_sampler_without_shuffle_is_in_range_order():
    sampler = EpochSampler(10, seed=1, shuffle=False)
    for epoch in (0, 5):
        sampler.set_epoch(epoch)
        assert list(sampler) == list(range(10))
    sampler.set_epoch(5, start=4)
    assert list(sampler) == list(range(4, 10)) and len(sampler) == 6


@pytest.mark.parametrize("world_size", [1, 2])
def test_run_sampler_chains_whole_batches_of_each_epoch(world_size):
    """Epoch after epoch, the epoch sampler's order cut to whole batches, each index with its epoch."""
    size, batch = 23, 3  # 7 batches of 3 on one process (2 samples dropped); 3 global batches of 6 on two

    def epoch_order(epoch, start=0, rank=0):
        sampler = EpochSampler(size, seed=4, rank=rank, world_size=world_size, batch_size=batch)
        sampler.set_epoch(epoch, start)
        order = list(sampler)
        return order[:len(order) // batch * batch]

    for rank in range(world_size):
        run = RunSampler(EpochSampler(size, seed=4, rank=rank, world_size=world_size, batch_size=batch), batch)
        per_epoch = len(epoch_order(0, rank=rank))
        assert per_epoch == (21 if world_size == 1 else 9)
        pairs = [pair for _, pair in zip(range(3 * per_epoch), run)]
        expected = [(e, i) for e in range(3) for i in epoch_order(e, rank=rank)]
        assert pairs == expected
        run.start_at(2, 6)  # a resumed run: epoch 2, six samples of the global order done
        pairs = [pair for _, pair in zip(range(per_epoch), run)]
        first = epoch_order(2, 6, rank=rank)
        assert pairs[:len(first)] == [(2, i) for i in first]
        assert pairs[len(first):] == [(3, i) for i in epoch_order(3, rank=rank)][:per_epoch - len(first)]


class _WorkerView(torch.utils.data.Dataset):
    """Each item: the worker's niceness and torch threads, as the worker sees them."""

    def __len__(self):
        return 2

    def __getitem__(self, index):
        return torch.tensor([os.nice(0), torch.get_num_threads()])


@pytest.mark.skipif(not hasattr(os, "nice"), reason="no os.nice on this platform")
def test_loader_workers_run_one_thread_at_a_lower_priority():
    base = os.nice(0)
    for nice, want in ((0, base), (3, min(19, base + 3))):
        loader = DataLoader(_WorkerView(), batch_size=1, num_workers=1,
                            worker_init_fn=partial(prepare_worker, nice=nice))
        seen = torch.cat(list(loader))
        assert seen[:, 0].tolist() == [want, want] and seen[:, 1].tolist() == [1, 1]
    assert os.nice(0) == base  # this process keeps its own priority


def test_a_failed_checkpoint_write_names_the_path_and_keeps_the_earlier_one(tmp_path):
    """A real write failure: the file size limit (RLIMIT_FSIZE, with SIGXFSZ ignored so the write
    fails with EFBIG instead of killing the process)."""
    import resource
    import signal

    from dagr_lite.engine.checkpoint import save_checkpoint

    path = tmp_path / "last.pt"
    save_checkpoint(path, {"model": {"w": torch.zeros(4)}})
    before = path.read_bytes()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, hard))
        with pytest.raises(OSError, match=r"last\.pt: the checkpoint could not be written \(.*\); the earlier "
                                          r"last\.pt is kept as it was"):
            save_checkpoint(path, {"model": {"w": torch.zeros(1 << 20)}})  # 4 MiB > 1 MiB
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old_handler)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]  # no temporary file left
    assert path.read_bytes() == before
    assert torch.load(path, weights_only=True)["model"]["w"].shape == (4,)
