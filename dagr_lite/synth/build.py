"""Build a dataset in the EventEgoHands layout from video frames: ``python -m dagr_lite.synth.build``.

From EgoHands (frame folders of the 48 videos plus ``metadata.mat``)::

    python -m dagr_lite.synth.build --egohands metadata.mat --frames FRAMES --out ROOT --version v6

From video files (decoded by PyAV as they are emulated; the frame rate is the files' own unless
``--fps`` is given)::

    python -m dagr_lite.synth.build --video a.mp4 b.mov [DIR_OF_VIDEOS ...] --out ROOT --version v6 \\
        [--labels bounding_boxes.json]

From any folder of videos laid out as ``<video>/frame_<k>.jpg`` (optionally with labels in the
release format, boxes in pixels of those frames)::

    python -m dagr_lite.synth.build --frames DIR --out ROOT --preset clean --upsample 41 --scale 2 \\
        [--labels bounding_boxes.json] [--splits splits.json] [--seed 0]

Each video is emulated and written in turn (progress per video); a finished video (its events
file exists) is not redone, so an interrupted build resumes where it stopped. The parameters
of a build are kept in ``build_info.json``; resuming with different ones is refused.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.check import training_note
from dagr_lite.data.frames import frame_size
from dagr_lite.data.labels import read_json_object, read_label_file
from dagr_lite.data.writer import VideoWriter, write_labels, write_text_atomically
from dagr_lite.progress import progress_bar
from dagr_lite.synth.dvs import PRESETS, DVSParams, preset
from dagr_lite.synth.egohands import (EGOHANDS_HEIGHT, EGOHANDS_WIDTH, Labeller, default_split, interpolate_labels,
                                      load_metadata)
from dagr_lite.synth.video import (VIDEO_SUFFIXES, FolderSource, choose_dvs_model, emulate_video, frame_number,
                                   list_frame_files, open_source, scale_boxes, video_fps)

# The EventEgoHands versions (paper, Table I): upsampling factor, scale, DVS model.
VERSIONS = {
    "v1": {"upsample": 1, "scale": 1, "dvs_model": "clean"},
    "v2": {"upsample": 1, "scale": 4, "dvs_model": "clean"},
    "v3": {"upsample": 1, "scale": 2, "dvs_model": "clean"},
    "v4": {"upsample": 41, "scale": 2, "dvs_model": "clean"},
    "v5": {"upsample": 41, "scale": 2, "dvs_model": "noisy"},
    "v6": {"upsample": 41, "scale": 2, "dvs_model": "mixed"},
}
DVS_MODELS = (*PRESETS, "mixed")
BUILD_INFO = "build_info.json"
LABEL_SOURCES = "label_sources.json"


@dataclass
class VideoJob:
    """One video to build: its frames, split, and labels (frame -> xywh boxes at source resolution, sources)."""

    name: str
    split: str
    frames: Path
    labels: dict[int, tuple[np.ndarray, list[str]]]


@dataclass(frozen=True)
class BuildSettings:
    dvs_model: str  # clean, noisy or mixed
    upsample: int
    scale: int
    fps: float = fmt.DEFAULT_FPS
    seed: int = 0
    clean_fraction: float = 0.5
    compression: str | None = "blosc"
    dvs_overrides: tuple[tuple[str, float], ...] = ()

    def __post_init__(self):
        if self.dvs_model not in DVS_MODELS:
            raise UserError(f"DVS model must be one of {DVS_MODELS}, got {self.dvs_model!r}")
        if self.upsample < 1 or self.scale < 1:
            raise UserError(f"upsample and scale must be >= 1, got {self.upsample} and {self.scale}")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise UserError(f"--fps must be a positive number of frames per second, got {self.fps}")
        if not 0.0 <= self.clean_fraction <= 1.0:
            raise UserError(f"--clean-fraction must lie in [0, 1], got {self.clean_fraction}")
        self.params("clean")  # unknown or bad overrides fail now, not after the first video

    def params(self, model: str) -> DVSParams:
        return preset(model, **dict(self.dvs_overrides))

    def model_for(self, video: str) -> str:
        if self.dvs_model != "mixed":
            return self.dvs_model
        return choose_dvs_model(video, seed=self.seed, clean_fraction=self.clean_fraction)

    def video_seed(self, video: str) -> int:
        return (self.seed * 1_000_003 + zlib.crc32(video.encode())) % 2**32

    def as_dict(self) -> dict:
        return {"dvs_model": self.dvs_model, "upsample": self.upsample, "scale": self.scale, "fps": self.fps,
                "seed": self.seed, "clean_fraction": self.clean_fraction, "compression": self.compression,
                "dvs_overrides": dict(self.dvs_overrides)}


def _write_json(path: Path, content: dict) -> None:
    write_text_atomically(path, json.dumps(content, indent=1, sort_keys=True))


def _read_json(path: Path, default: dict) -> dict:
    return read_json_object(path) if path.exists() else default


def _drop_video_keys(mapping: dict, video: str) -> dict:
    return {key: value for key, value in mapping.items() if fmt.label_video(key) != video}


def _set_video_labels(out: Path, video: str, boxes: dict[int, np.ndarray], sources: dict[str, list[str]]) -> None:
    """Replace every label and label source of ``video`` (none left over from an earlier attempt)."""
    write_labels(out, {video: boxes}, merge=True)
    all_sources = _drop_video_keys(_read_json(out / LABEL_SOURCES, {}), video)
    all_sources.update(sources)
    _write_json(out / LABEL_SOURCES, all_sources)


def _finished_split(out: Path, video: str) -> str | None:
    return next((split for split in fmt.SPLITS if fmt.events_path(out, split, video).exists()), None)


def _labels_at_scale(job: VideoJob, source: FolderSource, scale: int):
    """The job's labels in pixels of the scaled frames, and the source of each box kept."""
    boxes, sources = {}, {}
    for k, (xywh, origin) in job.labels.items():
        if k >= source.num_frames:
            raise UserError(f"{job.frames}: labels for frame {k}, but the video has {source.num_frames} frames")
        boxes[k], kept = scale_boxes(xywh, scale, source.height, source.width)
        sources[fmt.label_key(job.name, k)] = [o for o, keep in zip(origin, kept) if keep]
    return boxes, sources


