"""A checkpoint over a recording or a live stream: detections in the sensor's pixels, a video, a summary.

:func:`run_detect` feeds the streaming detector in time order: events through the :class:`Sensor`
to the model's pixels, frames the same way. It answers every ``1 / rate_hz`` seconds of recording
and at every frame's time, just before that frame is pushed, so an answer at a frame is the
evaluated sample (the previous image, image age 1, and the events up to the frame). A live source
(:class:`~dagr_lite.camera.udp.UdpSource`) is answered at most ``rate_hz`` times per second of
stream, at its latest event, and never drops what arrived while the detector was busy.

Writes into ``out``: ``detections.jsonl`` (one line per answer: ``t_us``, ``boxes`` xyxy in sensor
pixels, ``scores``, ``latency_ms``), ``detections.mp4`` (recent events, the latest frame, the boxes,
the time and the update's latency) and ``summary.json``.
"""
from __future__ import annotations

import dataclasses
import json
import math
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dagr_lite.errors import UserError
from dagr_lite.camera.recording import Events, concat, take
from dagr_lite.camera.render import Mp4Writer, render_moment
from dagr_lite.camera.sensor import Sensor, fit_sensor
from dagr_lite.progress import progress_bar
from dagr_lite.stream import StreamingDetector

# A stretch of the recording's clock this long without an event is a jump (a clock reset, a
# recording resumed, a jump to Unix-epoch microseconds): its periodic answers stop once the last
# events before it have left the horizon, and resume at the first event after it.
CLOCK_JUMP_US = 10_000_000

SUMMARY = "summary.json"
DETECTIONS = "detections.jsonl"
VIDEO = "detections.mp4"
OUTPUTS = (SUMMARY, DETECTIONS, VIDEO)


def partial_name(name: str) -> str:
    """What an output is called until its run finished: ``detections.partial.jsonl``, ..."""
    stem, suffix = name.rsplit(".", 1)
    return f"{stem}.partial.{suffix}"


@dataclass
class VideoSettings:
    """The MP4: ``fps`` frames per second played, ``rate_hz`` pictures per second of recording (at
    most one per answer; ``rate_hz = fps``: real time), events of the last ``events_ms``."""
    enabled: bool
    fps: float
    rate_hz: float
    events_ms: float
    max_seconds: float | None  # of recording; None: all of it


class _Output:
    """The answers as they are made: the JSON lines, the video, the counts."""

    def __init__(self, out: Path, sensor: Sensor, video: VideoSettings, live: bool):
        self.out, self.sensor, self.video, self.live = out, sensor, video, live
        self.lines = open(out / partial_name(DETECTIONS), "w")
        self.mp4 = Mp4Writer(out / partial_name(VIDEO), fps=video.fps) if video.enabled else None
        self.latencies: list[float] = []
        self.answers = 0
        self.last_picture_t = -math.inf
        self.recent: list[Events] = []  # sensor events of the last events_ms, for the video
        self.frame: np.ndarray | None = None  # the latest frame, sensor pixels
        self.frame_t: int | None = None

    def add_events(self, events: Events, now: float) -> None:
        if self.mp4 is None:
            return
        self.recent.append(events)
        keep_from = now - 1e3 * self.video.events_ms
        while len(self.recent) > 1 and (not len(self.recent[0]["t"]) or self.recent[0]["t"][-1] < keep_from):
            self.recent.pop(0)

    def answer(self, t_us: float, result: dict, latency: float, t_start: float) -> None:
        boxes = self.sensor.boxes_to_sensor(result["boxes"])
        record = {"t_us": int(round(t_us)), "boxes": np.round(boxes, 2).tolist(),
                  "scores": np.round(result["scores"].astype(np.float64), 4).tolist(),
                  "latency_ms": round(1e3 * latency, 3)}
        self.lines.write(json.dumps(record) + "\n")
        self.latencies.append(latency)
        self.answers += 1
        if self.live:
            print(f"t {t_us / 1e6:10.4f} s  {len(boxes)} hands  {json.dumps(record['boxes'])}  "
                  f"({1e3 * latency:.1f} ms)", flush=True)
        self._picture(t_us, boxes, result["scores"], latency, t_start)

    def _picture(self, t_us, boxes, scores, latency, t_start) -> None:
        if self.mp4 is None or t_us - self.last_picture_t < 1e6 / self.video.rate_hz:
            return
        if self.video.max_seconds is not None and t_us - t_start > 1e6 * self.video.max_seconds:
            return
        self.last_picture_t = t_us
        width, height = self.sensor.size
        recent = concat(self.recent)
        recent = take(recent, recent["t"] >= t_us - 1e3 * self.video.events_ms)
        image = self.frame if self.frame is not None else np.zeros((height, width, 3), np.uint8)
        age = "no frame" if self.frame_t is None else f"frame age {(t_us - self.frame_t) / 1e3:5.1f} ms"
        caption = (f"t {(t_us - t_start) / 1e6:7.3f} s  {age}  update {1e3 * latency:5.1f} ms  "
                   f"{len(boxes)} hands")
        self.mp4.write(render_moment(image, recent, boxes, scores, caption))

    def close(self) -> Path | None:
        """Finish the outputs under their partial names; the video's path (None: none)."""
        self.lines.close()
        return self.mp4.close() if self.mp4 is not None else None

    def discard_video(self) -> None:
        self.lines.close()
        if self.mp4 is not None:
            self.mp4.discard()


