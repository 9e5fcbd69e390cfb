"""Progress bars that suit where they are read.

On a terminal a bar redraws in place, ten times a second (tqdm's default). Written to a file (a
job's log under ``nohup`` or a cluster's scheduler, CI), every redraw is one more copy of the bar
after a carriage return, so a 13-minute training run would leave thousands of them. There a bar
redraws at most every :data:`LOG_INTERVAL_S` seconds, and a passing bar (``leave=False``) drawn
while another is (a validation inside training, the frames of one video among the videos) is not
drawn at all.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

LOG_INTERVAL_S = 30.0  # seconds between a bar's lines in a log file


def progress_bar(iterable=None, **kwargs) -> tqdm:
    """``tqdm(iterable, **kwargs)``, drawn for a log file as the module says when its output is not a terminal."""
    if not _live(kwargs.get("file") or sys.stderr):
        kwargs.setdefault("mininterval", LOG_INTERVAL_S)
        kwargs.setdefault("maxinterval", max(LOG_INTERVAL_S, kwargs["mininterval"]))
        if kwargs.get("leave") is False and any(not b.disable for b in list(getattr(tqdm, "_instances", ()))):
            kwargs["disable"] = True
    return tqdm(iterable, **kwargs)


def _live(stream) -> bool:
    """Whether ``stream`` is redrawn in place: a terminal, or a notebook's output."""
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty()) or "ipykernel" in sys.modules


def say(message: str) -> None:
    """Prints ``message`` as a line of its own while bars are drawn (above them on a terminal, and
    not run on after a bar's last draw in a log file); a plain ``print`` when none is."""
    tqdm.write(message)
    sys.stdout.flush()
