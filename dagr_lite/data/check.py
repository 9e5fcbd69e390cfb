"""Validate a dataset in the EventEgoHands layout: ``python -m dagr_lite.data.check ROOT``.

Walks every split present and reports each problem with its file and key: missing keys,
unequal lengths, unsorted ``t``, polarities outside {0, 1}, ``timeidx`` fitting neither
frame-time convention, frames missing, unreadable or of the wrong size, boxes outside the image
or of non-positive size, and labels for frames or videos that do not exist. Names the
frame-time convention (``round`` or ``truncate``, see :mod:`dagr_lite.data.format`) each event
file follows. Exits with status 1 when anything is wrong. Event arrays are streamed in blocks,
so files of any size are checked in bounded memory.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from dagr_lite.data import format as fmt
from dagr_lite.data.errors import DatasetFormatError, Problem
from dagr_lite.data.events import fits_neither_message, header_problems, open_h5, polarity_problem
from dagr_lite.data.frames import frame_header_problems, jpeg_size, list_frames, read_frame
from dagr_lite.data.labels import box_problems, list_videos, load_labels_json, parse_boxes, read_labels
from dagr_lite.progress import progress_bar

BLOCK_EVENTS = 1 << 22


def check_events_file(path: Path, *, num_frames: int | None, width: int | None, height: int | None,
                      fps: float = fmt.DEFAULT_FPS) -> tuple[list[Problem], str | None]:
    """Full check of one event file: the header checks, then every event in blocks.

    Returns the problems and the frame-time convention found (None when ``timeidx`` could not
    be checked or fits neither); ``"round (truncate fits too)"`` when no entry tells them apart.
    """
    try:
        h5 = open_h5(path)
    except DatasetFormatError as err:
        return err.problems, None
    with h5:
        try:
            problems = [Problem(path, key, msg) for key, msg in header_problems(h5, num_frames, fps)]
        except OSError as err:
            return [Problem(path, "", f"cannot read the file's index ({err})")], None
        if not _readable_in_blocks(h5):
            return problems, None
        try:
            reported = {p.key for p in problems}  # keys the header checks found wrong already
            block_problems, convention = _check_event_blocks(h5, path, width=width, height=height, fps=fps,
                                                             reported=reported)
            problems += block_problems
        except OSError as err:
            problems.append(Problem(path, "", f"cannot read the events ({err})"))
            convention = None
    return problems, convention


def _readable_in_blocks(h5) -> bool:
    """Whether the arrays exist as 1-D integer datasets of one non-zero length."""
    keys = (*fmt.EVENT_KEYS, fmt.KEY_TIMEIDX)
    if not all(key in h5 and getattr(h5[key], "ndim", 0) == 1 and np.issubdtype(h5[key].dtype, np.integer)
               for key in keys):
        return False
    return len({h5[key].shape[0] for key in fmt.EVENT_KEYS}) == 1 and h5[fmt.KEY_T].shape[0] > 0


def _check_event_blocks(h5, path: Path, *, width: int | None, height: int | None, fps: float,
                        reported: set[str]) -> tuple[list[Problem], str | None]:
    """Sortedness, coordinate and polarity ranges and ``timeidx`` against ``t``, block by block.

    Keys in ``reported`` are not reported again. Returns the problems and the convention
    ``timeidx`` follows (None when not checked or none fits).
    """
    problems = []
    n = h5[fmt.KEY_T].shape[0]
    timeidx = h5[fmt.KEY_TIMEIDX][()].astype(np.int64)
    frame_times = {c: fmt.frame_time_us(np.arange(len(timeidx)), fps, c) for c in fmt.FRAME_TIME_CONVENTIONS}
    counted = {c: np.zeros(len(timeidx), dtype=np.int64) for c in fmt.FRAME_TIME_CONVENTIONS}
    last_t, sorted_ok, reported = None, True, set(reported)
    for start in range(0, n, BLOCK_EVENTS):
        stop = min(n, start + BLOCK_EVENTS)
        t = h5[fmt.KEY_T][start:stop].astype(np.int64)
        if sorted_ok:
            down = np.flatnonzero(t[1:] < t[:-1])
            if last_t is not None and t[0] < last_t:
                problems.append(Problem(path, fmt.KEY_T, f"not sorted ascending at index {start}"))
                sorted_ok = False
            elif len(down):
                problems.append(Problem(path, fmt.KEY_T, f"not sorted ascending at index {start + down[0] + 1}"))
                sorted_ok = False
            for c in fmt.FRAME_TIME_CONVENTIONS:
                counted[c] += np.searchsorted(t, frame_times[c], side="left")
        last_t = t[-1]
        problems += _value_problems(h5, path, start, stop, width=width, height=height, reported=reported)
    if not sorted_ok or fmt.KEY_TIMEIDX in reported:
        return problems, None
    timeidx_problem, convention = _timeidx_against_counts(path, timeidx, counted, frame_times)
    return problems + timeidx_problem, convention


def _value_problems(h5, path: Path, start: int, stop: int, *, width: int | None, height: int | None,
                    reported: set) -> list[Problem]:
    """Coordinates and polarities of events ``[start, stop)``; each key is reported once (``reported``)."""
    problems = []
    for key, size in ((fmt.KEY_X, width), (fmt.KEY_Y, height)):
        a = h5[key][start:stop].astype(np.int64)
        if key not in reported and (a.min() < 0 or (size is not None and a.max() >= size)):
            problems.append(Problem(path, key, f"values must lie in [0, {size}), found "
                                               f"[{a.min()}, {a.max()}] in events {start}..{stop - 1}"))
            reported.add(key)
    if fmt.KEY_P not in reported:
        message = polarity_problem(h5[fmt.KEY_P][start:stop], start)
        if message is not None:
            problems.append(Problem(path, fmt.KEY_P, message))
            reported.add(fmt.KEY_P)
    return problems


def _timeidx_against_counts(path: Path, timeidx: np.ndarray, counted: dict[str, np.ndarray],
                            frame_times: dict[str, np.ndarray]) -> tuple[list[Problem], str | None]:
    """The convention whose counts equal every ``timeidx`` entry, or the problem when none does."""
    wrong = {c: np.flatnonzero(counted[c] != timeidx) for c in fmt.FRAME_TIME_CONVENTIONS}
    fitting = [c for c in fmt.FRAME_TIME_CONVENTIONS if not len(wrong[c])]
    if fitting:
        others = " (" + ", ".join(f"{c} fits too" for c in fitting[1:]) + ")" if len(fitting) > 1 else ""
        return [], fitting[0] + others
    first_wrong = {c: int(wrong[c][0]) for c in fmt.FRAME_TIME_CONVENTIONS}
    k = max(first_wrong.values())  # entries before k fit one convention or the other, entry k neither
    expected = {c: (int(counted[c][k]), int(frame_times[c][k])) for c in fmt.FRAME_TIME_CONVENTIONS}
    counts = ", ".join(f"{len(wrong[c])} under {c}" for c in fmt.FRAME_TIME_CONVENTIONS)
    message = fits_neither_message(k, int(timeidx[k]), expected, first_wrong)
    return [Problem(path, fmt.KEY_TIMEIDX, f"{message}; entries disagreeing with events/t: {counts}")], None


def check_frames(directory: Path, *, num_frames: int | None, expected_hw: tuple[int, int] | None,
                 decode: bool) -> tuple[list[Problem], tuple[int, int] | None, int]:
    """Frames of one video: names contiguous from 0, one per ``timeidx`` entry, all the same size.

    Returns the problems, the frame size found and the number of frames.
    """
    try:
        frames = list_frames(directory)
    except DatasetFormatError as err:
        return err.problems, None, 0
    problems = []
    count = len(frames)
    expected = set(range(num_frames if num_frames is not None else (max(frames) + 1 if frames else 0)))
    missing = sorted(expected - set(frames))
    if missing:
        problems.append(Problem(directory, "", f"{len(missing)} frames missing, first "
                                               f"{fmt.frame_name(missing[0])}"))
    extra = sorted(set(frames) - expected)
    if extra:
        problems.append(Problem(directory, "", f"{len(extra)} frames beyond the {num_frames} frames of timeidx, "
                                               f"first {fmt.frame_name(extra[0])}"))
    read_size = _decoded_size if decode else jpeg_size
    size_problems, size = frame_header_problems({k: directory / name for k, name in frames.items()}, expected_hw,
                                                "as configured" if expected_hw is not None else "",
                                                read_size=read_size)
    return problems + size_problems, size, count


def _decoded_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` of a frame after reading its JPEG header and decoding it whole."""
    jpeg_size(path)
    return read_frame(path).shape[:2]