def build(jobs: list[VideoJob], out: Path | str, settings: BuildSettings, *, progress: bool = True) -> dict:
    """Build every job's video into ``out``; returns the build summary also written to ``build_info.json``.

    Settings are recorded before the first video; a later run with other settings, or with a
    finished video assigned to another split, is refused. A video that gives no events (a
    static scene, a single frame) cannot be a dataset video: it is left out with a warning.
    """
    out = Path(out)
    info = _start_build(jobs, out, settings)
    for job in progress_bar(jobs, desc="videos", unit="video", disable=not progress):
        if _finished_split(out, job.name) is not None:
            if job.name not in info["videos"]:  # finished, but the run stopped before recording it
                info["videos"][job.name] = {"split": job.split, "dvs_model": settings.model_for(job.name)}
                _write_json(out / BUILD_INFO, info)
            continue
        _build_video(job, out, settings, info, progress=progress)
        _write_json(out / BUILD_INFO, info)
    return info


def _start_build(jobs: list[VideoJob], out: Path, settings: BuildSettings) -> dict:
    """Refuse repeated names, moved videos and other settings; record the settings; returns the build info."""
    names = [job.name for job in jobs]
    if len(set(names)) != len(names):
        raise UserError(f"video names must be unique, got {sorted(n for n in set(names) if names.count(n) > 1)}")
    for job in jobs:
        done = _finished_split(out, job.name)
        if done is not None and done != job.split:
            raise UserError(f"{fmt.events_path(out, done, job.name)}: video {job.name} was built into {done}, "
                             f"but is now assigned to {job.split}; keep the split or choose a new --out")
    info_path = out / BUILD_INFO
    foreign = [p.name for p in (*(out / split for split in fmt.SPLITS), fmt.labels_path(out)) if p.exists()]
    if foreign and not info_path.exists():
        raise UserError(f"{out}: holds a dataset this builder did not make ({', '.join(foreign)}, no {BUILD_INFO}); "
                         "choose a new --out")
    info = _read_json(info_path, {"settings": settings.as_dict(), "videos": {}, "skipped": {}})
    if info["settings"] != settings.as_dict():
        raise UserError(f"{info_path}: {out} was built with settings {info['settings']}, not "
                         f"{settings.as_dict()}; resume with the same settings or choose a new --out")
    out.mkdir(parents=True, exist_ok=True)
    _write_json(info_path, info)
    if not fmt.labels_path(out).exists():
        write_labels(out, {})
    return info


