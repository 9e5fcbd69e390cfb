"""Shared fixtures: small datasets written with the project's writer, and a private cache folder."""
from __future__ import annotations

import os

# The suite runs on every core (pytest-xdist, `-n auto`): each worker takes one core's share of
# threads, set before torch is first imported, and the processes a test starts inherit it.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.data.writer import write_labels, write_video

HEIGHT, WIDTH = 48, 64


@dataclass
class Written:
    """What a test dataset holds, kept in memory for brute-force comparisons."""

    root: Path
    events: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    frames: dict[str, list[np.ndarray]] = field(default_factory=dict)
    labels: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    splits: dict[str, str] = field(default_factory=dict)


def random_events(rng: np.random.Generator, num_events: int, duration_us: int, height: int = HEIGHT,
                  width: int = WIDTH) -> dict[str, np.ndarray]:
    t = np.sort(rng.integers(0, duration_us, num_events))
    return {"x": rng.integers(0, width, num_events), "y": rng.integers(0, height, num_events), "t": t,
            "p": rng.integers(0, 2, num_events)}


def smooth_frame(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A random colour gradient: survives JPEG almost unchanged, unlike pixel noise."""
    yy, xx = np.mgrid[0:height, 0:width]
    gains = rng.uniform(-1, 1, (2, 3))
    frame = 128 + gains[0] * xx[..., None] * 100 / width + gains[1] * yy[..., None] * 100 / height
    return np.clip(frame, 0, 255).astype(np.uint8)


def make_dataset(root: Path, *, videos: dict[str, str] | None = None, num_frames: int = 12, events_per_video: int = 3000,
                 compression: str | None = "blosc", seed: int = 0, height: int = HEIGHT, width: int = WIDTH) -> Written:
    """Write a small dataset: random events, smooth random frames, boxes on every other frame."""
    rng = np.random.default_rng(seed)
    videos = videos or {"CARDS_COURTYARD_B_T": "train", "vid_b": "train", "vid_c": "valid", "vid_d": "test"}
    written = Written(root=root, splits=dict(videos))
    duration = fmt.frame_time_us(num_frames)
    for video, split in videos.items():
        events = random_events(rng, events_per_video, duration, height, width)
        frames = [smooth_frame(rng, height, width) for _ in range(num_frames)]
        labels = {}
        for k in range(num_frames):
            if k % 2 == 0:
                m = int(rng.integers(1, 4))
                xy = rng.uniform(0, [width - 12, height - 12], (m, 2))
                wh = rng.uniform(4, 12, (m, 2))
                labels[k] = np.round(np.concatenate([xy, wh], axis=1), 3)
            elif k % 4 == 1:
                labels[k] = np.zeros((0, 4))  # a labelled frame without hands
        write_video(root, split, video, events=events, frames=frames, compression=compression)
        written.events[video], written.frames[video], written.labels[video] = events, frames, labels
    write_labels(root, written.labels)
    return written


@pytest.fixture(autouse=True, scope="session")
def private_cache(tmp_path_factory):
    """Keep generated data (the stub dataset) out of the user's cache folder. The workers of one
    run share it: each dataset is made once, atomically, by whichever worker needs it first."""
    mp = pytest.MonkeyPatch()
    base = tmp_path_factory.getbasetemp()
    shared = base.parent / "cache" if os.environ.get("PYTEST_XDIST_WORKER") else base / "cache"
    shared.mkdir(exist_ok=True)
    mp.setenv("DAGR_LITE_CACHE", str(shared))
    mp.delenv("EVENTEGOHANDS_ROOT", raising=False)
    yield
    mp.undo()


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Written:
    """A small Blosc-compressed dataset; tests must not modify it (copy it first)."""
    return make_dataset(tmp_path_factory.mktemp("dataset"))


@pytest.fixture
def dataset_copy(tmp_path) -> Written:
    """A fresh small dataset a test may break."""
    return make_dataset(tmp_path / "ds", compression=None)


@pytest.fixture(scope="session")
def trained_checkpoints(tmp_path_factory) -> dict[str, Path]:
    """``last.pt`` of a hybrid (with its carry branch), of an events-only model and of a hybrid
    whose query maps join its head after the towers (``hybrid_late``, no carry branch) trained for
    three steps on the stub by the training loop, on the CPU in float32, with the default sample
    settings."""
    from dagr_lite.config import compose_config
    from dagr_lite.engine.train import train

    root = tmp_path_factory.mktemp("trained")
    paths = {}
    for variant, model in (("hybrid", "hybrid"), ("events_only", "events_only"), ("hybrid_late", "hybrid")):
        late = [f"model.late_query={variant.endswith('_late')}"]
        if variant.endswith("_late"):
            late += ["model.carry_width=0"]
        train(compose_config("train", [f"run_dir={root / variant}", f"model={model}", *late, "trainer.max_steps=3",
                                       "trainer.schedule_by=steps", "trainer.dense_first=0",  # every step trains the graph
                                       "device=cpu", "trainer.amp=false", "loader.batch_size=4",
                                       "loader.num_workers=0", "trainer.image_every=0", "trainer.warmup_steps=1",
                                       "optim.lr=3e-3", "trainer.val_samples=8"]))
        paths[variant] = root / variant / "checkpoints" / "last.pt"
    return paths