def publish(out: Path, summary: dict) -> None:
    """Write the summary and give every output of a finished run its name (the summary last), over
    those of an earlier run; until then a folder holds the earlier run's outputs whole."""
    (out / partial_name(SUMMARY)).write_text(json.dumps(summary, indent=1))
    for name in (DETECTIONS, VIDEO, SUMMARY):
        if (out / partial_name(name)).exists():
            (out / partial_name(name)).replace(out / name)
        elif name == VIDEO:
            (out / VIDEO).unlink(missing_ok=True)  # this run drew no video: an earlier one's is not its


def check_out(out: Path, overwrite: bool) -> None:
    taken = [out / name for name in OUTPUTS if (out / name).exists()]
    if taken and not overwrite:
        raise FileExistsError(f"{taken[0]} already exists; choose another out= (or overwrite=true)")
    out.mkdir(parents=True, exist_ok=True)


def run_detect(stream: StreamingDetector, source, sensor: Sensor, out: Path | str, *, rate_hz: float,
               video: VideoSettings, seconds: float | None = None, live: bool = False,
               progress: bool = True, overwrite: bool = False) -> dict:
    """Run ``stream`` over ``source`` (a :class:`~dagr_lite.camera.recording.Recording` or a
    :class:`~dagr_lite.camera.udp.UdpSource`); writes into ``out`` (see the module). Returns the summary."""
    if not rate_hz > 0:
        raise UserError(f"rate_hz must be positive, got {rate_hz}")
    if stream.hybrid and not source.has_frames:
        raise UserError(f"{source.path}: the model is a hybrid and needs frames, but the input carries none; give "
                         "frames=DIR|VIDEO (with timestamps) or use an events-only checkpoint")
    fit_sensor(sensor, (stream.width, stream.height))
    out = Path(out)
    check_out(out, overwrite)
    if progress:
        print("warming the detector up (compiled kernels, the first time after an install: up to a minute)",
              flush=True)
    warm_up_s = stream.warm_up()  # compiled kernels ready before the clock of the first answer starts
    output = _Output(out, sensor, video, live)
    bar, stopped = None, None
    previous = _catch_sigterm()
    try:
        runner = _Runner(stream, sensor, output, 1e6 / rate_hz, live, source.frames())
        bar = progress_bar(desc=f"detect {Path(str(source.path)).name}", unit=" ev", unit_scale=True,
                           disable=not progress or live)
        for chunk in source.events():
            bar.update(len(chunk["t"]))
            if seconds is not None:  # the events of the first ``seconds`` only, wherever a chunk ends
                end = (runner.t_first if runner.t_first is not None else int(chunk["t"][0])) + 1e6 * seconds
                cut = int(np.searchsorted(chunk["t"], end, side="right"))
                if cut:
                    runner.feed(take(chunk, slice(0, cut)) if cut < len(chunk["t"]) else chunk)
                if cut < len(chunk["t"]):
                    break
                continue
            runner.feed(chunk)
        if runner.t_first is None and not live:
            raise UserError(f"{source.path}: the recording holds no events")
        runner.finish()
        if stream.hybrid and not output.answers and runner.t_first is not None:
            raise UserError(runner.no_frame_message(source))
    except (KeyboardInterrupt, Terminated) as err:
        stopped = "interrupted (Ctrl-C)" if isinstance(err, KeyboardInterrupt) else "stopped by SIGTERM"
        print(f"stopped; what was made so far is in {out} under partial names", flush=True)
    except BaseException:
        output.discard_video()  # no finished-looking video of a failed run; its answers stay partial
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if bar is not None:
            bar.close()
    video_path = output.close()
    summary = {**runner.summary(source, video_path), "warm_up_seconds": warm_up_s, "finished": stopped is None,
               "stopped": stopped}
    if stopped is None:
        publish(out, {**summary, "video": None if video_path is None else str(out / VIDEO)})
        return {**summary, "video": None if video_path is None else str(out / VIDEO)}
    (out / partial_name(SUMMARY)).write_text(json.dumps(summary, indent=1))
    return summary


