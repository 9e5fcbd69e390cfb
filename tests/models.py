"""Small detectors for tests, built from the defaults in conf/ (the only place defaults live)."""
from __future__ import annotations

import dataclasses

from dagr_lite.config import compose_config, detector_config, resolve_config
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.nn.detector import DetectorConfig

SPEC = EventGraphSpec(radius=5.0, beta=5e-4, max_neighbors=16)


def small_detector_config(height: int = 180, width: int = 320, *, variant: str = "hybrid", **changes) -> DetectorConfig:
    """The ``variant``'s detector config of ``conf/model`` at size s, with ``changes`` applied."""
    cfg = resolve_config(compose_config("train", [f"model={variant}"]))
    return dataclasses.replace(detector_config(cfg, height=height, width=width), **changes)