def check_dataset(root: Path | str, *, fps: float = fmt.DEFAULT_FPS, decode_frames: bool = False,
                  expected_hw: tuple[int, int] | None = None, progress: bool = False,
                  conventions: dict[Path, str | None] | None = None) -> list[Problem]:
    """Every problem found in the dataset at ``root`` (an empty list when it is valid).

    ``conventions``, when given, receives the frame-time convention of each event file checked
    (None where ``timeidx`` could not be checked or fits neither).
    """
    root = Path(root)
    if not root.is_dir():
        return [Problem(root, "", "dataset folder is missing")]
    splits = [s for s in fmt.SPLITS if (root / s).is_dir()]
    if not splits:
        return [Problem(root, "", f"no split folder found (expected one or more of {', '.join(fmt.SPLITS)})")]
    problems: list[Problem] = []
    videos: dict[str, tuple[int, tuple[int, int] | None]] = {}  # video -> (frame count, (H, W))
    jobs = []
    for split in splits:
        try:
            names = list_videos(root, split)
        except DatasetFormatError as err:
            problems += err.problems
            events_dir = root / split / fmt.EVENTS_DIR
            names = sorted(p.name[: -len(fmt.EVENTS_SUFFIX)] for p in events_dir.glob("*" + fmt.EVENTS_SUFFIX)
                           if fmt.frames_dir(root, split, p.name[: -len(fmt.EVENTS_SUFFIX)]).is_dir())
        jobs += [(split, name) for name in names]
    for split, video in progress_bar(jobs, desc="checking videos", disable=not progress):
        if video in videos:
            problems.append(Problem(fmt.events_path(root, split, video), "", "video name appears in two splits"))
        num_frames = None
        try:
            with open_h5(fmt.events_path(root, split, video)) as h5:
                if fmt.KEY_TIMEIDX in h5 and h5[fmt.KEY_TIMEIDX].ndim == 1:
                    num_frames = h5[fmt.KEY_TIMEIDX].shape[0]
        except DatasetFormatError:
            pass
        frame_problems, hw, count = check_frames(fmt.frames_dir(root, split, video), num_frames=num_frames,
                                                 expected_hw=expected_hw, decode=decode_frames)
        problems += frame_problems
        height, width = hw if hw is not None else (None, None)
        events_path = fmt.events_path(root, split, video)
        event_problems, convention = check_events_file(events_path, num_frames=count, width=width,
                                                       height=height, fps=fps)
        problems += event_problems
        if conventions is not None:
            conventions[events_path] = convention
        videos[video] = (count, hw)
    problems += size_problems(root, videos)
    problems += check_labels(root, videos)
    return problems


