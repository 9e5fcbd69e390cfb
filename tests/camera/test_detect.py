"""``detect`` over a written recording answers what the batch model answers on the same samples; on a
larger sensor with a declared crop and scale it answers the same, in the sensor's pixels; the UDP
path on loopback receives every event it is sent."""
from __future__ import annotations

import json
import math
import socket
import threading
import time

import numpy as np
import pytest
import torch

from dagr_lite.camera.aedat import write_aedat4
from dagr_lite.camera.detect import run_detect
from dagr_lite.camera.recording import concat, open_recording, take
from dagr_lite.camera.sensor import Sensor, SensorError
from dagr_lite.camera.udp import UdpSource, send
from dagr_lite.data.collate import collate
from dagr_lite.engine.checkpoint import load_checkpoint
from dagr_lite.stream import StreamingDetector
from dagr_lite.eval.operating import NMS_IOUS, OperatingPoint
from dagr_lite.nn.head import box_iou
from tests.settings import EVAL, EVAL_ANSWER, UDP, sample_set, video_settings

FRAMES = 10  # frames of the stub's first test video used
CONF = 0.0


@pytest.fixture(scope="module")
def stub_video(trained_checkpoints):
    """The first test video of the stub (the data the checkpoints were trained on), cut to FRAMES frames."""
    from dagr_lite.synth.stub import stub_root

    root = stub_root()
    path = sorted((root / "test" / "events").glob("*.h5"))[0]
    rec = open_recording(path)
    frames = list(rec.frames())[:FRAMES + 1]
    events = concat(list(rec.events()))
    events = take(events, events["t"] < frames[-1][0])
    return {"root": root, "video": path.stem, "events": events, "frames": frames, "size": rec.size}


def lines(out) -> list[dict]:
    return [json.loads(line) for line in (out / "detections.jsonl").read_text().splitlines()]



def overlapping_pairs(answer: dict) -> int:
    """Pairs of boxes of one answer that overlap with IoU >= 0.5 (two boxes on one hand)."""
    boxes = torch.tensor(answer["boxes"], dtype=torch.float64).reshape(-1, 4)
    iou = box_iou(boxes, boxes)
    return int((torch.triu(iou, diagonal=1) >= 0.5).sum())