def _build_video(job: VideoJob, out: Path, settings: BuildSettings, info: dict, *, progress: bool) -> None:
    """Emulate and write one video, recording it in ``info`` as built or skipped (with a warning)."""
    source = open_source(job.frames, scale=settings.scale)
    try:
        _emulate_job(job, source, out, settings, info, progress=progress)
    finally:
        if hasattr(source, "close"):
            source.close()


def _emulate_job(job: VideoJob, source, out: Path, settings: BuildSettings, info: dict, *, progress: bool) -> None:
    if source.num_frames < 2:
        warnings.warn(f"{job.frames}: {source.num_frames} frame(s); a video needs two to give events, skipped")
        info["skipped"][job.name] = "fewer than two frames"
        return
    model = settings.model_for(job.name)
    boxes, sources = _labels_at_scale(job, source, settings.scale)
    # Labels go first: a video counts as finished only once its events file exists.
    _set_video_labels(out, job.name, boxes, sources)
    writer = VideoWriter(out, job.split, job.name, num_frames=source.num_frames, height=source.height,
                         width=source.width, fps=settings.fps, compression=settings.compression)
    try:
        with progress_bar(total=source.num_frames - 1, desc=job.name, unit="frame", leave=False,
                          disable=not progress) as bar:
            count = emulate_video(source, writer, params=settings.params(model), upsample=settings.upsample,
                                  fps=settings.fps, seed=settings.video_seed(job.name), progress=bar.update)
        if count == 0:
            writer.abort()
            shutil.rmtree(writer.folder, ignore_errors=True)
            _set_video_labels(out, job.name, {}, {})
            warnings.warn(f"{job.frames}: the emulator gave no events (a static video?); skipped")
            info["skipped"][job.name] = "no events"
            return
        writer.close()
    except BaseException:
        writer.abort()
        raise
    info["videos"][job.name] = {"split": job.split, "dvs_model": model, "frames": source.num_frames,
                                "events": count, "labelled_frames": len(boxes)}


# Jobs from the two kinds of input.

def _read_splits(path: Path | None, videos: list[str], default: dict[str, list[str]]) -> dict[str, str]:
    """video -> split, from a JSON file ``{"train": [...], "valid": [...], "test": [...]}`` or the default."""
    if path is None:
        mapping = default
    else:
        mapping = read_json_object(path, "split file", 'a JSON object {"train": [...], "valid": [...], "test": [...]}')
        if set(mapping) - set(fmt.SPLITS):
            raise DatasetFormatError.at(path, f"expected an object with keys among {fmt.SPLITS}")
    assignment = {}
    for split, names in mapping.items():
        for name in names:
            if name in assignment:
                raise DatasetFormatError.at(path or "splits", f"video {name!r} is in two splits")
            assignment[name] = split
    unknown = sorted(set(assignment) - set(videos))
    if unknown:
        raise DatasetFormatError.at(path or "splits", f"videos {unknown} have no frame folder")
    return assignment


def _given_labels(labels: Path | None, videos: list[str],
                  unknown: str) -> dict[str, dict[int, tuple[np.ndarray, list[str]]]]:
    """Each video's labels from a release-format file, all marked ``given``; a key naming another
    video is an error (``unknown`` says what it names none of)."""
    per_video: dict[str, dict[int, tuple[np.ndarray, list[str]]]] = {v: {} for v in videos}
    if labels is not None:
        for video, frame_boxes in read_label_file(labels).items():
            if video not in per_video:
                raise DatasetFormatError.at(labels, f"key names {unknown}",
                                            key=fmt.label_key(video, min(frame_boxes)))
            per_video[video] = {k: (boxes, ["given"] * len(boxes)) for k, boxes in frame_boxes.items()}
    return per_video