def size_problems(root: Path, videos: dict[str, tuple[int, tuple[int, int] | None]]) -> list[Problem]:
    """One problem when the videos' frames are of several sizes (a model takes one)."""
    by_size: dict[tuple[int, int], list[str]] = {}
    for video, (_, hw) in videos.items():
        if hw is not None:
            by_size.setdefault(hw, []).append(video)
    if len(by_size) < 2:
        return []
    sizes = ", ".join(f"{w}x{h} ({', '.join(sorted(names))})" for (h, w), names in
                      sorted(by_size.items(), key=lambda item: -len(item[1])))
    return [Problem(root, "", f"frames of {len(by_size)} sizes (WxH): {sizes}; a dataset's videos share one "
                              "frame size")]


def check_labels(root: Path, videos: dict[str, tuple[int, tuple[int, int] | None]]) -> list[Problem]:
    """Problems of ``bounding_boxes.json`` against the videos found (name -> frame count, size)."""
    path = fmt.labels_path(root)
    try:
        raw = load_labels_json(root)
    except DatasetFormatError as err:
        return err.problems
    problems = []
    for key, value in raw.items():
        parsed = fmt.parse_label_key(key)
        if parsed is None:
            problems.append(Problem(path, key, "key is not of the form <video>_frame_<k>"))
            continue
        video, k = parsed
        if video not in videos:
            problems.append(Problem(path, key, f"label for video {video!r}, which no split holds"))
            continue
        count, hw = videos[video]
        if k >= count:
            problems.append(Problem(path, key, f"label for frame {k}, but the video has {count} frames"))
        try:
            boxes = parse_boxes(value)
        except ValueError as err:
            problems.append(Problem(path, key, str(err)))
            continue
        if hw is not None:
            problems += [Problem(path, key, msg) for msg in box_problems(boxes, *hw)]
    return problems


