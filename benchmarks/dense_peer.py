"""The event branch against a dense peer that reads the same events.

    python benchmarks/dense_peer.py --dataset ego [--seed 0] [--out DIR]
    python benchmarks/dense_peer.py --dataset ego --events EVENTS_ONLY.pt --peer PEER.pt   # score only

The peer is the image-only model (the project's own CNN and head) reading a picture of the
events-only sample in place of the camera frame: ON count, OFF count and recency of the events of
the last ``data.window_us`` (``data.event_picture=true``, :func:`dagr_lite.data.dataset.event_picture`).
Both are trained with the dataset's recipe (``python train.py dataset=D model=events_only`` and
``python train.py dataset=D model=image_only data.event_picture=true``, the same seed), then scored by
the sweep on the test split; both read the window alone, so one image age scores them. Prints AP50
and mAP of each and the events-only model's AP50 minus the peer's (the target: at least -0.02).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def train(dataset: str, seed: int, run_dir: Path, *overrides: str) -> Path:
    """Train with ``train.py`` into ``run_dir`` (reused when it already holds a finished run)."""
    best = run_dir / "checkpoints" / "best.pt"
    if not (run_dir / "metrics.json").is_file():
        command = [sys.executable, str(ROOT / "train.py"), f"dataset={dataset}", f"seed={seed}", f"run_dir={run_dir}",
                   "trainer.image_every=0", *overrides]
        print("+", " ".join(command[1:]), flush=True)
        subprocess.run(command, check=True, cwd=ROOT)
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="ego", help="a dataset of conf/dataset (stub, ego, or custom with --root)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--events", type=Path, help="an events-only checkpoint (else one is trained)")
    parser.add_argument("--peer", type=Path, help="a dense peer's checkpoint (else one is trained)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--out", type=Path, default=None, help="a new folder for the runs and the sweep")
    args = parser.parse_args(argv)
    out = args.out or ROOT / "runs" / "dense_peer" / f"{args.dataset}-seed{args.seed}"
    if (out / "sweep" / "sweep.json").exists():
        print(f"{out}: holds an earlier comparison (sweep/sweep.json); choose a new --out", file=sys.stderr)
        return 1
    events = args.events or train(args.dataset, args.seed, out / "events_only", "model=events_only")
    peer = args.peer or train(args.dataset, args.seed, out / "peer", "model=image_only", "data.event_picture=true")
    command = [sys.executable, "-m", "dagr_lite.apps.sweep", f"ckpt=[{events},{peer}]", f"dataset={args.dataset}",
               f"split={args.split}", "ages=[1]", f"out={out / 'sweep'}"]
    print("+", " ".join(command[1:]), flush=True)
    subprocess.run(command, check=True, cwd=ROOT)
    rows = json.loads((out / "sweep" / "sweep.json").read_text())["results"]
    by_ckpt = {Path(r["ckpt"]): r for r in rows}
    a, b = by_ckpt[events], by_ckpt[peer]
    print(f"\n{args.dataset}, seed {args.seed}, {args.split} split:")
    print(f"  events_only (event branch)   AP50 {a['AP50']:.3f}  mAP {a['mAP']:.3f}")
    print(f"  dense peer (event picture)   AP50 {b['AP50']:.3f}  mAP {b['mAP']:.3f}")
    print(f"  events_only - peer           AP50 {a['AP50'] - b['AP50']:+.3f}  (target: >= -0.020)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