def test_detect_answers_one_box_per_hand_at_the_checkpoints_operating_point(stub_video, trained_checkpoints, tmp_path):
    checkpoint = load_checkpoint(trained_checkpoints["hybrid"])
    point = checkpoint.operating
    assert point.nms_iou in NMS_IOUS and point.chosen_on == "valid, image age 1 and 10" and point.f1 is not None
    model = checkpoint.model()
    with torch.no_grad():  # every anchor answers a box 4 strides wide: neighbours overlap with IoU 0.6, as
        for pred in model.head.reg_preds:  # the several boxes a trained model puts on one hand do
            pred.weight.zero_()
            pred.bias.copy_(torch.tensor([0.0, 0.0, math.log(4.0), math.log(4.0)]))
    path = write_aedat4(tmp_path / "davis.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    answers = {}
    for name, nms_iou in (("operating", point.nms_iou), ("coco", EVAL["nms_threshold"])):
        # a model three steps old scores near its prior: a low score keeps many boxes to compare
        stream = StreamingDetector(model, checkpoint.sample, OperatingPoint(score=1e-6, nms_iou=nms_iou))
        run_detect(stream, open_recording(path), Sensor(stub_video["size"]), tmp_path / name, rate_hz=100,
                   video=video_settings(enabled=False), progress=False)
        answers[name] = lines(tmp_path / name)
    assert sum(len(a["boxes"]) for a in answers["operating"]) > 10 * len(answers["operating"]) > 0
    assert sum(map(overlapping_pairs, answers["coco"])) > 100  # COCO's NMS IoU leaves several boxes on a hand
    assert sum(map(overlapping_pairs, answers["operating"])) == 0


def assert_same_detections(answer: dict, expected: dict, k: int, cut: int = 100) -> None:
    """The streamed detections are the batch model's, paired one to one (boxes within 0.02 px, scores
    within 2e-4): scores that tie to float32 rounding may come in either order, and where the list was cut
    at ``cut`` detections, at most three scored as its last may fall on either side of the cut."""
    from scipy.optimize import linear_sum_assignment

    boxes, scores = np.asarray(answer["boxes"]), np.asarray(answer["scores"])
    want_boxes, want_scores = expected["boxes"].numpy(), expected["scores"].numpy()
    cost = np.abs(boxes[:, None] - want_boxes[None]).max(-1) + np.abs(scores[:, None] - want_scores[None])
    rows, cols = linear_sum_assignment(cost)
    close = (np.abs(boxes[rows] - want_boxes[cols]).max(-1) <= 0.02) & (np.abs(scores[rows] - want_scores[cols]) <= 2e-4)
    for values, paired in ((scores, rows[close]), (want_scores, cols[close])):
        unpaired = np.setdiff1d(np.arange(len(values)), paired)
        if len(unpaired):
            assert len(values) == cut and len(unpaired) <= 3, (k, len(values), unpaired)
            np.testing.assert_allclose(values[unpaired], values.min(), rtol=0, atol=2e-4)


def test_detect_on_a_written_aedat4_answers_what_the_batch_model_answers(stub_video, trained_checkpoints, tmp_path):
    ckpt = trained_checkpoints["hybrid"]
    path = write_aedat4(tmp_path / "davis.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    stream = StreamingDetector.from_checkpoint(ckpt, score=CONF, nms_iou=EVAL["nms_threshold"])
    summary = run_detect(stream, open_recording(path), Sensor(stub_video["size"]), tmp_path / "out", rate_hz=1,
                         video=video_settings(enabled=False), progress=False)
    answers = {a["t_us"]: a for a in lines(tmp_path / "out")}
    assert summary["answers"] == len(answers) and summary["events_in"] == len(stub_video["events"]["t"])
    assert summary["warm_up_seconds"] > 0  # made-up input ran first, outside the answers' latencies

    trained = load_checkpoint(ckpt).sample
    dataset = sample_set(stub_video["root"], "test", image_age=1, window_us=trained.window_us,
                         context_us=trained.context_us, refractory_us=trained.refractory_us,
                         support_us=trained.support_us, carry_picture=trained.carry_picture, carry_recent_us=trained.carry_recent_us,
                         carry_confirm_us=trained.carry_confirm_us, carry_align_us=trained.carry_align_us,
                         carry_spans_us=trained.carry_spans_us, carry_onset=trained.carry_onset,
                         videos=[stub_video["video"]])
    model = stream.model
    checked = 0
    for index in range(len(dataset)):
        video, k = dataset.sample_name(index)
        if not 1 <= k < FRAMES:
            continue
        sample = dataset[index]
        with torch.no_grad():
            expected = model(collate([sample]), conf_threshold=CONF, nms_threshold=stream.operating.nms_iou)[0]
        answer = answers[int(sample.t_end_us)]
        assert len(answer["boxes"]) == len(expected["boxes"]) > 0, k
        assert_same_detections(answer, expected, k)
        checked += 1
    assert checked == FRAMES - 1


def test_a_larger_camera_with_a_declared_crop_and_scale_gives_the_same_detections(stub_video, trained_checkpoints,
                                                                                 tmp_path):
    """The stub seen by a 640x480 camera: each event at one of its 2x2 sensor pixels, 60 rows down;
    frames upsampled into the sensor. With ``crop=[0,60,640,360] scale=2`` the detector reads exactly
    the stub, and its boxes come out doubled and shifted by the crop."""
    rng = np.random.default_rng(0)
    events = dict(stub_video["events"])
    events["x"] = 2 * events["x"] + rng.integers(0, 2, len(events["x"]))
    events["y"] = 60 + 2 * events["y"] + rng.integers(0, 2, len(events["y"]))
    frames = []
    for t, image in stub_video["frames"]:
        big = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
        big[60:420] = np.kron(image, np.ones((2, 2, 1), np.uint8))
        frames.append((t, big))
    ckpt = trained_checkpoints["hybrid"]
    small = write_aedat4(tmp_path / "small.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    large = write_aedat4(tmp_path / "large.aedat4", events, (640, 480), frames)
    for name, path, sensor in (("small", small, Sensor(stub_video["size"])),
                               ("large", large, Sensor((640, 480), crop=(0, 60, 640, 360), scale=2))):
        stream = StreamingDetector.from_checkpoint(ckpt, score=CONF, nms_iou=EVAL["nms_threshold"])
        run_detect(stream, open_recording(path), sensor, tmp_path / name, rate_hz=200,
                   video=video_settings(enabled=name == "large", max_seconds=0.1),
                   progress=False)
    small_answers, large_answers = lines(tmp_path / "small"), lines(tmp_path / "large")
    assert [a["t_us"] for a in small_answers] == [a["t_us"] for a in large_answers]
    for a, b in zip(small_answers, large_answers):
        expected = np.asarray(a["boxes"]).reshape(-1, 4) * 2 + [0, 60, 0, 60]
        np.testing.assert_allclose(np.asarray(b["boxes"]).reshape(-1, 4), expected, atol=0.05)
    assert (tmp_path / "large" / "detections.mp4").stat().st_size > 0
    with pytest.raises(SensorError, match=r"the 640x480 sensor gives 640x480.*sensor.scale=2 sensor.crop=\[0,60,640,360\]"):
        run_detect(StreamingDetector.from_checkpoint(ckpt, **EVAL_ANSWER), open_recording(large), Sensor((640, 480)),
                   tmp_path / "refused", rate_hz=100, video=video_settings(), progress=False)
    with pytest.raises(FileExistsError, match="small/summary.json already exists; choose another out="):
        run_detect(StreamingDetector.from_checkpoint(ckpt, **EVAL_ANSWER), open_recording(small), Sensor(stub_video["size"]),
                   tmp_path / "small", rate_hz=100, video=video_settings(), progress=False)


def test_a_hybrid_needs_frames_and_says_so(stub_video, trained_checkpoints, tmp_path):
    path = write_aedat4(tmp_path / "events_only.aedat4", stub_video["events"], stub_video["size"])
    with pytest.raises(ValueError, match="events_only.aedat4: the model is a hybrid and needs frames"):
        run_detect(StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"], **EVAL_ANSWER), open_recording(path),
                   Sensor(stub_video["size"]), tmp_path / "out", rate_hz=100, video=video_settings(), progress=False)


def test_frames_on_another_clock_are_named_not_answered_zero_times(stub_video, trained_checkpoints, tmp_path):
    epoch = 1_700_000_000_000_000  # frame times in Unix-epoch microseconds, events from the camera's 0
    frames = [(t + epoch, image) for t, image in stub_video["frames"]]
    path = write_aedat4(tmp_path / "clocks.aedat4", stub_video["events"], stub_video["size"], frames)
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"], **EVAL_ANSWER)
    t = stub_video["events"]["t"]
    with pytest.raises(ValueError, match=rf"no answer: the first frame is at t={frames[0][0]} us and the events run "
                                         rf"from t={t[0]} to t={t[-1]} us; frames and events must share one clock"):
        run_detect(stream, open_recording(path), Sensor(stub_video["size"]), tmp_path / "out", rate_hz=100,
                   video=video_settings(enabled=False), progress=False)


def test_seconds_limits_the_events_read_inside_a_chunk(stub_video, trained_checkpoints, tmp_path):
    events = stub_video["events"]
    path = tmp_path / "rec.csv"
    path.write_text("t,x,y,on\n" + "".join(f"{t},{x},{y},{p}\n" for t, x, y, p in zip(*(events[k] for k in "txyp"))))
    assert len(list(open_recording(path, size=stub_video["size"]).events())) == 1  # one chunk holds every event
    summary = run_detect(StreamingDetector.from_checkpoint(trained_checkpoints["events_only"]),
                         open_recording(path, size=stub_video["size"]),
                         Sensor(stub_video["size"]), tmp_path / "out", rate_hz=100, seconds=0.05,
                         video=video_settings(enabled=False), progress=False)
    t = stub_video["events"]["t"]
    assert summary["events_in"] == int(np.sum(t <= t[0] + 50_000)) < len(t)
    assert summary["recording_seconds"] <= 0.05


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_a_live_udp_stream_on_loopback_is_read_whole_and_answered(stub_video, trained_checkpoints, tmp_path):
    url = f"udp://127.0.0.1:{free_port()}"
    events = take(stub_video["events"], stub_video["events"]["t"] < 150_000)
    source = UdpSource(url, stub_video["size"], **{**UDP, "idle_s": 1.0, "wait_first_s": 30.0}, seconds=None)
    sent = []

    def sender():
        source.ready.wait(30)
        time.sleep(0.2)
        sent.append(send([events], url, fmt=UDP["fmt"], speed=1.0))

    thread = threading.Thread(target=sender)
    thread.start()
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["events_only"], score=CONF, nms_iou=EVAL["nms_threshold"])
    summary = run_detect(stream, source, Sensor(stub_video["size"]), tmp_path / "live", rate_hz=100, live=True,
                         video=video_settings(enabled=False))
    thread.join()
    assert sent == [len(events["t"])]
    assert summary["udp"]["events"] == summary["events_in"] == len(events["t"])
    assert summary["udp"]["packets_out_of_order"] == 0 and summary["udp"]["late_events_dropped"] == 0
    # How often it answers depends on the machine (a busy detector answers less often, never drops
    # events); what it answered is all written.
    assert summary["answers"] == len(lines(tmp_path / "live")) >= 1
    assert lines(tmp_path / "live")[-1]["t_us"] <= int(events["t"][-1]) + 1  # (answered at the latest event + 1 us)


def test_the_readers_and_sensors_defaults_are_conf_detects():
    """A recording read and a sensor made without settings are what ``python detect.py`` reads by
    default: the one value, held equal here, not two that drift."""
    import dataclasses

    from omegaconf import OmegaConf

    from dagr_lite.camera.recording import ORDER, ORDER_WINDOW_US
    from tests.settings import CONF

    conf = OmegaConf.load(CONF / "detect.yaml")
    assert (conf.order, conf.order_window_us) == (ORDER, ORDER_WINDOW_US)
    defaults = {f.name: f.default for f in dataclasses.fields(Sensor) if f.name != "size"}
    assert defaults == {key: conf.sensor[key] for key in defaults}


def test_a_checkpoint_runs_at_the_sensors_size_with_its_own_weights(trained_checkpoints):
    """``sensor.model_size=sensor``: the same weights, a detector built at the sensor's size."""
    ckpt = trained_checkpoints["events_only"]
    trained = StreamingDetector.from_checkpoint(ckpt, **EVAL_ANSWER)
    at_sensor = StreamingDetector.from_checkpoint(ckpt, model_size=(640, 360), **EVAL_ANSWER)
    assert (at_sensor.width, at_sensor.height) == (640, 360) != (trained.width, trained.height)
    ours, theirs = trained.model.state_dict(), at_sensor.model.state_dict()
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)


@pytest.mark.parametrize("jump_us", [100_000_000, 1_700_000_000_000_000])  # 100 s; to Unix-epoch microseconds
def test_a_clock_that_jumps_is_answered_at_the_jumps_edges_and_reported(trained_checkpoints, jump_us, tmp_path):
    rng = np.random.default_rng(3)
    before = np.sort(rng.integers(0, 200_000, 400))
    after = jump_us + np.sort(rng.integers(0, 200_000, 400))
    t = np.concatenate([before, after])
    rows = "".join(f"{ti},{x},{y},{p}\n" for ti, x, y, p in zip(t, rng.integers(0, 320, len(t)),
                                                                rng.integers(0, 180, len(t)), rng.integers(0, 2, len(t))))
    path = tmp_path / "jump.csv"
    path.write_text("t,x,y,on\n" + rows)
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["events_only"])
    summary = run_detect(stream, open_recording(path, size=(320, 180)), Sensor((320, 180)), tmp_path / "out",
                         rate_hz=100, video=video_settings(enabled=False), progress=False)
    # 0.2 s of events on each side at 100 Hz, and the answers until the events before it left the horizon
    assert summary["answers"] <= 2 * 21 + 5
    assert summary["clock_jumps"] == [{"from_us": float(before[-1]), "to_us": float(after[0])}]
    assert summary["recording_seconds"] == pytest.approx((before[-1] - before[0] + after[-1] - after[0]) / 1e6)
    times = [a["t_us"] for a in lines(tmp_path / "out")]
    assert times == sorted(times) and max(times) >= after[-1] and any(t > before[-1] for t in times)


