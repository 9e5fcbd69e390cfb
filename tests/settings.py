"""The settings tests pass where a test does not choose its own: the library has no defaults for
what `conf/` sets (docs/design.md, "Settings: where each one lives")."""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from dagr_lite.data.dataset import EventEgoHands

CONF = Path(__file__).resolve().parents[1] / "conf"
_eval = OmegaConf.load(CONF / "eval" / "default.yaml")
EVAL = {"conf_threshold": float(_eval.conf_threshold), "nms_threshold": float(_eval.nms_threshold)}  # conf/eval's own
EVAL_ANSWER = {"score": EVAL["conf_threshold"], "nms_iou": EVAL["nms_threshold"]}  # the same, as an operating point
# One sample: the image one frame old, the events of its horizon since the image, no filter, no guard;
# a carry picture (where asked for) with conf/data's recent channel.
SAMPLE = {"image_age": 1, "window_us": 33_333, "context_us": 0, "refractory_us": 0, "support_us": 0,
          "max_events": None,
          "graph_context_us": 0, "carry_recent_us": 33_333}
# detect's settings (conf/detect.yaml): its video, its UDP receiver.
_detect = OmegaConf.load(CONF / "detect.yaml")
VIDEO = OmegaConf.to_container(_detect.video)
UDP = {"fmt": _detect.udp.format, "idle_s": float(_detect.udp.idle_s), "wait_first_s": float(_detect.udp.wait_first_s),
       "max_backlog_bytes": int(_detect.udp.max_backlog_mb * 2 ** 20)}
# TrainAugment without the hybrid's grey images.
AUGMENT = {"flip_prob": 0.5, "zoom": (1.0, 1.5), "translate": 0.1, "min_box_size": 2.0, "image_dropout": 0.0,
           "event_drop": 0.0, "crop": 1.0, "crop_multiple": 1, "crop_boxes": 0.0}


def sample_set(root, split: str, **settings) -> EventEgoHands:
    """``EventEgoHands(root, split)`` with :data:`SAMPLE`, any of it replaced by ``settings``."""
    return EventEgoHands(root, split, **{**SAMPLE, **settings})


def video_settings(**changes):
    """``VideoSettings`` of conf/detect.yaml, any of it replaced by ``changes``."""
    from dagr_lite.camera.detect import VideoSettings

    return VideoSettings(**{**VIDEO, **changes})
