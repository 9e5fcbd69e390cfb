"""``python detect.py``: the config to a source, a sensor and a streaming detector, then :func:`run_detect`."""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dagr_lite.camera.detect import VideoSettings, run_detect
from dagr_lite.camera.recording import open_recording
from dagr_lite.camera.sensor import Sensor
from dagr_lite.camera.udp import UdpSource
from dagr_lite.config import ConfigError, check_values
from dagr_lite.engine.runs import resolve_device
from dagr_lite.stream import StreamingDetector

MODEL_SIZES = ("model", "sensor")


def build_source(cfg: DictConfig):
    """A recording or a live stream, from ``cfg.input`` and its settings."""
    size = None if cfg.sensor.size is None else tuple(cfg.sensor.size)  # two integers (check_values)
    if str(cfg.input).startswith("udp://"):
        if size is None:
            raise ConfigError("a live stream does not say its sensor size; give sensor.size=[width,height]")
        if cfg.frames is not None:
            raise ConfigError("frames= goes with a recording; a live stream carries events only")
        return UdpSource(str(cfg.input), size, fmt=cfg.udp.format, idle_s=cfg.udp.idle_s, seconds=cfg.seconds,
                         wait_first_s=cfg.udp.wait_first_s,
                         max_backlog_bytes=int(cfg.udp.max_backlog_mb * 2 ** 20))
    return open_recording(cfg.input, size=size, frames=cfg.frames, frame_times=cfg.frame_times, order=cfg.order,
                          order_window_us=cfg.order_window_us)


def build_sensor(cfg: DictConfig, size: tuple[int, int]) -> Sensor:
    """The sensor mapping of ``cfg.sensor``, whose values :func:`check_values` has typed."""
    crop = cfg.sensor.crop
    return Sensor(size=size, crop=None if crop is None else tuple(crop), scale=cfg.sensor.scale,
                  rotate=cfg.sensor.rotate, flip_x=cfg.sensor.flip_x, flip_y=cfg.sensor.flip_y)


def detect(cfg: DictConfig) -> dict:
    """Run ``cfg.ckpt`` over ``cfg.input``; returns the summary (see :mod:`dagr_lite.camera.detect`)."""
    check_values(cfg)
    if cfg.sensor.model_size not in MODEL_SIZES:
        raise ConfigError(f"sensor.model_size={cfg.sensor.model_size!r}: expected one of {MODEL_SIZES}")
    print(OmegaConf.to_yaml(cfg), flush=True)
    source = build_source(cfg)
    retimed = getattr(source, "retimed", None)
    if retimed is not None and retimed.late:
        print(f"{cfg.input}: {retimed.late} of {retimed.events} events are written out of time order (the first is "
              f"event {retimed.first_at} at t={retimed.first_t} us, after t={retimed.first_after} us); they are read "
              "at the time of the event before them, as the file's decoder does (order=refuse refuses the file)",
              flush=True)
    sensor = build_sensor(cfg, source.size)
    model_size = sensor.output_size if cfg.sensor.model_size == "sensor" else None
    stream = StreamingDetector.from_checkpoint(cfg.ckpt, device=resolve_device(cfg.device), model_size=model_size,
                                               score=cfg.operating.score, nms_iou=cfg.operating.nms_iou)
    print(f"{cfg.ckpt}: answers at {stream.operating.describe()}", flush=True)
    out = Path(cfg.out) if cfg.out is not None else Path("runs/detect") / time.strftime("%Y-%m-%d/%H-%M-%S")
    video = VideoSettings(**OmegaConf.to_container(cfg.video))
    live = isinstance(source, UdpSource)
    if live:
        print(f"listening on {cfg.input} ({source.size[0]}x{source.size[1]} sensor); Ctrl-C stops", flush=True)
    summary = run_detect(stream, source, sensor, out, rate_hz=cfg.rate_hz, video=video, seconds=cfg.seconds,
                         live=live, overwrite=cfg.overwrite)
    if not summary["finished"]:
        print(f"{summary['stopped']}: {summary['events_in']} events read; the outputs in {out} keep their partial "
              "names (summary.partial.json says what was processed)", flush=True)
        raise SystemExit(143 if "SIGTERM" in summary["stopped"] else 130)
    rtf = summary["real_time_factor"]
    print(f"{summary['events_in']} events, {summary['recording_seconds']:.2f} s of recording, {summary['answers']} "
          f"answers -> {out}\nlatency median {summary['latency_ms_median']:.1f} ms, p95 "
          f"{summary['latency_ms_p95']:.1f} ms; real-time factor {rtf if rtf is None else round(rtf, 3)}", flush=True)
    return summary