class _Stopping:
    """A recording whose reading stops after ``chunks`` chunks with ``error``."""

    def __init__(self, recording, chunks: int, error: BaseException):
        self.recording, self.chunks, self.error = recording, chunks, error
        self.path, self.size, self.has_frames = recording.path, recording.size, recording.has_frames

    def frames(self):
        return self.recording.frames()

    def events(self):
        for i, chunk in enumerate(self.recording.events()):
            if i == self.chunks:
                raise self.error
            yield chunk


def written(out) -> dict:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())}


def test_an_interrupted_run_keeps_partial_names_and_a_retry_into_the_same_folder_works(stub_video,
                                                                                       trained_checkpoints, tmp_path):
    path = write_aedat4(tmp_path / "davis.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"])
    out = tmp_path / "out"
    stopped = _Stopping(open_recording(path), 1, KeyboardInterrupt())
    summary = run_detect(stream, stopped, Sensor(stub_video["size"]), out, rate_hz=100, video=video_settings(),
                         progress=False)
    assert summary["finished"] is False and summary["stopped"] == "interrupted (Ctrl-C)"
    assert sorted(written(out)) == ["detections.partial.jsonl", "detections.partial.mp4", "summary.partial.json"]
    assert json.loads((out / "summary.partial.json").read_text())["finished"] is False
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"])
    summary = run_detect(stream, open_recording(path), Sensor(stub_video["size"]), out, rate_hz=100,
                         video=video_settings(), progress=False)  # no overwrite needed: nothing was finished
    assert summary["finished"] is True and summary["video"] == str(out / "detections.mp4")
    assert {"detections.jsonl", "detections.mp4", "summary.json"} <= set(written(out))
    assert json.loads((out / "summary.json").read_text())["finished"] is True


