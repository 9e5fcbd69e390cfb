"""The paper's version experiment (Table III) on one source, in one command.

    python -m dagr_lite.apps.versions --source DIR --versions v2,v3,v4,v5,v6 \\
        --budget-minutes M --out OUT [--labels L.json] [--splits S.json] [--seed 0]
    python -m dagr_lite.apps.versions --stub-source 1280x720 --versions v2,v3,v4,v5,v6 \\
        --budget-minutes M --out OUT

From the same source frames (``DIR/<video>/frame_<k>.jpg`` with labels in the release format at
the source's resolution, as ``python -m dagr_lite.synth.build --frames`` takes them) it builds each
version (scale, upsampling, clean / noisy / mixed, as in the paper's Table I) into
``OUT/datasets/<v>``, trains the default hybrid on each with the same wall-clock budget into
``OUT/runs/<v>``, evaluates each model on its version's test split (the same test videos for
every version), and prints and writes ``OUT/versions.json`` and ``OUT/versions.md``: mAP50,
mAP75 and mAP per version. Finished builds, training runs and evaluations are reused, so an
interrupted experiment resumes. ``--stub-source WxH`` first renders the stub's hand scenes at
that size (by default 12 / 2 / 2 train / valid / test videos of 2 s, ``--stub-videos`` and
``--stub-seconds`` to change it; upscaled from the stub's 320x180 so the hands keep their
proportions) into ``OUT/source``.

Training uses the quick CPU recipe (``conf/recipe/quick.yaml``, composed as ``recipe=quick``) with
``trainer.max_minutes`` as the budget in place of its length.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.writer import write_frame, write_text_atomically
from dagr_lite.synth.build import VERSIONS, BuildSettings, build, folder_jobs

RECIPE = ["recipe=quick", "trainer.image_every=0"]  # conf/recipe/quick.yaml itself; the budget replaces its length
METRICS = ("AP50", "AP75", "mAP")


def write_stub_source(out: Path, height: int, width: int, *, seconds: float = 2.0,
                      splits: dict[str, int] | None = None) -> tuple[Path, Path, Path]:
    """Frame folders, labels (xywh at ``height x width``) and a split file of the stub's scenes,
    rendered at 320x180 and upscaled; returns ``(frames folder, labels file, splits file)``."""
    from dagr_lite.synth.stub import STUB_SPLITS, HandScene, split_of_videos

    frames_dir, labels_file, splits_file = out / "frames", out / "labels.json", out / "splits.json"
    counts = dict(splits or STUB_SPLITS)
    settings = {"height": height, "width": width, "seconds": seconds, "videos": counts}
    made = out / "source.json"
    if labels_file.exists():
        if made.exists() and json.loads(made.read_text()) != settings:
            raise UserError(f"{out} holds a stub source made with {made.read_text().strip()}, not {settings}; "
                             f"choose another --out or remove {out}")
        return frames_dir, labels_file, splits_file
    names, labels = {s: [] for s in counts}, {}
    for index, split in enumerate(split_of_videos(counts)):
        video = f"source_{index:03d}"
        scene = HandScene(index, seconds=seconds)
        factor = (width / scene.width, height / scene.height)
        for k in range(scene.num_frames):
            image = Image.fromarray(scene.frame(k).clip(0, 255).astype(np.uint8)).resize((width, height),
                                                                                       Image.BICUBIC)
            write_frame(frames_dir / video / fmt.frame_name(k), np.asarray(image), overwrite=True)
        labels[video] = {k: (scene.boxes(k) * [*factor, *factor]).tolist() for k in range(scene.num_frames)}
        names[split].append(video)
    write_text_atomically(made, json.dumps(settings))
    write_text_atomically(splits_file, json.dumps(names))
    write_text_atomically(labels_file, json.dumps({fmt.label_key(v, k): boxes for v, frames in labels.items()
                                                   for k, boxes in frames.items()}))
    return frames_dir, labels_file, splits_file


def version_config(root: Path, run: Path, *, minutes: float, steps: int | None, seed: int,
                   overrides: list[str] = ()):
    """The training config of one version: the default hybrid, the stub recipe, the budget."""
    from dagr_lite.config import compose_config
    from dagr_lite.config import budget_overrides

    return compose_config("train", ["dataset=custom", f"dataset.root={root}", f"run_dir={run}", f"seed={seed}",
                                    *RECIPE, "trainer.val_every=200", *budget_overrides(minutes, steps), *overrides])


def train_version(root: Path, run: Path, *, minutes: float, steps: int | None, seed: int,
                  overrides: list[str] = ()) -> Path:
    """The default hybrid trained on ``root`` for the budget; a finished run is reused."""
    from dagr_lite.engine.train import train

    if not (run / "metrics.json").exists():
        train(version_config(root, run, minutes=minutes, steps=steps, seed=seed, overrides=overrides))
    return run / "checkpoints" / "best.pt"


def evaluate_version(root: Path, checkpoint: Path, out: Path) -> dict:
    """Test-split metrics of ``checkpoint`` on ``root`` (written to ``out``; reused when there)."""
    from dagr_lite.config import compose_config
    from dagr_lite.engine.evaluate import evaluate

    if (out / "metrics.json").exists():
        return json.loads((out / "metrics.json").read_text())
    return evaluate(compose_config("evaluate", ["dataset=custom", f"dataset.root={root}", f"ckpt={checkpoint}",
                                                "split=test", f"run_dir={out}"]))["metrics"]


def check_versions(versions: list[str], minutes: float, steps: int | None) -> None:
    """The experiment's own arguments, checked before any work (rendering, building, training)."""
    if not versions:
        raise UserError(f"--versions: expected some of {sorted(VERSIONS)}, comma-separated, got none")
    unknown = [v for v in versions if v not in VERSIONS]
    if unknown:
        raise UserError(f"--versions: unknown {unknown}; expected some of {sorted(VERSIONS)}")
    if not minutes > 0:
        raise UserError(f"--budget-minutes: expected a positive number of minutes, got {minutes}")
    if steps is not None and steps <= 0:
        raise UserError(f"--steps: expected a positive number of steps, got {steps}")


