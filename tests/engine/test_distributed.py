"""Training on two CPU processes (Gloo on loopback) equals training on one with the global batch."""
from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.engine.loading import EpochSampler

STEPS = 4
PER_RANK = 2  # samples per process and step; the global batch is 4


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_training(rank: int, world: int, port: int, run_dir: str, overrides: list[str], out: str) -> None:
    """One process of a run: trains, recording a checksum of every parameter after each step and
    keeping a copy of ``last.pt`` at each step."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    import dagr_lite.engine.loop as loop_module
    import dagr_lite.engine.train as train_module
    from tests.engine.test_train import small

    sums, original_step, original_save = [], loop_module.train_step, loop_module.save_checkpoint

    def recording_step(state, batch, **kwargs):
        result = original_step(state, batch, **kwargs)
        sums.append([float(p.detach().double().sum()) for p in state.model.parameters()])
        return result

    def keep_copies(path, state):
        original_save(path, state)
        if path.name == "last.pt":
            original_save(path.with_name(f"step{state['step']}.pt"), state)

    loop_module.train_step, loop_module.save_checkpoint = recording_step, keep_copies
    result = train_module.train(small(run_dir, *overrides))
    torch.save({"sums": sums, "losses": result["losses"], "metrics": result["metrics"]}, f"{out}.rank{rank}")


def launch(tmp_path: Path, name: str, world: int, *overrides: str) -> list[dict]:
    run_dir = tmp_path / name
    common = [f"loader.batch_size={PER_RANK * 2 // world}", f"trainer.max_steps={STEPS}", "trainer.schedule_by=steps", "trainer.val_every=4",
              "trainer.checkpoint_every=1", "model=events_only", "model.event_dense=0", "data.window_us=20000",
              "trainer.val_samples=null"]  # every sample: sharded validation is compared with evaluate
    args = (world, free_port(), str(run_dir), [*common, *overrides], str(tmp_path / f"{name}.out"))
    if world == 1:
        run_training(0, *args)
    else:
        mp.start_processes(run_training, args=args, nprocs=world, start_method="spawn")
    return [torch.load(f"{tmp_path / name}.out.rank{r}", weights_only=False) for r in range(world)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ddp")
    two = launch(tmp, "two", 2)
    one = launch(tmp, "one", 1)
    return tmp, two, one


def test_ranks_hold_identical_weights_after_every_step_and_match_one_process(runs):
    tmp, two, one = runs
    assert len(two[0]["sums"]) == STEPS
    assert two[0]["sums"] == two[1]["sums"]  # bit-identical on both ranks after every step
    ddp = load_checkpoint(tmp / "two" / "checkpoints" / "last.pt").training
    single = load_checkpoint(tmp / "one" / "checkpoints" / "last.pt").training
    assert ddp["world_size"] == 2 and ddp["global_batch_size"] == 4 and single["world_size"] == 1
    where = [{key: saved["position"][key] for key in ("epoch", "offset")} for saved in (ddp, single)]
    assert where[0] == where[1] == {"epoch": 0, "offset": STEPS * 4}
    # The events-only model with GCN pooled stages (event_dense=0): its dense stages' batch norms over
    # mostly empty maps give many more near-zero gradients, which the bound below does not allow for.
    # Sums in another order differ in the last bits; AdamW divides each gradient by its own size, so
    # where a gradient is near zero that can move a weight by a fraction of a step (lr = 2e-3, at most
    # about lr per step). Wrong gradients would move most weights by whole steps.
    lr = 2e-3
    floats = [k for k, v in single["model"].items() if v.is_floating_point()]
    diffs = torch.cat([(ddp["model"][k] - single["model"][k]).abs().flatten() for k in floats])
    assert float(diffs.max()) < 0.5 * lr
    assert int((diffs > 0.1 * lr).sum()) <= max(2, int(1e-4 * len(diffs)))  # a few near-zero gradients at most
    assert float(diffs.mean()) < 1e-3 * lr
    torch.testing.assert_close(torch.tensor(two[0]["losses"]), torch.tensor(one[0]["losses"]), rtol=1e-4, atol=1e-5)


def test_sharded_validation_equals_one_process(runs):
    tmp, two, _ = runs
    from dagr_lite.engine.evaluate import evaluate
    from tests.engine.test_train import config

    metrics = two[0]["metrics"]
    assert two[1]["metrics"] == metrics
    result = evaluate(config("evaluate", f"ckpt={tmp / 'two' / 'checkpoints' / 'last.pt'}", "split=valid",
                             f"run_dir={tmp / 'eval'}", "loader.num_workers=0"))
    for key in ("mAP", "AP50", "AP75", "AR100"):
        assert result["metrics"][key] == pytest.approx(metrics[key], abs=1e-12)


def test_resume_under_ddp_and_on_another_number_of_processes(runs):
    tmp, two, _ = runs
    step2 = tmp / "two" / "checkpoints" / "step2.pt"
    resumed = launch(tmp, "resumed", 2, f"resume={step2}")
    assert len(resumed[0]["losses"]) == STEPS - 2
    torch.testing.assert_close(torch.tensor(resumed[0]["losses"]), torch.tensor(two[0]["losses"][2:]),
                               rtol=1e-6, atol=1e-7)
    alone = launch(tmp, "alone", 1, f"resume={step2}")  # the same global batch on one process
    torch.testing.assert_close(torch.tensor(alone[0]["losses"]), torch.tensor(two[0]["losses"][2:]),
                               rtol=1e-4, atol=1e-5)
    saved = json.loads((tmp / "alone" / "metrics.json").read_text())
    assert saved["world_size"] == 1 and saved["global_batch_size"] == 4


def test_epoch_sampler_splits_each_global_batch_between_ranks():
    whole = EpochSampler(23, seed=5, batch_size=6)
    shards = [EpochSampler(23, seed=5, rank=r, world_size=2, batch_size=3) for r in range(2)]
    for sampler in (whole, *shards):
        sampler.set_epoch(2, start=6)
    order, parts = list(whole), [list(s) for s in shards]
    assert [len(p) for p in parts] == [len(s) for s in shards] == [6, 6]  # 17 left: two global batches of 6
    for g in range(2):
        assert sorted(parts[0][3 * g:3 * g + 3] + parts[1][3 * g:3 * g + 3]) == sorted(order[6 * g:6 * g + 6])


def test_processes_of_one_torchrun_share_one_run_folder(monkeypatch):
    """Hydra names the run folder in each process; under torchrun every process (and every restart
    of the group) must get the same one, whatever its clock says."""
    from dagr_lite.config import torchrun_folder

    default = "runs/train/2026-01-01/10-00-00-123456"
    assert torchrun_folder(default) == default  # a single process keeps the dated folder
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "3f2a")
    assert torchrun_folder(default) == "runs/train/torchrun-3f2a"
    assert torchrun_folder("runs/train/2026-01-01/10-00-01-000001") == "runs/train/torchrun-3f2a"
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "none")  # a static rendezvous
    monkeypatch.setenv("MASTER_ADDR", "node1")
    monkeypatch.setenv("MASTER_PORT", "29500")
    assert torchrun_folder(default) == "runs/train/torchrun-node1-29500"


def test_torchrun_restarts_a_failed_group_which_resumes_from_its_own_checkpoint(tmp_path):
    """``benchmarks/torchrun_restart.py``: rank 1 dies mid-run, torchrun restarts the group, and
    the run ends from its own last.pt, in one folder, without resume=."""
    import subprocess
    import sys

    from dagr_lite.synth.stub import stub_root

    stub_root()  # made once here, not by both processes
    script = Path(__file__).resolve().parents[2] / "benchmarks" / "torchrun_restart.py"
    done = subprocess.run([sys.executable, str(script), "--steps", "6", "--fail-at", "3", "--out",
                           str(tmp_path / "check")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ok   the group resumed from its own last.pt" in done.stdout


def test_more_processes_than_gpus_is_refused_before_touching_the_gpu(monkeypatch):
    """torchrun --nproc_per_node 2 on a one-GPU machine: rank 1 would need GPU 1."""
    from dagr_lite.engine import distributed

    monkeypatch.setattr(distributed.torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(distributed.torch.cuda, "set_device", lambda device: pytest.fail("set_device reached"))
    with pytest.raises(RuntimeError, match=r"LOCAL_RANK 1, so it needs GPU 1, but this machine has 1 GPU.*device=cpu"):
        distributed.setup(distributed.Distributed(rank=1, world_size=2, local_rank=1), torch.device("cuda"))
