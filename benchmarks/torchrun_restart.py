"""Fault check: torchrun restarts a failed group and training goes on from the run's own last.pt.

    python benchmarks/torchrun_restart.py [--steps 8] [--fail-at 5] [--out /tmp/restart_check]

Launches ``torchrun --standalone --nproc_per_node=2 --max-restarts=1`` on the stub dataset with
``trainer.checkpoint_every=2``, on the CPU (Gloo), so it runs on any machine, one GPU or none. On the group's first attempt, rank 1 dies (``os._exit(1)``)
right after step ``--fail-at``; torchrun restarts both processes, which find the run folder's
``last.pt`` and resume without ``resume=``. The check passes when the run ends at ``--steps``
with one run folder whose ``last.pt`` says ``world_size`` 2, and the log shows the resume.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def python_path() -> str:
    """The repository first, then whatever PYTHONPATH already holds (packages installed there too)."""
    return os.pathsep.join(part for part in (str(ROOT), os.environ.get("PYTHONPATH")) if part)


def worker(fail_at: int, overrides: list[str]) -> None:
    """One torchrun process: train.py's entry, with rank 1 dying after step ``fail_at`` on the first attempt."""
    sys.path.insert(0, str(ROOT))
    import dagr_lite.engine.loop as loop_module
    import dagr_lite.engine.train as train_module

    original = loop_module.train_step
    first_attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT", "0") == "0"

    def failing_step(state, batch, **kwargs):
        out = original(state, batch, **kwargs)
        if first_attempt and os.environ.get("RANK") == "1" and state.step == fail_at:
            print(f"rank 1: dying after step {state.step} (fault check)", flush=True)
            os._exit(1)
        return out

    loop_module.train_step = failing_step
    sys.argv = [str(ROOT / "train.py"), *overrides]
    import hydra

    # train.py's own entry (Hydra, the run folder, everything), with the config folder given absolutely
    hydra.main(config_path=str(ROOT / "conf"), config_name="train", version_base=None)(train_module.train)()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--fail-at", type=int, default=5)
    parser.add_argument("--out", default="/tmp/torchrun_restart_check", help="working folder (must not exist)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args, overrides = parser.parse_known_args()
    if args.worker:
        worker(args.fail_at, overrides)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=False)
    overrides = [f"trainer.max_steps={args.steps}", "trainer.schedule_by=steps", "trainer.checkpoint_every=2", f"trainer.val_every={args.steps}",
                 "loader.batch_size=2", "loader.num_workers=0", "data.window_us=15000", "trainer.image_every=0",
                 "model=events_only", "device=cpu"]
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
               "--max-restarts=1", __file__, "--worker", f"--fail-at={args.fail_at}", *overrides]
    started = time.monotonic()
    log = out / "log.txt"
    with open(log, "w") as handle:
        code = subprocess.call(command, cwd=out, stdout=handle, stderr=subprocess.STDOUT,
                               env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": python_path()})
    text = log.read_text()
    folders = sorted((out / "runs" / "train").glob("torchrun-*"))
    from dagr_lite.engine.checkpoint import load_checkpoint

    last = load_checkpoint(folders[0] / "checkpoints" / "last.pt").training if len(folders) == 1 else None
    checks = {
        "torchrun exited 0": code == 0,
        f"rank 1 died after step {args.fail_at}": f"dying after step {args.fail_at}" in text,
        "the group resumed from its own last.pt": "resumed from" in text and "last.pt at step" in text,
        "one run folder": len(folders) == 1,
        f"last.pt at step {args.steps}, world_size 2": last is not None and last["step"] == args.steps
        and last["world_size"] == 2,
    }
    for name, ok in checks.items():
        print(f"{'ok  ' if ok else 'FAIL'} {name}")
    resumed = [line for line in text.splitlines() if "resumed from" in line]
    print(f"{resumed[0] if resumed else 'no resume line'}\n{time.monotonic() - started:.0f} s; log: {log}")
    sys.exit(0 if all(checks.values()) else 1)


if __name__ == "__main__":
    main()
