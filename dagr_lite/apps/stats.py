"""Statistics and pictures of a dataset: ``python -m dagr_lite.apps.stats ROOT --out DIR [--videos ...]``.

Writes ``DIR/stats.json``: per video and per split the events, duration, mean and peak event
rate (over 10 ms bins), ON fraction, frames, labelled frames, boxes and boxes per labelled
frame, a histogram of box sizes (square root of the area, in pixels) and, per split, how fast the
labels go stale: the AP50 and mAP of frame ``k - a``'s boxes taken as the answer for frame ``k``
(every box score 1, on the frames the sweep scores, ``k >= max(ages)``), what a detector that
reads an image ``a`` frames old and nothing since could reach at best. Event arrays are
read a second at a time, so files of any size take bounded memory. Per video (at the middle
labelled frame ``k`` unless ``--frame`` says) it draws:

- ``event_rate_<video>.png``: ON and OFF events per second over time (10 ms bins);
- ``event_frame_<video>_<k>.png``: the 33 ms of events before frame ``k``;
- ``overlay_<video>_<k>.png``: those events over frame ``k`` with its boxes;
- ``presets_<video>_<k>.png``: the clean and the noisy DVS presets emulated on the video's own
  frames up to ``k``, the last 33 ms of each side by side;

and ``index.html`` shows them all.
"""
from __future__ import annotations

import argparse
import html
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from dagr_lite.errors import UserError
from dagr_lite.apps.cli import user_errors  # noqa: E402
from dagr_lite.apps.event_rate import BIN_US, OFF_COLOUR, ON_COLOUR, rate_picture  # noqa: E402
from dagr_lite.data import format as fmt  # noqa: E402
from dagr_lite.data.events import EventFile
from dagr_lite.data.frames import list_frames, read_frame
from dagr_lite.data.labels import list_videos, read_labels
from dagr_lite.eval.fast_coco import coco_stats
from dagr_lite.progress import progress_bar  # noqa: E402

READ_US = 1_000_000  # events are read this much at a time
WINDOW_US = fmt.DEFAULT_WINDOW_US  # the events drawn before a frame
SIZE_EDGES = [0, 8, 16, 24, 32, 48, 64, 96, 128, 192, 256, 1e9]  # box-size histogram, sqrt(area) in px
STALE_AGES = (1, 2, 3, 5, 7, 10)  # the sweep's image ages, in frames


def video_stats(root: Path, split: str, video: str, labels: dict[int, np.ndarray], fps: float) -> tuple[dict, dict]:
    """The numbers of one video and its per-bin ON / OFF counts (for the event-rate picture)."""
    frames = len(list_frames(fmt.frames_dir(root, split, video)))
    events = EventFile(fmt.events_path(root, split, video), fps=fps, num_frames=frames)
    try:
        end = max(int(events.frame_times[-1]) + int(1e6 / fps), 1)
        bins = int(np.ceil(end / BIN_US))
        on, off = np.zeros(bins, np.int64), np.zeros(bins, np.int64)
        for start in range(0, end, READ_US):
            part = events.window(start, min(start + READ_US, end))
            index = part["t"] // BIN_US
            on += np.bincount(index[part["p"] == 1], minlength=bins)
            off += np.bincount(index[part["p"] == 0], minlength=bins)
        after = events.window(end, 1 << 62)  # past the last frame's interval: counted apart
    finally:
        events.close()
    total = int(on.sum() + off.sum())
    boxes = [b for k, b in labels.items() if k < frames]
    num_boxes = int(sum(len(b) for b in boxes))
    duration = end / 1e6
    return ({"split": split, "events": total, "duration_s": duration, "mean_rate": total / duration,
             "peak_rate": float((on + off).max() / (BIN_US / 1e6)) if bins else 0.0,
             "on_fraction": float(on.sum() / total) if total else None, "frames": frames,
             "labelled_frames": len(boxes), "boxes": num_boxes,
             "boxes_per_labelled_frame": num_boxes / len(boxes) if boxes else None,
             "events_after_last_frame": int(len(after["t"]))},
            {"on": on, "off": off})


def size_histogram(labels: dict[str, dict[int, np.ndarray]], videos: list[str]) -> dict:
    sizes = [np.sqrt(b[:, 2] * b[:, 3]) for v in videos for b in labels.get(v, {}).values() if len(b)]
    sizes = np.concatenate(sizes) if sizes else np.zeros(0)
    counts, _ = np.histogram(sizes, bins=SIZE_EDGES)
    return {"edges_px": [*SIZE_EDGES[:-1], None], "counts": counts.tolist(),  # the last bin is open: null
            "median_px": float(np.median(sizes)) if len(sizes) else None}


