"""Write the stub dataset: ``python data_stubs/generate.py OUT [--seconds S] [--seed N]``.

The default run (``python train.py``) generates the same dataset on first use into
``$DAGR_LITE_CACHE`` (default ``~/.cache/dagr_lite``); this script writes it anywhere.
"""
import argparse
import sys
from pathlib import Path

from dagr_lite.synth.stub import STUB_SECONDS, generate_stub


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="output folder (must not exist yet)")
    parser.add_argument("--seconds", type=float, default=STUB_SECONDS, help="length of each video")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.out.exists():
        print(f"{args.out}: already exists; choose a new folder", file=sys.stderr)
        return 1
    generate_stub(args.out, seconds=args.seconds, seed=args.seed)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
