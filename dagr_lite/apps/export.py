"""Export a dataset to the formats event-camera tools open, and to MP4 renders.

    python -m dagr_lite.apps.export ROOT --to aedat4 evt3 mp4 --out DIR [--videos stub_000 ...]

Writes ``DIR/<split>/<video>.<ext>`` per video (see :mod:`dagr_lite.camera.export`); nothing is overwritten.
"""
from __future__ import annotations

import argparse

from dagr_lite.apps.cli import user_errors
from dagr_lite.camera.export import TARGETS, export_dataset


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.apps.export", description=__doc__.splitlines()[0])
    parser.add_argument("root", help="dataset folder in the EventEgoHands layout")
    parser.add_argument("--to", nargs="+", required=True, choices=sorted(TARGETS), help="formats to write")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--videos", nargs="+", help="only these videos (default: all)")
    args = parser.parse_args(argv)
    with user_errors():
        written = export_dataset(args.root, args.out, args.to, args.videos)
    print(f"{len(written)} files written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