def stale_labels(labels: dict[str, dict[int, np.ndarray]], videos: list[str],
                 ages: tuple[int, ...] = STALE_AGES) -> dict[int, dict[str, float]]:
    """Per age ``a``: ``{"frames", "AP50", "mAP"}`` of the boxes of frame ``k - a`` taken as the
    detections (score 1) for frame ``k``, over every labelled ``k >= max(ages)`` whose frame
    ``k - a`` is labelled too (a labelled frame without boxes counts: it says no hand)."""
    out = {}
    for age in ages:
        truth, answers = [], []
        for video in videos:
            frames = labels.get(video, {})
            for k in sorted(frames):
                if k >= max(ages) and k - age in frames:
                    truth.append(np.asarray(frames[k], dtype=np.float64).reshape(-1, 4))
                    answers.append(np.asarray(frames[k - age], dtype=np.float64).reshape(-1, 4))
        if not truth:
            continue
        stats = coco_stats(truth, answers, [np.ones(len(a)) for a in answers])
        out[age] = {"frames": len(truth), "AP50": float(stats[1]), "mAP": float(stats[0])}
    return out


def split_totals(per_video: dict[str, dict]) -> dict[str, dict]:
    out = {}
    for split in fmt.SPLITS:
        rows = [r for r in per_video.values() if r["split"] == split]
        if not rows:
            continue
        events, duration = sum(r["events"] for r in rows), sum(r["duration_s"] for r in rows)
        on = sum(r["events"] * (r["on_fraction"] or 0) for r in rows)
        labelled, boxes = sum(r["labelled_frames"] for r in rows), sum(r["boxes"] for r in rows)
        out[split] = {"videos": len(rows), "events": events, "duration_s": duration, "mean_rate": events / duration,
                      "peak_rate": max(r["peak_rate"] for r in rows), "on_fraction": on / events if events else None,
                      "frames": sum(r["frames"] for r in rows), "labelled_frames": labelled, "boxes": boxes,
                      "boxes_per_labelled_frame": boxes / labelled if labelled else None}
    return out


def event_image(events: dict, height: int, width: int, background: np.ndarray | None = None) -> np.ndarray:
    """ON red and OFF blue pixels (the later event wins) over ``background`` or white."""
    canvas = np.full((height, width, 3), 1.0) if background is None else background.astype(float) / 255 * 0.55
    canvas[events["y"].astype(int), events["x"].astype(int)] = np.where(events["p"][:, None] > 0, ON_COLOUR,
                                                                         OFF_COLOUR)
    return canvas


def frame_pictures(root: Path, split: str, video: str, k: int, boxes: np.ndarray, out: Path, fps: float) -> list[str]:
    """The event-frame, overlay and presets pictures of frame ``k``; returns their file names."""
    frames = len(list_frames(fmt.frames_dir(root, split, video)))
    file = EventFile(fmt.events_path(root, split, video), fps=fps, num_frames=frames)
    try:
        t_k = int(file.frame_times[k])
        events = file.window(t_k - WINDOW_US, t_k)
    finally:
        file.close()
    image = read_frame(fmt.frame_path(root, split, video, k))
    height, width = image.shape[:2]
    names = [f"event_frame_{video}_{k}.png", f"overlay_{video}_{k}.png", f"presets_{video}_{k}.png"]
    title = f"{video}, frame {k}: {len(events['t']):,} events of the {WINDOW_US / 1000:.0f} ms before it"
    for name, background in zip(names[:2], (None, image)):
        fig, ax = plt.subplots(figsize=(8, 8 * height / width + 0.6))
        ax.imshow(event_image(events, height, width, background), interpolation="nearest")
        if background is not None:
            for x, y, w, h in boxes:
                ax.add_patch(plt.Rectangle((x, y), w, h, fill=False, color=(0.1, 0.9, 0.1), lw=1.5))
        boxed = background is not None and len(boxes) > 0  # an unlabelled frame has no boxes to name
        ax.set(title=title + (" over the frame" if background is not None else "") + (", with its boxes" if boxed else ""),
               xlabel="x (px)", ylabel="y (px)")
        _colour_legend(ax, with_box=boxed)
        fig.tight_layout()
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(fig)
    presets_picture(root, split, video, k, fps, out / names[2])
    return names