def run_versions(frames: Path, out: Path, versions: list[str], *, minutes: float, labels: Path | None = None,
                 splits: Path | None = None, steps: int | None = None, seed: int = 0,
                 train_overrides: list[str] = ()) -> list[dict]:
    """Build, train and evaluate each version; returns the table's rows (also written to ``out``).
    ``train_overrides``: more training settings (e.g. ``loader.batch_size=4`` for a tiny source)."""
    check_versions(versions, minutes, steps)
    jobs = folder_jobs(frames, labels=labels, splits=splits)
    rows = []
    for version in versions:
        started = time.monotonic()
        root = out / "datasets" / version
        build(jobs, root, BuildSettings(seed=seed, **VERSIONS[version]))
        built = time.monotonic()
        checkpoint = train_version(root, out / "runs" / version, minutes=minutes, steps=steps, seed=seed,
                                   overrides=list(train_overrides))
        metrics = evaluate_version(root, checkpoint, out / "eval" / version)
        rows.append({"version": version, **VERSIONS[version], **{m: metrics[m] for m in METRICS},
                     "build_s": round(built - started, 1), "train_and_eval_s": round(time.monotonic() - built, 1)})
        write_results(out, rows, minutes)
    return rows


def write_results(out: Path, rows: list[dict], minutes: float) -> str:
    header = "| version | upsampling | scale | DVS model | mAP50 | mAP75 | mAP |\n|---|---|---|---|---|---|---|\n"
    table = header + "".join(f"| {r['version']} | {r['upsample']} | {r['scale']} | {r['dvs_model']} | "
                             f"{r['AP50']:.3f} | {r['AP75']:.3f} | {r['mAP']:.3f} |\n" for r in rows)
    write_text_atomically(out / "versions.json", json.dumps({"budget_minutes": minutes, "rows": rows}, indent=1))
    write_text_atomically(out / "versions.md", f"Test split, {minutes:g} minutes of training per version.\n\n{table}")
    return table


def parse_numbers(text: str, separator: str, count: int, option: str, expected: str) -> list[int]:
    """``count`` positive integers from ``text``; a clear error naming ``option`` otherwise."""
    parts = text.lower().split(separator)
    if len(parts) != count or not all(p.strip().isdigit() and int(p) > 0 for p in parts):
        raise SystemExit(f"{option}: expected {expected}, got {text!r}")
    return [int(p) for p in parts]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.apps.versions", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--source", type=Path, help="folder of <video>/frame_<k>.jpg folders")
    source.add_argument("--stub-source", metavar="WxH", help="render the stub's scenes at this size as the source")
    parser.add_argument("--stub-videos", default="12,2,2", metavar="TRAIN,VALID,TEST",
                        help="videos per split of --stub-source (default 12,2,2)")
    parser.add_argument("--stub-seconds", type=float, default=2.0, help="length of each --stub-source video")
    parser.add_argument("--labels", type=Path, help="labels of the source frames (release format)")
    parser.add_argument("--splits", type=Path, help='JSON {"train": [...], "valid": [...], "test": [...]}')
    parser.add_argument("--versions", default="v2,v3,v4,v5,v6", help="comma-separated, e.g. v1,v2,v3,v4,v5,v6")
    parser.add_argument("--budget-minutes", type=float, required=True, help="training budget per version")
    parser.add_argument("--steps", type=int, help="train this many steps instead (still capped by the budget)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    versions = [v.strip() for v in args.versions.split(",") if v.strip()]
    try:
        check_versions(versions, args.budget_minutes, args.steps)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    frames, labels, splits = args.source, args.labels, args.splits
    if args.stub_source:
        width, height = parse_numbers(args.stub_source, "x", 2, "--stub-source", "WxH, e.g. 1280x720")
        counts = parse_numbers(args.stub_videos, ",", 3, "--stub-videos", "TRAIN,VALID,TEST, e.g. 12,2,2")
        if args.stub_seconds <= 0:
            parser.error(f"--stub-seconds must be positive, got {args.stub_seconds}")
        frames, labels, splits = write_stub_source(args.out / "source", height, width, seconds=args.stub_seconds,
                                                   splits=dict(zip(("train", "valid", "test"), counts)))
    started = time.monotonic()
    rows = run_versions(frames, args.out, versions,
                        minutes=args.budget_minutes, labels=labels, splits=splits, steps=args.steps, seed=args.seed)
    print(write_results(args.out, rows, args.budget_minutes))
    print(f"{(time.monotonic() - started) / 60:.1f} minutes; {args.out / 'versions.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
