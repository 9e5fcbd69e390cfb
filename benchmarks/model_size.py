"""What running a checkpoint at a camera's own size does to accuracy (``detect``'s ``sensor.model_size=sensor``).

    python benchmarks/model_size.py --ckpt CKPT [--split test] [--out DIR]

A camera with twice the model's resolution is emulated from the stub's scenes of one split: every
frame (and in-between frame) rendered at 320x180 is upsampled bilinearly to 640x360, events are
emulated at 640x360 with the stub's DVS preset and temporal upsampling, and boxes are doubled. The
checkpoint is then scored (``evaluate``, COCO mAP) three ways:

- on the stub split itself, the data it was trained for (the reference);
- ``sensor.scale=2``: the camera's events and frames binned to 320x180 by :class:`Sensor`, as
  ``detect`` does by default;
- ``sensor.model_size=sensor``: the weights run at 640x360 on the camera's own pixels
  (``evaluate.py model_size=data``).

The datasets are written under ``--out`` (a new folder; reused by a second run with the same folder).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from scipy.ndimage import zoom as nd_zoom

from dagr_lite.camera.recording import open_recording
from dagr_lite.camera.sensor import Sensor
from dagr_lite.data.writer import VideoWriter, write_labels
from dagr_lite.engine.evaluate import evaluate
from dagr_lite.synth.dvs import preset
from dagr_lite.synth.stub import STUB_DVS_MODEL, STUB_SPLITS, STUB_UPSAMPLE, HandScene, stub_root
from dagr_lite.synth.video import emulate_video, to_uint8

CONF = Path(__file__).resolve().parents[1] / "conf"


class Upsampled:
    """A frame source (:mod:`dagr_lite.synth.video`) seen by a camera of ``factor`` times its resolution."""

    def __init__(self, scene: HandScene, factor: int):
        self.scene, self.factor = scene, factor
        self.height, self.width = scene.height * factor, scene.width * factor
        self.num_frames, self.fps = scene.num_frames, scene.fps

    def _up(self, image: np.ndarray) -> np.ndarray:
        return np.clip(nd_zoom(image, (self.factor, self.factor, 1), order=1, grid_mode=True, mode="nearest"), 0, 255)

    def frame(self, k: int) -> np.ndarray:
        return self._up(self.scene.frame(k))

    def between(self, k: int, alpha: float) -> np.ndarray:
        return self._up(self.scene.between(k, alpha))


def split_videos(split: str) -> list[tuple[int, str]]:
    """``(index, name)`` of the stub's videos of ``split`` (the stub numbers its videos in split order)."""
    jobs = [s for s, count in STUB_SPLITS.items() for _ in range(count)]
    return [(i, f"stub_{i:03d}") for i, s in enumerate(jobs) if s == split]


def write_camera(root: Path, split: str, factor: int) -> None:
    labels = {}
    for index, video in split_videos(split):
        camera = Upsampled(HandScene(index), factor)
        with VideoWriter(root, split, video, num_frames=camera.num_frames, height=camera.height,
                         width=camera.width) as writer:
            emulate_video(camera, writer, params=preset(STUB_DVS_MODEL), upsample=STUB_UPSAMPLE, seed=index)
        labels[video] = {k: camera.scene.boxes(k) * factor for k in range(camera.num_frames)}
        print(f"{root / split / video}: {camera.width}x{camera.height}", flush=True)
    write_labels(root, labels)


def write_binned(camera_root: Path, root: Path, split: str, factor: int) -> None:
    labels = {}
    for _, video in split_videos(split):
        recording = open_recording(camera_root / split / "events" / f"{video}.h5")
        sensor = Sensor(recording.size, scale=factor)
        frames = list(recording.frames())
        width, height = sensor.output_size
        with VideoWriter(root, split, video, num_frames=len(frames), height=height, width=width) as writer:
            for chunk in recording.events():
                binned = sensor.events(chunk)
                writer.add_events(binned["x"], binned["y"], binned["t"], binned["p"])
            for _, image in frames:
                writer.add_frame(to_uint8(sensor.frame(image)))
        labels[video] = {k: HandScene(int(video[-3:])).boxes(k) for k in range(len(frames))}
    write_labels(root, labels)


def score(ckpt: str, root: Path | None, split: str, model_size: str, run_dir: Path) -> dict:
    overrides = [f"ckpt={ckpt}", f"split={split}", f"model_size={model_size}", f"run_dir={run_dir}"]
    overrides += [] if root is None else ["dataset=custom", f"dataset.root={root}"]
    with initialize_config_dir(str(CONF), version_base=None):
        cfg = compose("evaluate", overrides=overrides)
    return evaluate(cfg)["metrics"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True, help="a checkpoint trained on the stub (320x180)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--out", default="runs/model_size", help="where the camera datasets go")
    parser.add_argument("--factor", type=int, default=2)
    args = parser.parse_args()
    out = Path(args.out)
    camera, binned = out / f"camera_x{args.factor}", out / f"binned_x{args.factor}"
    if not (camera / "bounding_boxes.json").exists():
        write_camera(camera, args.split, args.factor)
    if not (binned / "bounding_boxes.json").exists():
        write_binned(camera, binned, args.split, args.factor)
    stub_root()
    rows = [("stub split (reference)", None, "checkpoint"),
            (f"sensor.scale={args.factor} (binned)", binned, "checkpoint"),
            ("sensor.model_size=sensor", camera, "data")]
    results = [(name, score(args.ckpt, root, args.split, size, out / f"eval_{i}"))
               for i, (name, root, size) in enumerate(rows)]
    print(f"\n{args.ckpt}, {args.split} split, camera {args.factor}x the model's 320x180")
    print(f"{'input':<30}{'mAP':>8}{'AP50':>8}")
    for name, metrics in results:
        print(f"{name:<30}{metrics['mAP']:>8.3f}{metrics['AP50']:>8.3f}")


if __name__ == "__main__":
    main()