class _Signalled(_Stopping):
    """A recording during whose reading the process gets a SIGTERM."""

    def events(self):
        import os
        import signal

        for i, chunk in enumerate(self.recording.events()):
            if i == self.chunks:
                os.kill(os.getpid(), signal.SIGTERM)
            yield chunk


def test_sigterm_stops_detect_as_ctrl_c_does_leaving_no_temporary_video(stub_video, trained_checkpoints, tmp_path):
    import signal

    path = write_aedat4(tmp_path / "davis.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    out = tmp_path / "out"
    before = signal.getsignal(signal.SIGTERM)
    summary = run_detect(StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"]),
                         _Signalled(open_recording(path), 2, None), Sensor(stub_video["size"]), out, rate_hz=100,
                         video=video_settings(), progress=False)
    assert summary["finished"] is False and summary["stopped"] == "stopped by SIGTERM"
    assert sorted(written(out)) == ["detections.partial.jsonl", "detections.partial.mp4", "summary.partial.json"]
    assert not list(out.glob(".*"))  # no hidden temporary video left
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_failed_run_over_an_earlier_one_leaves_the_earlier_outputs_whole(stub_video, trained_checkpoints,
                                                                           tmp_path):
    path = write_aedat4(tmp_path / "davis.aedat4", stub_video["events"], stub_video["size"], stub_video["frames"])
    out = tmp_path / "out"
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"])
    run_detect(stream, open_recording(path), Sensor(stub_video["size"]), out, rate_hz=100, video=video_settings(),
               progress=False)
    earlier = written(out)
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["hybrid"])
    failing = _Stopping(open_recording(path), 1, OSError("the disk is full"))
    with pytest.raises(OSError, match="the disk is full"):
        run_detect(stream, failing, Sensor(stub_video["size"]), out, rate_hz=100, video=video_settings(),
                   progress=False, overwrite=True)
    now = written(out)
    assert {name: now[name] for name in earlier} == earlier  # summary, answers and video of the earlier run
    assert set(now) - set(earlier) == {"detections.partial.jsonl"}  # no video, no summary of the failed run