def folder_jobs(frames: Path, *, labels: Path | None = None, splits: Path | None = None) -> list[VideoJob]:
    """Jobs for a folder of ``<video>/`` frame folders; labels in the release format, keyed by frame order."""
    frames = Path(frames)
    if not frames.is_dir():
        raise DatasetFormatError.at(frames, "frames folder is missing")
    videos = sorted(p.name for p in frames.iterdir() if p.is_dir())
    if not videos:
        raise DatasetFormatError.at(frames, "holds no video folders (expected <video>/frame_<k>.jpg)")
    per_video = _given_labels(labels, videos, "no video of the frames folder")
    assignment = _read_splits(splits, videos, {"train": videos})
    return [VideoJob(v, assignment[v], frames / v, per_video[v]) for v in videos if v in assignment]


def video_jobs(paths: list[Path], *, labels: Path | None = None, splits: Path | None = None) -> list[VideoJob]:
    """Jobs for video files (or folders of them), one video each, named by the file's stem; labels
    in the release format, keyed by ``<stem>_frame_<k>``."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(f for f in path.iterdir() if f.suffix.lower() in VIDEO_SUFFIXES)
            if not found:
                raise DatasetFormatError.at(path, f"holds no video files ({', '.join(VIDEO_SUFFIXES)})")
            files += found
        elif path.is_file():
            if path.suffix.lower() not in VIDEO_SUFFIXES:
                raise DatasetFormatError.at(path, f"is not a video file the builder reads (by its suffix: "
                                                  f"{', '.join(VIDEO_SUFFIXES)}); a folder of frames goes to --frames")
            files.append(path)
        else:
            raise DatasetFormatError.at(path, "video file is missing")
    names = [f.stem for f in files]
    if len(set(names)) != len(names):
        repeated = sorted(n for n in set(names) if names.count(n) > 1)
        raise UserError(f"video files must have distinct names, got {repeated}")
    per_video = _given_labels(labels, names, "no video given")
    assignment = _read_splits(splits, names, {"train": names})
    return [VideoJob(n, assignment[n], f, per_video[n]) for n, f in zip(names, files) if n in assignment]


def container_fps(jobs: list[VideoJob]) -> float:
    """The frame rate the video files state, which must be one for the whole dataset."""
    rates = {job.name: video_fps(job.frames) for job in jobs}
    if len({round(r, 6) for r in rates.values()}) > 1:
        raise UserError(f"the videos state different frame rates {rates}; a dataset has one: give --fps")
    return next(iter(rates.values()))


def egohands_jobs(metadata: Path, frames: Path, *, splits: Path | None = None, labeller: Labeller = interpolate_labels,
                  split_seed: int = 0) -> list[VideoJob]:
    """Jobs for EgoHands: ``frames/<video_id>/`` holds every frame of a video (frame_0001.jpg, ...)."""
    annotations = load_metadata(metadata)
    frames = Path(frames)
    missing = [v for v in annotations if not (frames / v).is_dir()]
    if missing:
        raise DatasetFormatError.at(frames, f"no frame folder for videos {missing}")
    videos = sorted(annotations)
    default = default_split(videos, seed=split_seed) if len(videos) == 48 else {"train": videos}
    assignment = _read_splits(splits, videos, default)
    jobs = []
    for video in videos:
        if video not in assignment:
            continue
        folder = frames / video
        files = list_frame_files(folder)
        # metadata frame_num N is the file numbered N: folders must count from 1, as EgoHands' do.
        if frame_number(files[0]) != 1:
            raise DatasetFormatError.at(folder, f"frames are numbered from {frame_number(files[0])}; EgoHands "
                                                "frame folders count from 1 (frame_0001.jpg), as frame_num does")
        size = frame_size(files[0])
        if size != (EGOHANDS_HEIGHT, EGOHANDS_WIDTH):
            raise DatasetFormatError.at(files[0], f"frame is {size[1]}x{size[0]} (WxH); EgoHands polygons are in "
                                                  f"{EGOHANDS_WIDTH}x{EGOHANDS_HEIGHT} frames (use --scale to shrink)")
        num_frames = len(files)
        jobs.append(VideoJob(video, assignment[video], folder, labeller(annotations[video], num_frames)))
    return jobs


def _parse_overrides(items: list[str]) -> tuple[tuple[str, float], ...]:
    overrides = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise UserError(f"--dvs takes name=value, got {item!r}")
        try:
            overrides.append((name, float(value)))
        except ValueError as err:
            raise UserError(f"--dvs {name}: {value!r} is not a number") from err
    return tuple(overrides)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.synth.build", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--frames", type=Path, help="folder holding one frame folder per video")
    source.add_argument("--video", type=Path, nargs="+", help="video files (MP4, AVI, MOV, ...) or folders of them")
    parser.add_argument("--out", type=Path, required=True, help="dataset folder to write (resumed if it exists)")
    parser.add_argument("--egohands", type=Path, help="EgoHands metadata.mat: labels from its polygons")
    parser.add_argument("--labels", type=Path, help="labels in the release format (bounding_boxes.json)")
    parser.add_argument("--version", choices=sorted(VERSIONS), help="an EventEgoHands version (sets the next three)")
    parser.add_argument("--preset", choices=DVS_MODELS, help="DVS model: clean, noisy or mixed (per video)")
    parser.add_argument("--upsample", type=int, help="emulator steps per frame interval (U - 1 in-between frames)")
    parser.add_argument("--scale", type=int, help="downscaling factor of frames and boxes (1, 2, 4, ...)")
    parser.add_argument("--splits", type=Path, help='JSON {"train": [...], "valid": [...], "test": [...]}')
    parser.add_argument("--fps", type=float,
                        help=f"frame rate (default: the video files' own, else {fmt.DEFAULT_FPS:g})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--clean-fraction", type=float, default=0.5, help="share of clean videos with --preset mixed")
    parser.add_argument("--compression", choices=["blosc", "gzip", "none"], default="blosc")
    parser.add_argument("--dvs", action="append", default=[], metavar="NAME=VALUE",
                        help="override a DVS parameter, e.g. --dvs sigma_threshold=0.05 (repeatable)")
    args = parser.parse_args(argv)
    chosen = dict(VERSIONS[args.version]) if args.version else {}
    given = {"dvs_model": ("--preset", args.preset), "upsample": ("--upsample", args.upsample),
             "scale": ("--scale", args.scale)}  # each setting's flag and value
    chosen.update({key: value for key, (_, value) in given.items() if value is not None})
    missing = [flag for key, (flag, _) in given.items() if key not in chosen]
    if missing:
        parser.error(f"give --version or all of --preset, --upsample, --scale (missing: {', '.join(missing)})")
    if args.egohands and args.labels:
        parser.error("--egohands and --labels are two sources of labels; give one")
    if args.egohands and args.video:
        parser.error("--egohands reads EgoHands' frame folders: give --frames")
    try:
        if args.egohands:
            jobs = egohands_jobs(args.egohands, args.frames, splits=args.splits)
        elif args.video:
            jobs = video_jobs(args.video, labels=args.labels, splits=args.splits)
        else:
            jobs = folder_jobs(args.frames, labels=args.labels, splits=args.splits)
        fps = args.fps or (container_fps(jobs) if args.video and jobs else fmt.DEFAULT_FPS)
        settings = BuildSettings(dvs_model=chosen["dvs_model"], upsample=chosen["upsample"], scale=chosen["scale"],
                                 fps=fps, seed=args.seed, clean_fraction=args.clean_fraction,
                                 compression=None if args.compression == "none" else args.compression,
                                 dvs_overrides=_parse_overrides(args.dvs))
        info = build(jobs, args.out, settings)
    except (ValueError, DatasetFormatError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    total = sum(v["events"] for v in info["videos"].values())
    count = len(info["videos"])
    print(f"{args.out}: {count} video{'' if count == 1 else 's'}, {total:,} events, {settings.fps:g} fps")
    note = training_note(args.out)
    if note:
        print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