def _colour_legend(ax, *, with_box: bool) -> None:
    handles = [plt.Line2D([], [], marker="s", ls="", color=ON_COLOUR, label="ON"),
               plt.Line2D([], [], marker="s", ls="", color=OFF_COLOUR, label="OFF")]
    if with_box:
        handles.append(plt.Line2D([], [], color=(0.1, 0.9, 0.1), label="hand box"))
    # Below the picture (clear of the tick labels and the axis label, whatever the axes' height),
    # where it hides nothing.
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), borderaxespad=4.2,
              ncol=len(handles), fontsize=8, frameon=False)


def presets_picture(root: Path, split: str, video: str, k: int, fps: float, path: Path, upsample: int = 6) -> None:
    """The clean and noisy presets emulated on the video's frames ``k - 3 .. k``; the last frame
    interval of each (frames interpolated ``upsample`` times per interval)."""
    from dagr_lite.synth.dvs import DVSEmulator, preset
    from dagr_lite.synth.video import linear_interpolate

    first = max(0, k - 3)
    frames = [read_frame(fmt.frame_path(root, split, video, j)).astype(np.float32) for j in range(first, k + 1)]
    height, width = frames[0].shape[:2]
    fig, axes = plt.subplots(1, 2, figsize=(12, 6 * height / width + 0.8))
    for ax, name in zip(axes, ("clean", "noisy")):
        emulator = DVSEmulator(height, width, preset(name), seed=0)
        emulator.reset(frames[0], fmt.frame_time_us(first, fps))
        last = None
        for j in range(1, len(frames)):
            t_a, t_b = fmt.frame_time_us(first + j - 1, fps), fmt.frame_time_us(first + j, fps)
            parts = [emulator.step(frames[j] if s == upsample else linear_interpolate(frames[j - 1], frames[j],
                                                                                      s / upsample),
                                   t_a + s / upsample * (t_b - t_a)) for s in range(1, upsample + 1)]
            last = {key: np.concatenate([p[key] for p in parts]) for key in ("x", "y", "t", "p")}
        last = last or {key: np.zeros(0) for key in ("x", "y", "t", "p")}
        ax.imshow(event_image(last, height, width), interpolation="nearest")
        ax.set(title=f"{name} preset: {len(last['t']):,} events, frame {k - 1} to {k}", xlabel="x (px)",
               ylabel="y (px)")
        _colour_legend(ax, with_box=False)
    fig.suptitle(f"{video}: the same moment emulated with the clean and the noisy DVS presets "
                 f"(from its frames {first}-{k}, {upsample} steps per frame interval)")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def write_index(out: Path, pictures: list[str], stats: dict) -> None:
    rows = "".join(f"<tr><td>{html.escape(v)}</td><td>{r['split']}</td><td>{r['events']:,}</td>"
                   f"<td>{r['mean_rate'] / 1e3:.0f}k</td><td>{r['peak_rate'] / 1e3:.0f}k</td><td>{r['boxes']:,}</td></tr>"
                   for v, r in stats["videos"].items())
    images = "".join(f'<figure><img src="{html.escape(p)}" style="max-width:100%"><figcaption>{html.escape(p)}'
                     "</figcaption></figure>" for p in pictures)
    (out / "index.html").write_text(
        "<!doctype html><meta charset=utf-8><title>dataset statistics</title><h1>Dataset statistics</h1>"
        f"<p>{html.escape(stats['root'])}</p><table border=1 cellpadding=4><tr><th>video</th><th>split</th>"
        f"<th>events</th><th>mean rate /s</th><th>peak rate /s (10 ms)</th><th>boxes</th></tr>{rows}</table>"
        f"<p>stats.json holds every number.</p>{images}\n")


