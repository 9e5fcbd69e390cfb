"""A dataset in this package's layout to the formats event-camera tools open, and to MP4 renders
(``python -m dagr_lite.apps.export``).

Per video it writes ``DIR/<split>/<video>.<ext>``: ``aedat4`` (events and the frames as a frame
track, as a DAVIS records them), ``evt2`` / ``evt3`` (Prophesee ``.raw``), ``dat``, ``es``, ``csv``
(events only, through faery), and ``mp4`` (faery's render of the events, exponential decay).
Events are read and written a chunk at a time. Each file is written under a partial name
(``<video>.partial<pid><ext>``) and named when whole, so an interrupted export leaves no file that
looks finished; run again, it keeps the files already written and writes the rest (nothing is
overwritten), after removing the partial files an earlier run left.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


from dagr_lite.errors import UserError
from dagr_lite.camera.aedat import write_aedat4
from dagr_lite.camera.recording import open_recording
from dagr_lite.data import format as fmt
from dagr_lite.data.labels import list_videos
from dagr_lite.progress import progress_bar

TARGETS = {"aedat4": ".aedat4", "evt2": ".evt2.raw", "evt3": ".evt3.raw", "dat": ".dat", "es": ".es",
           "csv": ".csv", "mp4": ".mp4"}
RENDER_FPS = 30.0
RENDER_TAU = "00:00:00.100000"  # the decay of faery's render


def _faery_packets(recording):
    import faery
    import numpy as np

    for chunk in recording.events():
        packed = np.zeros(len(chunk["t"]), faery.EVENTS_DTYPE)
        packed["t"], packed["x"], packed["y"], packed["on"] = chunk["t"], chunk["x"], chunk["y"], chunk["p"] > 0
        yield packed


def partial_name(path: Path, ext: str) -> Path:
    """Where ``path`` (ending in ``ext``) is written until it is whole; the extension stays last,
    since faery chooses a format by it."""
    return path.with_name(path.name[:-len(ext)] + f".partial{os.getpid()}{ext}")


def remove_partials(path: Path, ext: str) -> None:
    """Remove the partial files of ``path`` that earlier runs left (any process's; with faery's own
    ``.write`` temporaries)."""
    for stale in path.parent.glob(path.name[:-len(ext)] + ".partial*" + ext + "*"):
        stale.unlink(missing_ok=True)


def _write(recording, path: Path, target: str) -> None:
    import faery

    if target == "aedat4":  # frames too: faery writes events only
        write_aedat4(path, recording.events(), recording.size, recording.frames())
    elif target == "mp4":
        with tempfile.TemporaryDirectory() as tmp:
            source = Path(tmp) / "events.aedat4"
            faery.file_encoder.events_to_file(_faery_packets(recording), source, dimensions=recording.size)
            (faery.events_stream_from_file(source).regularize(frequency_hz=RENDER_FPS)
             .render(decay="exponential", tau=RENDER_TAU, colormap=faery.colormaps.starry_night)
             .to_file(Path(tmp) / "render.mp4", frame_rate=RENDER_FPS))  # real time: a frame every 1 / RENDER_FPS s
            shutil.move(Path(tmp) / "render.mp4", path)  # faery's own temporaries stay in tmp
    else:
        version = {"evt2": "evt2", "evt3": "evt3"}.get(target)
        faery.file_encoder.events_to_file(_faery_packets(recording), path, dimensions=recording.size,
                                          version=version, file_type="evt" if version else None)


def export_video(events_path: Path, out_stem: Path, targets: list[str]) -> tuple[list[Path], list[Path]]:
    """Write one video of the layout to each target (see the module); returns the files written
    and the files kept (already there)."""
    recording = open_recording(events_path)
    written, kept = [], []
    for target in targets:
        ext = TARGETS[target]
        path = out_stem.with_name(out_stem.name + ext)
        if path.exists():
            kept.append(path)
            continue
        remove_partials(path, ext)
        partial = partial_name(path, ext)
        try:
            _write(recording, partial, target)
            os.replace(partial, path)
        except BaseException:
            remove_partials(path, ext)
            raise
        written.append(path)
    return written, kept


def export_dataset(root: Path | str, out: Path | str, targets: list[str], videos: list[str] | None = None) -> list[Path]:
    root, out = Path(root), Path(out)
    unknown = [t for t in targets if t not in TARGETS]
    if unknown:
        raise UserError(f"--to {unknown}: expected some of {sorted(TARGETS)}")
    found = {v: s for s in fmt.SPLITS if (root / s).is_dir() for v in list_videos(root, s)}
    if not found:
        raise UserError(f"{root}: no videos in the dataset layout (<root>/<split>/events/<video>.h5)")
    chosen = videos or list(found)
    missing = [v for v in chosen if v not in found]
    if missing:
        raise UserError(f"{root}: videos {missing} are not in the dataset (it holds {sorted(found)})")
    written, kept = [], []
    for video in progress_bar(chosen, desc="export", unit="video"):
        (out / found[video]).mkdir(parents=True, exist_ok=True)
        new, old = export_video(fmt.events_path(root, found[video], video), out / found[video] / video, targets)
        written, kept = written + new, kept + old
    if kept:
        print(f"{len(kept)} files were already in {out} and are kept as they are (first: {kept[0]})", flush=True)
    return written
