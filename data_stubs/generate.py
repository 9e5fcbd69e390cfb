"""Write a built-in dataset: ``python data_stubs/generate.py OUT [--dataset stub|ego] [--seconds S] [--seed N]``.

The default run (``python train.py``, or ``dataset=ego``) generates the same dataset on first use
into ``$DAGR_LITE_CACHE`` (default ``~/.cache/dagr_lite``); this script writes it anywhere.
``--dvs-model clean|noisy`` makes the ego dataset's scenes with one DVS model throughout (its
default is mixed: each video clean or noisy). ``--workers``: processes writing videos (default one per
CPU core); the dataset is the same for any number.
"""
import argparse
import sys
from pathlib import Path

from dagr_lite.synth.ego import EGO_DVS_MODEL, EGO_SECONDS, generate_ego
from dagr_lite.synth.stub import STUB_SECONDS, generate_stub


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="output folder (must not exist yet)")
    parser.add_argument("--dataset", choices=("stub", "ego"), default="stub")
    parser.add_argument("--seconds", type=float, default=None,
                        help=f"length of each video (default: stub {STUB_SECONDS}, ego {EGO_SECONDS})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dvs-model", choices=("clean", "noisy", "mixed"), default=None,
                        help=f"ego only: the DVS model of every video (default {EGO_DVS_MODEL})")
    parser.add_argument("--workers", type=int, default=None, help="processes writing videos (default: one per core)")
    args = parser.parse_args(argv)
    if args.out.exists():
        print(f"{args.out}: already exists; choose a new folder", file=sys.stderr)
        return 1
    if args.workers is not None and args.workers < 1:
        print(f"--workers must be at least 1, got {args.workers}", file=sys.stderr)
        return 1
    if args.dataset == "stub":
        if args.dvs_model is not None:
            print("--dvs-model is for --dataset ego (the stub is clean)", file=sys.stderr)
            return 1
        generate_stub(args.out, seconds=args.seconds or STUB_SECONDS, seed=args.seed, workers=args.workers)
    else:
        generate_ego(args.out, seconds=args.seconds or EGO_SECONDS, seed=args.seed,
                     dvs_model=args.dvs_model or EGO_DVS_MODEL, workers=args.workers)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
