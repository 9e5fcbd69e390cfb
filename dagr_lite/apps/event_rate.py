"""The event rate of a recording or a video, ON and OFF in 10 ms bins, as a picture (the dataset
and recording statistics both draw it)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ON_COLOUR, OFF_COLOUR = (0.85, 0.12, 0.12), (0.12, 0.25, 0.85)
BIN_US = 10_000  # event-rate bins


def rate_picture(path: Path, video: str, counts: dict) -> None:
    t = (np.arange(len(counts["on"])) + 0.5) * BIN_US / 1e6
    fig, ax = plt.subplots(figsize=(8, 3))
    scale = 1e6 / BIN_US / 1e3  # per bin -> thousands per second
    ax.plot(t, counts["on"] * scale, color=ON_COLOUR, lw=0.8, label="ON")
    ax.plot(t, counts["off"] * scale, color=OFF_COLOUR, lw=0.8, label="OFF")
    ax.set(xlabel="time (s)", ylabel="events per second (thousands)",
           title=f"{video}: event rate in {BIN_US // 1000} ms bins")
    ax.set_xlim(0, t[-1] if len(t) else 1)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