def convention_lines(conventions: dict[Path, str | None]) -> list[str]:
    """What ``check`` prints of the files' frame-time conventions: one line counting each (saying that a
    mix is read file by file where there is one), then a line for each file whose ``timeidx`` follows
    another convention than this package's own (``round``); one that could not be told is among the problems."""
    if not conventions:
        return []
    counts: dict[str, int] = {}
    for convention in conventions.values():
        name = convention.split(" ")[0] if convention else "not determined"
        counts[name] = counts.get(name, 0) + 1
    known = {"round": "round(1e6 * k / fps), as this package writes", "truncate": "int(1e6 * k / fps), the reference "
             "loader's", "not determined": "timeidx has a problem listed below"}
    order = [*known, *sorted(set(counts) - set(known))]
    parts = [f"{name} in {counts[name]} file{'s' * (counts[name] > 1)} ({known.get(name, name)})"
             for name in order if name in counts]
    mixed = len(counts) - ("not determined" in counts) > 1
    lines = [f"frame times (timeidx): {'; '.join(parts)}"
             + (". Each file is read in its own convention, so a mix is no problem" if mixed else "")]
    lines += [f"{path}: frame times (timeidx): {convention}"  # an undetermined file's problem is listed with the rest
              for path, convention in conventions.items() if convention is not None and not convention.startswith("round")]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.data.check", description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="dataset folder holding train/, valid/, test/ and bounding_boxes.json")
    parser.add_argument("--fps", type=float, default=fmt.DEFAULT_FPS, help="frame rate defining frame times")
    parser.add_argument("--decode-frames", action="store_true",
                        help="decode every JPEG fully (slower; finds corrupt image data, not only bad headers)")
    parser.add_argument("--max-report", type=int, default=200, help="print at most this many problems")
    args = parser.parse_args(argv)
    conventions: dict[Path, str | None] = {}
    problems = check_dataset(args.root, fps=args.fps, decode_frames=args.decode_frames, progress=True,
                             conventions=conventions)
    for line in convention_lines(conventions):
        print(line)
    for problem in problems[: args.max_report]:
        print(problem)
    if len(problems) > args.max_report:
        print(f"... and {len(problems) - args.max_report} more")
    if problems:
        print(f"{args.root}: {len(problems)} problem(s) found", file=sys.stderr)
        return 1
    print(f"{args.root}: no problems found")
    note = training_note(args.root)
    if note:
        print(note)
    return 0


def training_note(root: Path) -> str | None:
    """What a dataset without problems still lacks before ``train.py`` and ``evaluate.py`` can use it
    (a split folder, labelled frames), in one line; None: nothing."""
    absent = [split for split in fmt.SPLITS if not (Path(root) / split).is_dir()]
    labelled = sum(len(frames) for frames in read_labels(root).values()) if fmt.labels_path(root).is_file() else 0
    lacks = ([f"no {' or '.join(absent)} split"] if absent else []) + (["no labelled frame"] if not labelled else [])
    if not lacks:
        return None
    return (f"note: {'; '.join(lacks)}: train.py reads train and valid, evaluate.py test (by default), each with "
            "labels (python -m dagr_lite.synth.build --splits/--labels, python -m dagr_lite.apps.label)")


if __name__ == "__main__":
    sys.exit(main())