def dataset_stats(root: Path | str, out: Path | str, *, videos: list[str] | None = None, frame: int | None = None,
                  fps: float = fmt.DEFAULT_FPS, pictures: bool = True) -> dict:
    """Compute, write and return the statistics of the dataset at ``root`` (see the module's text)."""
    root, out = Path(root), Path(out)
    if (out / "stats.json").exists():
        raise FileExistsError(f"{out}: holds earlier statistics (stats.json); choose a new --out")
    labels = read_labels(root)
    found = {v: s for s in fmt.SPLITS if (root / s).is_dir() for v in list_videos(root, s)}
    chosen = list(found) if not videos else videos
    unknown = [v for v in chosen if v not in found]
    if unknown:
        raise UserError(f"{root}: videos {unknown} are not in the dataset (it holds {sorted(found)})")
    per_video, all_counts, names = {}, {}, []
    for video in progress_bar(chosen, desc="videos", unit="video"):
        per_video[video], all_counts[video] = video_stats(root, found[video], video, labels.get(video, {}), fps)
    short = {v: r["frames"] for v, r in per_video.items() if frame is not None and not 0 <= frame < r["frames"]}
    if pictures and short:  # checked before anything is written
        raise UserError(f"--frame {frame}: past the end of {', '.join(f'{v} ({n} frames)' for v, n in short.items())}; "
                         f"give a frame below {min(short.values())}")
    out.mkdir(parents=True, exist_ok=True)
    for video in chosen:
        counts = all_counts[video]
        if pictures:
            rate_picture(out / f"event_rate_{video}.png", video, counts)
            labelled = sorted(k for k, b in labels.get(video, {}).items() if len(b) and k < per_video[video]["frames"])
            k = frame if frame is not None else (labelled[len(labelled) // 2] if labelled
                                                 else per_video[video]["frames"] // 2)
            boxes = labels.get(video, {}).get(k, np.zeros((0, 4)))
            names += [f"event_rate_{video}.png", *frame_pictures(root, found[video], video, k, boxes, out, fps)]
    stats = {"root": str(root), "videos": per_video, "splits": split_totals(per_video),
             "box_size_histogram": size_histogram(labels, chosen),
             "stale_labels": {split: stale_labels(labels, [v for v in chosen if found[v] == split])
                              for split in fmt.SPLITS if split in set(found[v] for v in chosen)}}
    (out / "stats.json").write_text(json.dumps(stats, indent=1))
    if pictures:
        write_index(out, names, stats)
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dagr_lite.apps.stats", description=__doc__.splitlines()[0])
    parser.add_argument("root", help="dataset folder in the EventEgoHands layout, or one event recording "
                                     "(.aedat4 .raw .dat .es .csv .h5)")
    parser.add_argument("--out", required=True, help="folder for stats.json, the pictures and index.html")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="a recording's sensor size, where "
                                                                              "its file does not say it (CSV)")
    parser.add_argument("--videos", nargs="+", help="only these videos (default: all)")
    parser.add_argument("--frame", type=int, help="the frame of the pictures (default: each video's middle labelled frame)")
    parser.add_argument("--fps", type=float, default=fmt.DEFAULT_FPS)
    args = parser.parse_args(argv)
    if Path(args.root).is_file():
        from dagr_lite.apps.recording_stats import recording_stats

        with user_errors():
            stats = recording_stats(args.root, args.out, size=args.size)
        print(f"{stats['events']:,} events over {stats['duration_s']:.2f} s (mean {stats['mean_rate'] / 1e3:.0f}k/s, "
              f"peak {stats['peak_rate'] / 1e3:.0f}k/s), ON {stats['on_fraction']:.2f}, {stats['frames']} frames; "
              f"the {len(stats['hot_pixels'])} hottest pixels hold {100 * stats['hot_pixels_share']:.1f}% of the "
              f"events\nwritten to {args.out}")
        return 0
    with user_errors():  # a user's mistake: one line, no traceback
        if not Path(args.root).exists():
            raise FileNotFoundError(f"{args.root}: no such dataset folder or recording file")
        stats = dataset_stats(args.root, args.out, videos=args.videos, frame=args.frame, fps=args.fps)
    for split, row in stats["splits"].items():
        print(f"{split}: {row['videos']} videos, {row['events']:,} events over {row['duration_s']:.1f} s "
              f"(mean {row['mean_rate'] / 1e3:.0f}k/s, peak {row['peak_rate'] / 1e3:.0f}k/s), "
              f"ON {row['on_fraction']:.2f}, {row['boxes']:,} boxes on {row['labelled_frames']:,} labelled frames")
        stale = stats["stale_labels"].get(split)
        if stale:
            print("  AP50 of frame k - a's boxes taken as frame k's (the best a detector reading only an image "
                  "a frames old can do): "
                  + ", ".join(f"a={age} {row['AP50']:.3f}" for age, row in stale.items()))
    print(f"written to {args.out} (open index.html)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