class Terminated(Exception):
    """A SIGTERM arrived during :func:`run_detect` (a service stopped, a job preempted)."""


def _raise_terminated(signum, frame):
    raise Terminated()


def _catch_sigterm():
    """Make SIGTERM end the run as Ctrl-C does (outputs under partial names, a partial summary);
    returns the handler to put back (None off the main thread, where signals cannot be caught)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


class _Runner:
    """The time-ordered feeding of one source (see :func:`run_detect`)."""

    def __init__(self, stream: StreamingDetector, sensor: Sensor, output: _Output, step_us: float, live: bool,
                 frames):
        self.stream, self.sensor, self.output, self.step_us, self.live = stream, sensor, output, step_us, live
        self.frames = iter(frames)  # (t_us, sensor image), in time order
        self.next_frame = next(self.frames, None)
        self.pending: list[Events] = []  # model-pixel events read but not yet pushed (no chunk empty)
        self.t_first: float | None = None
        self.next_stop: float | None = None
        self.events_in = self.events_used = self.frames_used = 0
        self.late_dropped = 0  # live: events older than those already read (reported, not hidden)
        self.busy_s = 0.0  # wall time in the detector (push + detect)
        self.t_last: float | None = None
        self.jumps: list[tuple[float, float]] = []  # (last event before, first event after) each clock jump
        self.wall_start = time.perf_counter()

    def feed(self, chunk: Events) -> None:
        self.events_in += len(chunk["t"])
        if self.t_first is None:
            self.t_first = float(chunk["t"][0])
            self.next_stop = self.t_first + self.step_us
        self._find_jumps(chunk["t"])
        self.t_last = float(chunk["t"][-1])
        self.output.add_events(chunk, self.t_last)
        mapped = self.sensor.events(chunk)
        if self.live:  # a datagram that came late: older than what the detector has read
            late = mapped["t"] < self.stream.last_event_us
            if late.any():
                self.late_dropped += int(late.sum())
                mapped = take(mapped, ~late)
        self.events_used += len(mapped["t"])
        if len(mapped["t"]):
            self.pending.append(mapped)
        if self.live:  # answer at the latest event, at most once per step
            self._push_frames_until(self.t_last)
            if self.t_last >= self.next_stop:
                self._answer(self.t_last + 1, frame_due=False)
                self.next_stop = self.t_last + self.step_us
            return
        self._answer_until(self.t_last)

    def _find_jumps(self, t: np.ndarray) -> None:
        """Record each stretch of more than :data:`CLOCK_JUMP_US` without an event, up to ``t``."""
        times = np.concatenate([[self.t_last if self.t_last is not None else t[0]], t])
        for i in np.flatnonzero(np.diff(times) > CLOCK_JUMP_US):
            before, after = float(times[i]), float(times[i + 1])
            self.jumps.append((before, after))
            print(f"clock jump: no event from t={before:.0f} us to t={after:.0f} us "
                  f"({(after - before) / 1e6:.1f} s); answers pause there", flush=True)

    def _skip_jump(self, stop: float) -> bool:
        """Move a periodic stop that falls inside a jump, past the horizon of the events before it,
        to the first stop after it; whether it moved."""
        for before, after in self.jumps:
            if before + self.stream.window_us + self.step_us <= stop < after:
                self.next_stop += self.step_us * math.ceil((after - self.next_stop) / self.step_us)
                return True
        return False

    def _answer_until(self, t_known: float) -> None:
        """Answer at every stop before ``t_known`` (events up to it have all been read)."""
        while True:
            frame_t = self.next_frame[0] if self.next_frame is not None else math.inf
            stop = min(self.next_stop, frame_t)
            if stop > t_known:
                return
            if frame_t > stop and self._skip_jump(stop):
                continue
            self._answer(stop, frame_due=frame_t <= stop)
            if self.next_stop <= stop:
                self.next_stop += self.step_us * (1 + math.floor((stop - self.next_stop) / self.step_us))

    def _push_frames_until(self, t_us: float) -> None:
        while self.next_frame is not None and self.next_frame[0] <= t_us:
            self._push_frame()

    def _push_frame(self) -> None:
        t_frame, image = self.next_frame
        tic = time.perf_counter()
        self.stream.push_image(self.sensor.frame(image), t_frame)
        self.busy_s += time.perf_counter() - tic
        self.output.frame, self.output.frame_t = image, t_frame
        self.frames_used += 1
        self.next_frame = next(self.frames, None)

    def _answer(self, stop: float, frame_due: bool) -> None:
        now, rest = [], []  # views of the pending chunks before ``stop`` and from it on: the events
        for part in self.pending:  # left pending are not copied again at every answer
            cut = int(np.searchsorted(part["t"], stop, side="left"))
            if cut:
                now.append(take(part, slice(0, cut)))
            if cut < len(part["t"]):
                rest.append(take(part, slice(cut, None)))
        self.pending = rest
        now_events = concat(now) if len(now) != 1 else now[0]
        tic = time.perf_counter()
        self.stream.push_events(**now_events)
        result = self.stream.detect(stop) if self.stream.ready else None
        latency = time.perf_counter() - tic
        self.busy_s += latency
        if result is not None:
            self.output.answer(stop, result, latency, self.t_first)
        if frame_due:
            self._push_frame()

    def no_frame_message(self, source) -> str:
        """Why a hybrid gave no answer: no frame came at or before any event's time."""
        span = f"the events run from t={int(self.t_first)} to t={int(self.t_last)} us"
        if self.next_frame is None and not self.frames_used:
            return f"{source.path}: no frame was read; {span}"
        first = self.next_frame[0] if not self.frames_used else self.output.frame_t
        return (f"{source.path}: no answer: the first frame is at t={first} us and {span}; frames and events must "
                "share one clock (timestamps in the recording's microseconds)")

    def finish(self) -> None:
        if self.t_first is None:
            return
        if not self.live:
            self._answer_until(self.t_last)
        if self.pending:
            self._answer(self.t_last + 1, frame_due=False)

    def summary(self, source, video_path: Path | None) -> dict:
        span_s = 0.0 if self.t_first is None else (self.t_last - self.t_first) / 1e6
        span_s -= sum(after - before for before, after in self.jumps) / 1e6  # the recording, not its jumps
        latency = np.array(self.output.latencies) if self.output.latencies else np.zeros(1)
        result = {"input": str(source.path), "sensor": list(self.sensor.size),
                  "model_input": list(self.sensor.output_size), "events_in": self.events_in,
                  "events_in_model_view": self.events_used, "frames": self.frames_used,
                  "recording_seconds": span_s, "detector_seconds": self.busy_s,
                  "wall_seconds": time.perf_counter() - self.wall_start,
                  "events_per_second_sustained": self.events_in / self.busy_s if self.busy_s else None,
                  "real_time_factor": span_s / self.busy_s if self.busy_s else None,
                  "answers": self.output.answers, "latency_ms_median": 1e3 * float(np.median(latency)),
                  "latency_ms_p95": 1e3 * float(np.percentile(latency, 95)),
                  "video": None if video_path is None else str(video_path),
                  "operating_point": self.stream.operating.as_dict(),
                  "clock_jumps": [{"from_us": before, "to_us": after} for before, after in self.jumps]}
        if getattr(source, "order", None) is not None:
            result["out_of_order_events_sorted"] = source.order.out_of_order
        if getattr(source, "retimed", None) is not None:
            result["out_of_order_events_retimed"] = source.retimed.late
        if getattr(source, "stats", None) is not None:
            result["udp"] = {**dataclasses.asdict(source.stats), "late_events_dropped": self.late_dropped}
        return result
