"""A dataset in this package's layout to the formats event-camera tools open, and to MP4 renders
(``python -m dagr_lite.apps.export``).

Per video it writes ``DIR/<split>/<video>.<ext>``: ``aedat4`` (events and the frames as a frame
track, as a DAVIS records them), ``evt2`` / ``evt3`` (Prophesee ``.raw``), ``dat``, ``es``, ``csv``
(events only, through faery), and ``mp4`` (faery's render of the events, exponential decay).
Events are read and written a chunk at a time; nothing is overwritten.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

from tqdm import tqdm

from dagr_lite.errors import UserError
from dagr_lite.camera.aedat import write_aedat4
from dagr_lite.camera.recording import open_recording
from dagr_lite.data import format as fmt
from dagr_lite.data.labels import list_videos

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


def export_video(events_path: Path, out_stem: Path, targets: list[str]) -> list[Path]:
    """Write one video of the layout to each target (see the module); returns the files written."""
    import faery

    recording = open_recording(events_path)
    written = []
    for target in targets:
        path = out_stem.with_name(out_stem.name + TARGETS[target])
        if path.exists():
            raise FileExistsError(f"{path} already exists (nothing is overwritten)")
        if target == "aedat4":  # frames too: faery writes events only
            write_aedat4(path, recording.events(), recording.size, recording.frames())
        elif target == "mp4":
            with tempfile.TemporaryDirectory() as tmp:
                source = Path(tmp) / "events.aedat4"
                faery.file_encoder.events_to_file(_faery_packets(recording), source, dimensions=recording.size)
                (faery.events_stream_from_file(source).regularize(frequency_hz=RENDER_FPS)
                 .render(decay="exponential", tau=RENDER_TAU, colormap=faery.colormaps.starry_night)
                 .to_file(path))  # faery writes beside it and moves it into place
        else:
            version = {"evt2": "evt2", "evt3": "evt3"}.get(target)
            faery.file_encoder.events_to_file(_faery_packets(recording), path, dimensions=recording.size,
                                              version=version, file_type="evt" if version else None)
        written.append(path)
    return written


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
    written = []
    for video in tqdm(chosen, desc="export", unit="video"):
        (out / found[video]).mkdir(parents=True, exist_ok=True)
        written += export_video(fmt.events_path(root, found[video], video), out / found[video] / video, targets)
    return written