def test_an_empty_recording_is_refused_not_answered_zero_times(trained_checkpoints, tmp_path):
    from dagr_lite.errors import UserError

    (tmp_path / "empty.csv").write_text("t,x,y,on\n")
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["events_only"])
    with pytest.raises(UserError, match=r"empty\.csv: the recording holds no events"):
        run_detect(stream, open_recording(tmp_path / "empty.csv", size=(320, 180)), Sensor((320, 180)),
                   tmp_path / "out", rate_hz=100, video=video_settings(enabled=False), progress=False)


def test_events_a_decoder_retimes_are_counted_in_the_summary(trained_checkpoints, tmp_path):
    from tests.camera.test_rawtime import encode

    rng = np.random.default_rng(4)
    t = np.sort(rng.integers(0, 100_000, 2_000))
    t[[100, 101, 102]] = t[[102, 100, 101]]  # one event two places early: the two it skipped are late
    late = int(np.sum(t < np.maximum.accumulate(np.concatenate([[-1], t[:-1]]))))
    path = tmp_path / "rec.dat"
    path.write_bytes(encode("dat", t, rng.integers(0, 64, len(t)), rng.integers(0, 48, len(t)),
                            rng.integers(0, 2, len(t))))
    stream = StreamingDetector.from_checkpoint(trained_checkpoints["events_only"], model_size=(64, 48))
    summary = run_detect(stream, open_recording(path), Sensor((64, 48)), tmp_path / "out", rate_hz=100,
                         video=video_settings(enabled=False), progress=False)
    assert summary["out_of_order_events_retimed"] == late > 0 and summary["events_in"] == len(t)
