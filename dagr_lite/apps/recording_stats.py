"""Statistics of one event recording (any format :func:`~dagr_lite.camera.recording.open_recording`
reads): ``python -m dagr_lite.apps.stats RECORDING --out DIR [--size W H]``.

Writes ``DIR/stats.json`` (events, the clock's first and last time and its jumps (10 s or more
without an event, left out of the duration and of the rate's bins), duration, mean and peak rate
over 10 ms bins, ON fraction, frames, the hottest pixels and their share of all events, and the
events that share their pixel and microsecond with an earlier one) and ``DIR/event_rate.png``.
The recording is read a chunk at a time.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.apps.event_rate import BIN_US, rate_picture
from dagr_lite.camera.detect import CLOCK_JUMP_US
from dagr_lite.camera.recording import open_recording
from dagr_lite.progress import progress_bar

HOT_PIXELS = 10  # the hottest pixels listed


def recording_stats(path: Path | str, out: Path | str, *, size: tuple[int, int] | None = None) -> dict:
    out = Path(out)
    if (out / "stats.json").exists():
        raise FileExistsError(f"{out}: holds earlier statistics (stats.json); choose a new --out")
    rec = open_recording(path, size=size)
    width, height = rec.size
    per_pixel = np.zeros(width * height, np.int64)
    on = off = repeats = 0
    t_first = t_last = None
    counts = {"on": np.zeros(0, np.int64), "off": np.zeros(0, np.int64)}  # events per 10 ms bin
    carried = np.zeros(0, np.int64)  # keys of the last microsecond read, which the next chunk may share
    jumps, skipped = [], 0  # the clock's jumps, and the time they hold (beyond one bin each) left out
    for chunk in progress_bar(rec.events(), desc=f"reading {Path(path).name}", unit=" chunk"):
        t_raw = chunk["t"]
        t_first = int(t_raw[0]) if t_first is None else t_first
        # a stretch without events of CLOCK_JUMP_US or more is a jump of the clock (detect's rule): the
        # bins and keys run on without it, so an epoch-time jump costs one bin, not years of them
        step = np.diff(t_raw, prepend=t_raw[0] if t_last is None else t_last)
        gap = step > CLOCK_JUMP_US
        jumps += [(int(t_raw[i]) - int(step[i]), int(t_raw[i])) for i in np.flatnonzero(gap)]
        left_out = skipped + np.cumsum(np.where(gap, step - BIN_US, 0))
        skipped = int(left_out[-1])
        t = t_raw - left_out
        t_last = int(t_raw[-1])
        pixel = chunk["y"].astype(np.int64) * width + chunk["x"]
        per_pixel += np.bincount(pixel, minlength=width * height)
        on += int(chunk["p"].sum())
        off += int(len(t) - chunk["p"].sum())
        # Events sharing pixel and microsecond share a key, adjacent once sorted; the last microsecond's
        # keys go on to the next chunk, whose pairs with them count (those among them counted already).
        key = np.sort(np.concatenate([carried, (t - t_first) * (width * height) + pixel]))
        repeats += int(np.sum(key[1:] == key[:-1])) - int(np.sum(carried[1:] == carried[:-1]))
        carried = key[key >= (int(t[-1]) - t_first) * (width * height)]
        index = (t - t_first) // BIN_US
        for name, mask in (("on", chunk["p"] == 1), ("off", chunk["p"] == 0)):
            add = np.bincount(index[mask], minlength=int(index[-1]) + 1)
            grown = np.zeros(max(len(counts[name]), len(add)), np.int64)
            grown[:len(counts[name])] += counts[name]
            grown[:len(add)] += add
            counts[name] = grown
    if t_first is None:
        raise UserError(f"{path}: the recording holds no events")
    total = on + off
    duration = max(t_last - t_first - sum(after - before for before, after in jumps), 1) / 1e6
    hot = np.argsort(-per_pixel)[:HOT_PIXELS]
    stats = {"recording": str(path), "format": rec.kind, "sensor": [width, height], "events": total,
             "t_first_us": t_first, "t_last_us": t_last, "duration_s": duration, "mean_rate": total / duration,
             "clock_jumps": [{"from_us": before, "to_us": after} for before, after in jumps],
             "peak_rate": float((counts["on"] + counts["off"]).max() / (BIN_US / 1e6)), "on_fraction": on / total,
             "frames": sum(1 for _ in rec.frames()) if rec.has_frames else 0,
             "events_sharing_pixel_and_microsecond": repeats,
             "hot_pixels": [{"x": int(i % width), "y": int(i // width), "events": int(per_pixel[i]),
                             "rate": float(per_pixel[i] / duration)} for i in hot],
             "hot_pixels_share": float(per_pixel[hot].sum() / total)}
    out.mkdir(parents=True, exist_ok=True)
    rate_picture(out / "event_rate.png", Path(path).name, counts)
    (out / "stats.json").write_text(json.dumps(stats, indent=1))
    return stats
